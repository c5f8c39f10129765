"""PDDP's training data: dataset step dicts -> fixed-size tensors (``topocut.policies.inputs`` builds the fields).

Batches come from dataset step dicts (docs/contracts.md: x_t, f_t, mask, history, goal, goal_labels, ...) through
``topocut.policies.inputs`` -- the one builder of every learned policy's inputs -- FPS-sampled to ``num_points``
observation and ``num_goal_points`` goal points by PolicyDataset; the mask target is the pose-consistent label of
``topocut.policies.actions``.
"""
from __future__ import annotations

import logging

import numpy as np
import torch

from topocut.policies.config import SAMPLES
from topocut.policies.inputs import goal_inputs, policy_inputs, sample_indices, step_obs, step_targets

log = logging.getLogger(__name__)
WORKER_STRIDE = 1_000_000_007  # workers' seeds ~1e9 apart: far past any worker's access count


def subsample(n_total: int, points, n: int, seed: int) -> np.ndarray:
    """Indices of ``n`` of the points (``topocut.policies.inputs.sample_indices`` with a random FPS start; the
    first ``n_total`` are each point once when there are fewer: ``valid_rows`` marks them)."""
    return sample_indices(np.asarray(points)[:n_total], n, seed, start="random")


class PolicyDataset(torch.utils.data.Dataset):
    """Step dicts (an EpisodeDataset or a list) -> fixed-size tensors for PDDP (``topocut.policies.inputs``).

    Each access draws a fresh FPS start point for the observation (seed from ``seed``, the step, a counter and,
    in a DataLoader worker, the worker's id: each worker counts its own accesses, and without the id workers
    would repeat one another's starts), a mild augmentation; the goal fields are the deterministic ones every
    policy receives (cached per step).  ``mask_label``: the target mask (PolicyTrainConfig.mask_label).  Fields:
    points, labels, valid, history, goal, goal_labels, goal_valid, mask, prev_mask (the plane-from-previous-cut
    floor), has_prev.

    ``sample`` (PolicyTrainConfig.sample): "loader" runs the FPS here, an item at a time on the host (~5 ms an
    item of 2,048 points); "batch" hands over the whole cloud, its per-point targets (cached per step) and the
    drawn start instead, and ``sample_batch`` runs the FPS for the whole batch on its device (PDDPModule's
    ``on_after_batch_transfer``), in float64: the same picks, so the same batches as "loader".  Clouds of
    several sizes, or smaller than ``num_points`` (the loader pads those with random copies), keep "loader".
    """

    def __init__(self, steps, num_points: int = 256, num_goal_points: int = 256, seed: int = 0,
                 indices=None, mask_label: str = "goal_side", board_z: float = 0.05, sample: str = "loader"):
        if sample not in SAMPLES:
            raise ValueError(f"sample={sample!r} is not valid; choose one of {', '.join(SAMPLES)}")
        self.steps, self.num_points, self.num_goal_points = steps, num_points, num_goal_points
        self.indices = np.arange(len(steps)) if indices is None else np.asarray(indices)
        self.seed, self._calls, self.mask_label, self.board_z = seed, 0, mask_label, board_z
        self.sample = sample
        self._goals: dict[int, dict] = {}
        self._targets: dict[int, tuple] = {}  # sample="batch": the whole cloud's mask, prev mask, has_prev
        if sample == "batch":  # one cloud size (a batch stacks them), at least num_points (no padding copies)
            sizes = {len(steps[int(j)]["x_t"]) for j in self.indices}
            if len(sizes) > 1 or min(sizes, default=num_points) < num_points:
                log.info("policy.train.sample=batch: the clouds hold %s points (one size of at least num_points=%d "
                         "is needed), so the FPS runs in the loader", sorted(sizes)[:4], num_points)
                self.sample = "loader"

    def __len__(self):
        return len(self.indices)

    def __getitem__(self, i):
        j = int(self.indices[i])
        s = self.steps[j]
        self._calls += 1
        worker = torch.utils.data.get_worker_info()  # None in the main process: the seeds of num_workers=0
        seed = (self.seed * 1_000_003 + j * 7919 + self._calls + (worker.id * WORKER_STRIDE if worker else 0)) % (2**31)
        obs = step_obs(s)
        if j not in self._goals:
            self._goals[j] = goal_inputs(obs["goal"], obs["goal_labels"], self.num_goal_points)
        if self.sample == "batch":
            return self._whole_cloud(j, s, obs, seed)
        inp = policy_inputs(obs, self.num_points, self.num_goal_points, seed, goal=self._goals[j])
        inp.update(step_targets(s, inp["index"], self.board_z, self.mask_label))
        return to_tensors(inp)

    def _whole_cloud(self, j: int, s: dict, obs: dict, seed: int) -> dict:
        """sample="batch": the cloud and its per-point targets (cached: they do not depend on the sample) with
        the FPS start ``fps`` would draw from ``seed``; ``sample_batch`` takes the points."""
        M = len(obs["points"])
        inp = policy_inputs(obs, self.num_points, self.num_goal_points, seed, index=np.arange(M), goal=self._goals[j])
        if j not in self._targets:
            t = step_targets(s, np.arange(M), self.board_z, self.mask_label)
            self._targets[j] = (torch.as_tensor(t["mask"].astype(np.uint8)),
                                torch.as_tensor(t["prev_mask"].astype(np.uint8)), bool(t["has_prev"]))
        mask, prev, has_prev = self._targets[j]
        out = {"cloud": torch.as_tensor(inp["points"]), "cloud_labels": torch.as_tensor(inp["labels"]),
               "cloud_mask": mask, "cloud_prev": prev, "has_prev": torch.tensor(has_prev),
               "start": torch.tensor(int(np.random.default_rng(seed).integers(M)))}  # fps's start="random"
        for k in ("goal", "goal_labels", "goal_valid"):
            out[k] = torch.as_tensor(np.asarray(inp[k]))
        out["goal_labels"] = out["goal_labels"].long()
        out["history"] = torch.as_tensor(np.asarray(inp["history"], np.float32).reshape(-1))
        return out


def sample_batch(batch: dict, num_points: int) -> dict:
    """A batch of PolicyDataset(sample="batch") items -> the fields of sample="loader" items: the FPS of every
    cloud at once on the batch's device (float64, from each item's drawn start: ``fps``'s picks), its rows'
    points, labels and targets; ``valid`` the first occurrence of each pick; before a first cut ``prev_mask`` the
    majority of the sampled mask, as ``step_targets`` makes it.  A batch without clouds is returned as it is."""
    if "cloud" not in batch:
        return batch
    from topocut.metrics.sampling import fps_torch

    cloud = batch["cloud"]  # B,M,3
    idx = fps_torch(cloud.double(), num_points, start=batch["start"])  # B,N
    out = {k: v for k, v in batch.items() if not (k.startswith("cloud") or k == "start")}
    out["points"] = cloud.gather(1, idx[..., None].expand(-1, -1, 3))  # B,N,3
    out["labels"] = batch["cloud_labels"].long().gather(1, idx)
    out["mask"] = batch["cloud_mask"].long().gather(1, idx)
    earlier = torch.tril(torch.ones(num_points, num_points, dtype=torch.bool, device=idx.device), -1)  # N,N: j < i
    out["valid"] = ~((idx[:, :, None] == idx[:, None, :]) & earlier).any(2)  # B,N: no earlier row took it
    majority = (out["mask"] * out["valid"]).sum(1) > 0.5 * out["valid"].sum(1)  # B
    prev = batch["cloud_prev"].long().gather(1, idx)
    has = batch["has_prev"].bool()[:, None]
    out["prev_mask"] = torch.where(has, prev, majority[:, None].long().expand_as(prev))
    return out


def to_tensors(inp: dict) -> dict:
    """``policy_inputs`` (+ targets) as tensors: history flat (h*7,), ids long, masks bool."""
    out = {}
    for k in ("points", "labels", "valid", "goal", "goal_labels", "goal_valid", "mask", "prev_mask", "has_prev"):
        if k in inp:
            out[k] = torch.as_tensor(np.asarray(inp[k]))
    for k in ("labels", "goal_labels", "mask", "prev_mask"):
        if k in out:
            out[k] = out[k].long()
    out["history"] = torch.as_tensor(np.asarray(inp["history"], np.float32).reshape(-1))
    return out


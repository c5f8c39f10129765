"""PDDP's training data: dataset step dicts -> fixed-size tensors (``topocut.policies.inputs`` builds the fields).

Batches come from dataset step dicts (docs/contracts.md: x_t, f_t, mask, history, goal, goal_labels, ...) through
``topocut.policies.inputs`` -- the one builder of every learned policy's inputs -- FPS-sampled to ``num_points``
observation and ``num_goal_points`` goal points by PolicyDataset; the mask target is the pose-consistent label of
``topocut.policies.actions``.
"""
from __future__ import annotations

import numpy as np
import torch

from topocut.policies.inputs import goal_inputs, policy_inputs, sample_indices, step_obs, step_targets

WORKER_STRIDE = 1_000_000_007  # workers' seeds ~1e9 apart: far past any worker's access count


def subsample(n_total: int, points, n: int, seed: int) -> np.ndarray:
    """Indices of ``n`` of the points (``topocut.policies.inputs.sample_indices`` with a random FPS start; the
    first ``n_total`` are each point once when there are fewer: ``valid_rows`` marks them)."""
    return sample_indices(np.asarray(points)[:n_total], n, seed, start="random")


class PolicyDataset(torch.utils.data.Dataset):
    """Step dicts (an EpisodeDataset or a list) -> fixed-size tensors for PDDP (``topocut.policies.inputs``).

    Each access draws a fresh FPS start point for the observation (seed from ``seed``, the step, a counter and,
    in a DataLoader worker, the worker's id: each worker counts its own accesses, and without the id workers
    would repeat one another's starts), a mild augmentation; the goal fields are the deterministic ones every policy receives (cached per step).
    ``mask_label``: the target mask (PolicyTrainConfig.mask_label).  Fields: points, labels, valid, history, goal,
    goal_labels, goal_valid, mask, prev_mask (the plane-from-previous-cut floor), has_prev.
    """

    def __init__(self, steps, num_points: int = 256, num_goal_points: int = 256, seed: int = 0,
                 indices=None, mask_label: str = "goal_side", board_z: float = 0.05):
        self.steps, self.num_points, self.num_goal_points = steps, num_points, num_goal_points
        self.indices = np.arange(len(steps)) if indices is None else np.asarray(indices)
        self.seed, self._calls, self.mask_label, self.board_z = seed, 0, mask_label, board_z
        self._goals: dict[int, dict] = {}

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
        inp = policy_inputs(obs, self.num_points, self.num_goal_points, seed, goal=self._goals[j])
        inp.update(step_targets(s, inp["index"], self.board_z, self.mask_label))
        return to_tensors(inp)


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


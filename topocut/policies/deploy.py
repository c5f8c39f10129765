"""Deployment of a trained PDDP policy: PDDPPolicy, a ``topocut.policies.base.Policy`` over a PDDPModule or its
checkpoint (with the shim that finds an old checkpoint's perception file in its own artifact store)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from topocut.policies.base import check_obs
from topocut.policies.config import SamplerConfig
from topocut.policies.dataset import to_tensors
from topocut.policies.inputs import policy_inputs
from topocut.policies.module import PDDPModule
from topocut.policies.plane import action_from_mask


def _encoder_overrides(ckpt_path) -> dict:
    """Where a PDDP checkpoint from before ``encoder_arch`` finds its perception checkpoint.

    Such a checkpoint names Φ's file by the absolute path it was trained with (e.g. /tmp/o/checkpoint/perception/
    v001/model.ckpt on the GPU machine). Artifact stores move between machines, so when that path is missing the
    same version is looked up in the store this checkpoint lives in (<root>/checkpoint/pddp/vNNN/model.ckpt →
    <root>/checkpoint/perception/vNNN/model.ckpt); neither there → one error naming both."""
    hp = torch.load(str(ckpt_path), map_location="cpu", weights_only=True).get("hyper_parameters", {})
    recorded = hp.get("encoder_ckpt")
    if hp.get("encoder") != "pretrained" or hp.get("encoder_arch") or not recorded or Path(recorded).is_file():
        return {}
    rel = Path(*Path(recorded).parts[-4:])  # checkpoint/<name>/vNNN/model.ckpt: the store's layout
    here = Path(ckpt_path).parents[3] / rel  # the root of the store holding <root>/checkpoint/pddp/vNNN/model.ckpt
    if here.is_file():
        return {"encoder_ckpt": str(here)}
    raise FileNotFoundError(f"{ckpt_path} was trained on the perception checkpoint {recorded}, which does not exist "
                            f"here, nor does {here} (the same version in this checkpoint's artifact store): copy that "
                            f"checkpoint/perception version beside it")


class PDDPPolicy:
    """topocut.policies.base.Policy backed by a trained PDDPModule (or its checkpoint path).

    act() returns None ("no cut") when no sampled mask within ``retries`` tries splits the points.
    """

    def __init__(self, module_or_ckpt, sampler: str | SamplerConfig = "analytic", steps: int = 32,
                 device: str = "cpu", plane: str = "svm", seed: int = 0, board_z: float = 0.05, retries: int = 3,
                 use_ema: bool = True):
        # a SamplerConfig (the `policy.sampler` group) carries every sampling setting; a predictor name
        # with steps/plane/retries is the short form
        self.scfg = (sampler if isinstance(sampler, SamplerConfig)
                     else SamplerConfig(predictor=sampler, steps=steps, plane=plane, retries=retries)).validate()
        if isinstance(module_or_ckpt, PDDPModule):
            module = module_or_ckpt
        else:
            load = dict(map_location=device, weights_only=True)
            try:
                module = PDDPModule.load_from_checkpoint(str(module_or_ckpt), **load)
            except FileNotFoundError:  # a checkpoint from before encoder_arch whose Φ file is not where it was
                module = PDDPModule.load_from_checkpoint(str(module_or_ckpt), **load,
                                                         **_encoder_overrides(module_or_ckpt))
        self.module = module.to(device).eval()
        self.history_len = int(module.cfg.history_len)  # policy.net.history_len: the engine's observations hold it
        self.device, self.board_z, self.use_ema, self.seed = torch.device(device), board_z, use_ema, int(seed)
        self.generator = torch.Generator(device=self.device).manual_seed(self.seed)
        self.goal, self.goal_labels = None, None
        self.last_mask = None

    def reset(self, goal, seed: int | None = None) -> None:
        from topocut.policies.base import mix_seed

        self.goal = np.asarray(goal.points if hasattr(goal, "points") else goal, np.float32)
        labels = getattr(goal, "labels", None)
        self.goal_labels = None if labels is None else np.asarray(labels)
        if seed is not None:  # an episode's masks do not depend on the episodes sampled before it
            self.generator = torch.Generator(device=self.device).manual_seed(mix_seed(self.seed, seed))

    def act(self, obs: dict):
        obs = check_obs(obs)
        mask, action = self.sample((obs["points"], obs["labels"]), obs["goal"], obs["history"], obs["goal_labels"])
        self.last_mask = mask
        return action

    @staticmethod
    def act_batch(policies: list[PDDPPolicy], observations: list[dict]) -> list:
        """``[p.act(o) for p, o in zip(policies, observations)]`` with one network batch per sampling step.

        ``policies``: one copy per episode (``topocut.episode``'s slots) sharing the module and the sampling
        settings, each with its own goal and generator.  Every episode draws its randomness from its own generator
        in the order and shapes act() does (``topocut.policies.diffusion.rng``), so actions, ``last_mask`` and the
        generators' states afterwards are those of the one-at-a-time calls (up to float rounding of the batched
        network, which can in rare cases tip a sampled label).  Policies that do not share a module and settings
        fall back to act() one by one.
        """
        if len(policies) != len(observations):
            raise ValueError(f"act_batch: {len(policies)} policies for {len(observations)} observations")
        if not policies:
            return []
        lead = policies[0]
        if len({id(p) for p in policies}) < len(policies) or \
                not all(p.module is lead.module and p._settings() == lead._settings() for p in policies):
            # one object twice draws its two actions one after the other; other modules need their own batch
            return [p.act(o) for p, o in zip(policies, observations)]
        obs = [check_obs(o) for o in observations]
        prepared = [p._prepare((o["points"], o["labels"]), o["goal"], o["history"], o["goal_labels"])
                    for p, o in zip(policies, obs)]
        results = PDDPPolicy._sample_many(policies, prepared)
        for p, (mask, _) in zip(policies, results):
            p.last_mask = mask
        return [action for _, action in results]

    def _settings(self) -> tuple:
        """What must agree for policies to share one sampling batch."""
        return self.scfg, self.device, self.board_z, self.use_ema

    def inputs(self, obs: dict, seed: int = 0) -> dict:
        """The world-frame input fields (topocut.policies.inputs.policy_inputs) the network gets for ``obs``."""
        tc = self.module.train_cfg
        return policy_inputs(obs, tc.num_points, tc.num_goal_points, seed, start="random")

    def _batch(self, obs: dict, seed: int):
        inp = self.inputs(obs, seed)
        b = {k: v[None].to(self.device) for k, v in to_tensors(inp).items()}
        b["history"] = b["history"].reshape(1, -1)
        return b, inp["index"]

    def _prepare(self, observation, goal=None, history=None, goal_labels=None) -> dict:
        """sample()'s arguments as an observation dict (goal defaults from reset; history None: no cut yet)."""
        points, labels = observation
        points, labels = np.asarray(points, np.float32), np.asarray(labels).astype(np.int64)
        if goal is None:
            goal, goal_labels = self.goal, (self.goal_labels if goal_labels is None else goal_labels)
        if goal is None:
            raise ValueError("PDDPPolicy.sample needs a goal: pass goal= or call reset(goal) first")
        goal = np.asarray(goal, np.float32)
        history = np.zeros((self.history_len, 7), np.float32) if history is None else history
        return {"points": points, "labels": labels, "goal": goal, "goal_labels": goal_labels, "history": history}

    def sample(self, observation, goal=None, history=None, goal_labels=None):
        """observation (points (n,3), labels (n,)) -> (mask (n,) uint8 over all n points, KnifeAction | None).

        ``goal`` / ``goal_labels`` default to the goal of ``reset`` (labels: all 0 when it had none).  The network
        sees an FPS subset; the mask is spread to the other points from their nearest sampled point.
        """
        return PDDPPolicy._sample_many([self], [self._prepare(observation, goal, history, goal_labels)])[0]

    @staticmethod
    def _sample_many(policies: list[PDDPPolicy], observations: list[dict]) -> list[tuple]:
        """(full mask, action | None) of each policy for its prepared observation (``_prepare``).

        A try draws, from each episode's generator, the FPS seed of its subset and then the sampler's noise; the
        episodes whose mask does not split the points (action None) try again, up to ``retries`` times, batched
        among themselves -- so each generator sees the same draws as act() on that episode alone.
        """
        lead = policies[0]
        cfg, results, pending = lead.scfg, [None] * len(policies), list(range(len(policies)))
        for _ in range(cfg.retries + 1):
            seeds = [int(torch.randint(0, 2**31 - 1, (1,), generator=policies[b].generator, device=lead.device))
                     for b in pending]
            built = [policies[b]._batch(observations[b], seed) for b, seed in zip(pending, seeds)]
            batch = {k: torch.cat([one[k] for one, _ in built]) for k in built[0][0]}  # points B,N,3 ; history B,21 ...
            masks = lead.module.sample_masks(batch, steps=cfg.steps, predictor=cfg.predictor, use_ema=lead.use_ema,
                                             generator=[policies[b].generator for b in pending],
                                             denoise=cfg.denoise, eps=cfg.eps).cpu().numpy()  # B,N
            vertical = lead.module.vertical_planes(cfg.tilt)
            for row, (b, (_, idx)) in enumerate(zip(pending, built)):
                results[b] = _mask_action(observations[b]["points"], idx, masks[row], cfg.plane, lead.board_z,
                                          vertical)
            pending = [b for b in pending if results[b][1] is None]
            if not pending:
                break
        return results


def _mask_action(points, idx, mask, plane: str, board_z: float, vertical: bool = False) -> tuple:
    """(mask over all points, action | None) from the mask sampled on the rows ``idx`` of ``points``: the action
    from the plane fitted to the sampled points (``vertical``: among vertical planes); the other points take the
    label of their nearest sampled one."""
    sub = points[idx]
    action = action_from_mask(sub, mask, plane, board_z=board_z, vertical=vertical)
    if len(points) <= len(idx):  # every point was seen (some twice)
        full = np.zeros(len(points), np.uint8)
        full[idx] = mask
    else:
        from scipy.spatial import cKDTree

        full = mask[cKDTree(sub).query(points)[1]].astype(np.uint8)
    return full, action


"""The Policy protocol used by evaluation and planners, and helpers to build its observation dict.

obs keys: points (n,3), labels (n,), history (h,7) (pose features of the last h cuts, oldest first, zeros before
the first cut; h = the policy's ``history_len`` where it declares one, else HISTORY_LEN = 3), goal (g,3), goal_labels (g,).
"""
from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

# the episode core's history length, seed mixing and reset rule, re-exported for the policies
from topocut.episode import HISTORY_LEN, mix_seed, reset_policy  # noqa: F401
from topocut.sim.action import POSE_FEATURE_DIM, KnifeAction

OBS_KEYS = ("points", "labels", "history", "goal", "goal_labels")


@runtime_checkable
class Policy(Protocol):
    def reset(self, goal, seed: int | None = None) -> None:
        """Start an episode towards ``goal`` (topocut.tasks.Goal).

        A stochastic policy re-seeds its sampler from ``seed`` (the episode's seed) so that an
        episode's actions do not depend on which episodes ran before it in the same process.
        """

    def act(self, obs: dict) -> KnifeAction:
        """The next cut for an observation dict with OBS_KEYS."""


def history_from_actions(actions: list[KnifeAction], board_z: float = 0.05, history_len: int = HISTORY_LEN):
    """(history_len, 7) pose features of the last cuts, oldest first, zero-padded in front."""
    h = np.zeros((history_len, POSE_FEATURE_DIM), np.float32)
    last = list(actions)[-history_len:] if history_len else []
    for k, a in enumerate(last):
        h[history_len - len(last) + k] = a.pose_feature(board_z)
    return h


def make_obs(points, labels, goal, goal_labels=None, history=None) -> dict:
    """Validated observation dict; history None = no previous cut, goal_labels None = all 0."""
    if goal is None:
        raise KeyError(f"make_obs needs a goal point cloud (g,3); a policy observation needs {', '.join(OBS_KEYS)}")
    obs = {"points": points, "labels": labels, "goal": goal,
           "goal_labels": np.zeros(len(np.asarray(goal)), np.int32) if goal_labels is None else goal_labels,
           "history": np.zeros((HISTORY_LEN, POSE_FEATURE_DIM), np.float32) if history is None else history}
    return check_obs(obs)


def check_obs(obs: dict) -> dict:
    """Copy of ``obs`` with numpy arrays of the right dtype; KeyError/ValueError name the bad entry."""
    missing = [k for k in OBS_KEYS if k not in obs]
    if missing:
        raise KeyError(f"observation lacks {', '.join(missing)}; a policy observation needs {', '.join(OBS_KEYS)}")
    out = dict(obs)
    out["points"] = np.asarray(obs["points"], np.float32)
    out["labels"] = np.asarray(obs["labels"]).astype(np.int64)
    out["goal"] = np.asarray(obs["goal"], np.float32)
    out["goal_labels"] = np.asarray(obs["goal_labels"]).astype(np.int64)
    out["history"] = np.asarray(obs["history"], np.float32).reshape(-1, POSE_FEATURE_DIM)
    n = out["points"].shape[0]
    if out["points"].shape != (n, 3) or out["labels"].shape != (n,):
        raise ValueError(f"obs['points'] must be (n,3) and obs['labels'] (n,); got {out['points'].shape}, "
                         f"{out['labels'].shape}")
    if out["goal"].ndim != 2 or out["goal"].shape[1] != 3 or len(out["goal"]) == 0:
        raise ValueError(f"obs['goal'] must be a non-empty (g,3) point cloud; got {out['goal'].shape}")
    return out

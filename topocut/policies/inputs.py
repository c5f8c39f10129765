"""The one place that builds a learned policy's inputs: PDDP, its ablations, DP3 and 3D Diffuser Actor.

Every learned policy (``topocut.policies.registry``) reads the same fields, built here from an observation dict
(``topocut.policies.base.OBS_KEYS``) at deployment or from a dataset step dict in training:

    points (N,3) f32, labels (N,) i64, valid (N,) bool     FPS of the observed points and their cluster ids
    history (h,7) f32                                      pose features of the last cuts, oldest first
    goal (G,3) f32, goal_labels (G,) i64, goal_valid (G,)  GOAL_FIELDS: the goal of the target configuration

The goal fields are the goal cloud (the posed, uncut object) **with its piece labels** (0 = not a goal piece,
i = goal piece i): the labels are where slice, stick and dice differ, so they are what encodes the task.  They
are sampled deterministically (FPS from the point farthest from the centroid), so every policy receives the
very same goal fields for one episode whatever its seed.  Each policy then maps them into its own frame with
the observation (PDDP: the world frame, or centred with ``center_points``; DP3 / 3DDA: object-centred and
scaled, ``object_frame``) and embeds them as its network does: PDDP by the same encoder Φ as the
observation, z_g = Φ(X_g, F_g) with F_g = ``goal_feature(goal_labels)``; DP3 and 3DDA by their point encoders
over (xyz, one-hot label), as they embed the observation.

Training targets (``step_targets``): ``mask``, the policy's pose-consistent label (``topocut.policies.actions``),
and ``prev_mask``, the plane-from-previous-cut floor (the constant majority mask before the first cut).
"""
from __future__ import annotations

import numpy as np

from topocut.metrics.sampling import valid_rows
from topocut.policies.base import HISTORY_LEN, OBS_KEYS
from topocut.policies.config import MASK_LABELS
from topocut.sim.action import POSE_FEATURE_DIM, KnifeAction

INPUT_FIELDS = OBS_KEYS  # what every learned policy reads from an observation
GOAL_FIELDS = ("goal", "goal_labels", "goal_valid")  # handed identically to every learned policy
STARTS = ("random", "farthest")


def goal_feature(goal_labels) -> np.ndarray:
    """F_g, the per-point goal feature Φ embeds with the goal points: the goal's piece labels read as topology
    cluster ids -- 0 the rest of the object, i goal piece i -- i.e. the labelling of the target configuration,
    the same kind of ids as the observation's clusters (0 the uncut object, new ids for new pieces)."""
    return np.asarray(goal_labels).astype(np.int64).reshape(-1)


def sample_indices(points, n: int, seed: int = 0, start: str = "random") -> np.ndarray:
    """Indices of ``n`` of the points: farthest point sampling (``start``: "random" draws the first point from
    ``seed``, "farthest" starts at the point farthest from the centroid and ignores the seed).  A cloud of at
    most ``n`` points gives each point once, then padding copies drawn from ``seed`` (``valid_rows`` marks the
    first row of each point)."""
    if start not in STARTS:
        raise ValueError(f"sample_indices: start={start!r} is not valid; choose one of {', '.join(STARTS)}")
    pts = np.asarray(points)
    n_total = len(pts)
    if n_total == 0:
        raise ValueError("sample_indices: an empty point cloud")
    if n_total <= n:
        rng = np.random.default_rng(seed)
        return np.concatenate([np.arange(n_total), rng.integers(0, n_total, n - n_total)]).astype(np.int64)
    from topocut.metrics import fps  # lazy: the metrics package

    return np.asarray(fps(pts, n, seed=seed, start=start), np.int64)


def goal_inputs(goal, goal_labels, num_goal_points: int) -> dict:
    """GOAL_FIELDS of a goal cloud (world frame), deterministic: the same for every policy and every seed."""
    g = np.asarray(goal, np.float32).reshape(-1, 3)
    lab = np.zeros(len(g), np.int64) if goal_labels is None else goal_feature(goal_labels)
    if len(lab) != len(g):
        raise ValueError(f"goal ({len(g)} points) and goal_labels ({len(lab)}) differ in length")
    gidx = sample_indices(g, num_goal_points, seed=0, start="farthest")
    return {"goal": g[gidx], "goal_labels": lab[gidx], "goal_valid": valid_rows(gidx)}


def policy_inputs(obs: dict, num_points: int, num_goal_points: int, seed: int = 0, start: str = "random",
                  index=None, goal: dict | None = None) -> dict:
    """The input fields (module docstring) of an observation dict with OBS_KEYS, in the world frame (numpy).

    ``index``: observation rows chosen before (a cached FPS); ``goal``: GOAL_FIELDS computed before for this goal
    (``goal_inputs``).  Also returned: ``index`` (the rows taken) and ``center`` (the centroid of all observed
    points, the origin of ``object_frame``)."""
    points = np.asarray(obs["points"], np.float32).reshape(-1, 3)
    labels = np.asarray(obs["labels"]).astype(np.int64).reshape(-1)
    if len(labels) != len(points):
        raise ValueError(f"obs['points'] ({len(points)}) and obs['labels'] ({len(labels)}) differ in length")
    idx = sample_indices(points, num_points, seed, start) if index is None else np.asarray(index, np.int64)
    hist = obs.get("history")
    hist = (np.zeros((HISTORY_LEN, POSE_FEATURE_DIM), np.float32) if hist is None
            else np.array(hist, np.float32).reshape(-1, POSE_FEATURE_DIM))
    out = {"points": points[idx], "labels": labels[idx], "valid": valid_rows(idx), "history": hist,
           "index": idx, "center": points.mean(0).astype(np.float32)}
    out.update(goal if goal is not None else goal_inputs(obs["goal"], obs.get("goal_labels"), num_goal_points))
    return out


def step_obs(step: dict) -> dict:
    """A dataset step dict (docs/contracts.md) read as the observation its policy saw."""
    return {"points": step["x_t"], "labels": step["f_t"], "history": step.get("history"), "goal": step["goal"],
            "goal_labels": step.get("goal_labels")}


def step_action(step: dict) -> KnifeAction:
    a = step["action"]
    return a if isinstance(a, KnifeAction) else KnifeAction.from_vector(a)


def step_targets(step: dict, index, board_z: float = 0.05, mask_label: str = "goal_side") -> dict:
    """Training targets of a dataset step at the observation rows ``index``:

    ``mask``: the step's cut mask as the policy's label -- ``mask_label="goal_side"`` (default) the
    pose-consistent rule of topocut.policies.actions (the stored plane-side mask, complemented where the
    canonical normal points away from the goal frame's reference); ``"plane_side"`` the stored mask as is (the
    labels of checkpoints trained before the rule).  Without a stored mask the action's own mask is used.
    ``prev_mask``: the plane-from-previous-cut floor (same rule), or before the first cut the constant mask of
    the majority class of ``mask``; ``has_prev``: whether a previous cut existed.
    """
    from topocut.policies.actions import action_mask, orient_mask, previous_action
    from topocut.sim.action import cut_mask

    if mask_label not in MASK_LABELS:
        raise ValueError(f"mask_label={mask_label!r} is not valid; choose one of {', '.join(MASK_LABELS)}")
    idx = np.asarray(index, np.int64)
    x = np.asarray(step["x_t"], np.float32).reshape(-1, 3)
    goal, goal_labels = step["goal"], step.get("goal_labels")
    stored = step.get("mask")
    if "action" in step:
        action = step_action(step)
        plane = cut_mask(x, action, board_z) if stored is None else np.asarray(stored).astype(np.uint8)
        mask = orient_mask(plane, action, goal, goal_labels) if mask_label == "goal_side" else plane
    elif stored is not None:  # a mask without its action cannot be oriented: taken as the policy's label
        mask = np.asarray(stored).astype(np.uint8)
    else:
        raise KeyError("a training step needs 'action' (and optionally its stored 'mask')")
    mask = mask[idx].astype(np.int64)
    prev = None
    last = previous_action(step.get("history", np.zeros((HISTORY_LEN, POSE_FEATURE_DIM))), board_z)
    if last is not None:
        prev = (action_mask(x[idx], last, goal, goal_labels, board_z) if mask_label == "goal_side"
                else cut_mask(x[idx], last, board_z))
    has_prev = prev is not None
    if prev is None:
        ones = mask[valid_rows(idx)].mean() if len(idx) else 0.0
        prev = np.full(len(idx), int(ones > 0.5), np.int64)
    return {"mask": mask, "prev_mask": np.asarray(prev, np.int64), "has_prev": np.bool_(has_prev)}



def object_frame(inputs: dict, pos_scale: float = 0.15, board_z: float = 0.05, num_labels: int = 32) -> dict:
    """DP3 / 3DDA's view of ``policy_inputs``: positions (points, goal, history's board points) relative to the
    observation centroid and divided by ``pos_scale``; labels shifted to embedding rows (-1 unassigned -> 0,
    id c -> c + 1, clipped to ``num_labels``), for the observation and the goal alike; the board height."""
    center = np.asarray(inputs["center"], np.float64)
    hist = np.array(inputs["history"], np.float32).reshape(-1, POSE_FEATURE_DIM)
    had = np.abs(hist[:, 3:]).sum(axis=1) > 0  # zero-padded rows (no cut yet) have no quaternion
    hist[had, :3] = (hist[had, :3] - center) / pos_scale

    def lab(a):
        return np.clip(np.asarray(a, np.int64) + 1, 0, num_labels - 1)

    return {"points": ((inputs["points"] - center) / pos_scale).astype(np.float32), "labels": lab(inputs["labels"]),
            "valid": inputs["valid"], "goal": ((inputs["goal"] - center) / pos_scale).astype(np.float32),
            "goal_labels": lab(inputs["goal_labels"]), "goal_valid": inputs["goal_valid"], "history": hist,
            "board": np.float32((board_z - center[2]) / pos_scale), "center": center.astype(np.float32)}

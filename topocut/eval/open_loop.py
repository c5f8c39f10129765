"""Open-loop imitation error: a policy's cut against the demonstrator's on held-out demonstration states
(docs/evaluation.md, "Open loop").

Table 1 runs a policy in closed loop: the states it sees next are made by its own cuts.  Here it sees only the
states of held-out demonstrations and each of its cuts is compared with the demonstrator's cut on that same state:

- ``angle_deg``: the angle between the two cut planes (unsigned normals, 0-90 degrees);
- ``partition_error``: the share of the state's points that the two cuts put on different sides, taking the better
  of the two ways to match the sides (0: the same two parts; a cut that misses the object against one that halves
  it: 0.5);
- ``gap_mm``: how far the policy's plane passes from where the demonstrator cut: the mean distance to the policy's
  plane of the state's points within ``BAND`` of the demonstrator's plane, projected onto it, in mm (1 simulator
  unit = 1 m);
- ``prev_partition_error``: the partition error of the demonstrator's *previous* cut replayed on this state, a
  no-learning floor ("cut where you cut last"), undefined on an episode's first cut.

A policy that is right here and wrong in Table 1 suffers from the states its own cuts make (covariate shift); one
that is wrong here has not learned the demonstrator's cut.  The bootstrap unit is the held-out episode: an
episode's steps in one group are averaged first (``summarize``).
"""
from __future__ import annotations

import math
from collections import defaultdict

import numpy as np

from topocut.eval.stats import bootstrap_mean
from topocut.policies.actions import previous_action
from topocut.policies.base import mix_seed, reset_policy
from topocut.policies.inputs import step_action, step_obs
from topocut.sim.action import KnifeAction, cut_mask, signed_distance_to_plane
from topocut.tasks import Goal

METRICS = ("angle_deg", "partition_error", "gap_mm", "prev_partition_error")
BAND = 0.01  # m: the points that the demonstrator's blade passes through


def normal_angle_deg(a: KnifeAction, b: KnifeAction) -> float:
    """Angle between the planes of two cuts, in degrees (0-90: a plane has no direction)."""
    c = abs(float(np.dot(a.normal, b.normal)))
    return math.degrees(math.acos(min(1.0, c)))


def partition_error(points, a: KnifeAction, b: KnifeAction, board_z: float = 0.05) -> float:
    """Share of ``points`` (N,3) that cuts ``a`` and ``b`` put on different sides, sides matched the better way."""
    ma, mb = cut_mask(points, a, board_z).astype(bool), cut_mask(points, b, board_z).astype(bool)
    differ = float(np.mean(ma != mb))
    return min(differ, 1.0 - differ)


def plane_gap(points, a: KnifeAction, demo: KnifeAction, board_z: float = 0.05, band: float = BAND) -> float:
    """Mean |distance to a's plane| of the ``points`` within ``band`` of ``demo``'s plane, each first projected onto
    that plane (the material the demonstrator's blade cuts through; 0 when the planes agree). NaN if no point is."""
    d = signed_distance_to_plane(points, demo, board_z)  # N,
    near = np.abs(d) <= band
    if not near.any():
        return math.nan
    on_plane = np.asarray(points, np.float64)[near] - d[near, None] * demo.normal  # M,3
    return float(np.mean(np.abs(signed_distance_to_plane(on_plane, a, board_z))))


def cut_bucket(step: int) -> str:
    """The group of an episode's step (0-based): "1", "2", or "3+" (the later cuts together)."""
    return str(step + 1) if step < 2 else "3+"


def open_loop(policy, steps, board_z: float = 0.05, seed: int = 0, progress=None) -> list[dict]:
    """One record per dataset step dict in ``steps``: the policy's cut on the step's state against the step's own.

    ``policy`` follows the Policy protocol; it is reset before each step with the step's goal and a seed of
    (``seed``, episode, step), so a record does not depend on the order of the steps.  ``progress``: an optional
    callable run after each step.
    """
    records = []
    for s in steps:
        obs = step_obs(s)
        # the goal as the dataset keeps it: its cloud and piece labels (no fragments or oracle steps)
        goal = Goal(fragments=[], planes=[], points=obs["goal"], labels=obs["goal_labels"],
                    task=str(s.get("task", "")), object=str(s.get("object", "")))
        episode, k = int(s["episode"]), int(s["step"])
        reset_policy(policy, goal, seed=mix_seed(seed, episode * 101 + k))
        pred, demo = policy.act(obs), step_action(s)
        points = np.asarray(obs["points"], np.float64)  # N,3
        prev = previous_action(obs["history"], board_z) if k > 0 and obs["history"] is not None else None
        rec = {"task": str(s.get("task", "")), "object": str(s.get("object", "")), "episode": episode, "step": k,
               "cut": cut_bucket(k), "stopped": pred is None,
               "angle_deg": math.nan if pred is None else normal_angle_deg(pred, demo),
               "partition_error": _miss(points, demo, board_z) if pred is None
               else partition_error(points, pred, demo, board_z),
               "gap_mm": math.nan if pred is None else 1000.0 * plane_gap(points, pred, demo, board_z),
               "pred": None if pred is None else [float(v) for v in pred.to_vector()],
               "demo": [float(v) for v in demo.to_vector()],
               "prev_partition_error": math.nan if prev is None else partition_error(points, prev, demo, board_z)}
        records.append(rec)
        if progress is not None:
            progress()
    return records


def _miss(points, demo: KnifeAction, board_z: float) -> float:
    """A policy that stops cuts nothing: its error is the share of points on the smaller side of the demo's cut."""
    m = cut_mask(points, demo, board_z).astype(bool)
    return float(min(m.mean(), 1.0 - m.mean()))


def summarize(records: list[dict], by=("task", "cut"), label: str = "") -> list[dict]:
    """Mean [95% bootstrap interval over episodes] of each metric per group of ``by`` (plus "all" for every key),
    an episode's records in a group averaged first.  Rows: the group's keys, n (episodes), and per metric
    ``<metric>``, ``<metric>_lo``, ``<metric>_hi``."""
    groups: dict[tuple, dict[int, list[dict]]] = defaultdict(lambda: defaultdict(list))
    for r in records:
        for key in _keys(r, by):
            groups[key][r["episode"]].append(r)
    rows = []
    for key in sorted(groups, key=lambda k: tuple((v == "all", v) for v in k)):
        per_episode = groups[key]
        row = dict(zip(by, key))
        row["n"] = len(per_episode)
        for m in METRICS:
            vals = [np.nanmean([r[m] for r in rs]) for rs in per_episode.values()
                    if any(np.isfinite(r[m]) for r in rs)]
            iv = bootstrap_mean(vals, label=f"{label}/{m}/{key}")
            row[m], row[m + "_lo"], row[m + "_hi"] = iv.mean, iv.lo, iv.hi
        rows.append(row)
    return rows


def _keys(record: dict, by) -> list[tuple]:
    """Every group a record belongs to: its own values and "all" in each position."""
    keys = [()]
    for b in by:
        keys = [k + (v,) for k in keys for v in (str(record[b]), "all")]
    return keys


def markdown(rows_by_policy: dict[str, list[dict]], by=("task", "cut")) -> str:
    """A table of every policy's rows: mean [interval] of each metric."""
    head = [*by, "policy", "episodes", "angle (deg)", "partition error", "gap (mm)", "previous cut's partition error"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for policy, rows in rows_by_policy.items():
        for r in rows:
            cells = [str(r[b]) for b in by] + [policy, str(r["n"])]
            cells += [_fmt(r, m, 1 if m in ("angle_deg", "gap_mm") else 2) for m in METRICS]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _fmt(row: dict, m: str, digits: int) -> str:
    if not math.isfinite(row[m]):
        return "-"
    if not math.isfinite(row[m + "_lo"]):
        return f"{row[m]:.{digits}f}"
    return f"{row[m]:.{digits}f} [{row[m + '_lo']:.{digits}f}, {row[m + '_hi']:.{digits}f}]"

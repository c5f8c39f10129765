"""Cream writing's scene and scripted primitives: pen moves, the scripted writer, stroke clusters and rewards.

Actions are (dx, dy, b): move the pen by (dx, dy) in a straight line, extruding iff b = 1
(topocut.sim.pen.CreamPen.move).  ``stroke_actions`` turns letter polylines into such actions
(travel with b = 0 to a stroke's start, then its segments with b = 1, split into moves of at most
pen.step).  Clusters are the strokes (by construction: CreamPen bookkeeps a stroke id per
particle); ``stroke_fragments`` groups particles by it, ``cluster_check`` compares that with
topology discovery.  ``letter_rewards`` scores each letter against its own stroke (Hungarian pairing on
R(d), d = d_spec + d_size + the stroke's handedness on the board; the size terms at the pen's particle spacing,
which the strokes and the letters share) and the word by the geometric mean of its letters (``word_score``):
docs/tasks.md#cream-writing.

MPPI over the strokes' shapes is a planner: topocut.planning.stroke_mppi.StrokeMPPI.
"""
from __future__ import annotations

import time

import numpy as np


def _segments(strokes, start):
    """(from, to, b) of every straight move: travel to each stroke's start, then its segments."""
    pos, out = np.asarray(start, np.float64), []
    for poly in strokes:
        poly = np.asarray(poly, np.float64)
        out += [(pos, poly[0], 0.0)] + [(p, q, 1.0) for p, q in zip(poly[:-1], poly[1:])]
        pos = poly[-1]
    return out


def stroke_actions(strokes: list[np.ndarray], start, step: float, splits=None) -> np.ndarray:
    """Actions (T,3) that write ``strokes`` (list of (m,2) polylines) from pen position ``start``.

    Each straight move is split into k = ceil(length / step) equal actions, or ``splits[i]`` for
    move i (so that perturbed copies of a stroke have the same number of actions).
    """
    acts = []
    for i, (a, b, on) in enumerate(_segments(strokes, start)):
        d = b - a
        k = splits[i] if splits is not None else max(1, int(np.ceil(np.linalg.norm(d) / step)))
        acts += [[*(d / k), on]] * k
    return np.asarray(acts, np.float64)


def segment_splits(strokes, start, step: float) -> list[int]:
    return [max(1, int(np.ceil(np.linalg.norm(b - a) / step))) for a, b, _ in _segments(strokes, start)]


def execute(pen, actions: np.ndarray) -> None:
    """Run actions (T,3), or per scene (B,T,3), on the pen; consecutive moves each take their own substeps."""
    actions = np.asarray(actions, np.float64)
    per_scene = actions.ndim == 3
    T = actions.shape[1] if per_scene else len(actions)
    for t in range(T):
        a = actions[:, t] if per_scene else actions[t]
        b = a[..., 2] > 0.5
        if per_scene and not (b == b[0]).all():
            raise ValueError("extrusion b must agree across the batch (the particle count is shared)")
        pen.move(a[..., :2], bool(np.ravel(b)[0]))


def writing_scene(sim, task):
    """(goal clouds per letter, stroke polylines, pen start, draw(x, stroke, path, title)) for task.word."""
    from topocut.sim.render import render_particles
    from topocut.tasks.letters import word_goal

    goals, strokes = word_goal(task.word, task.letter_height, task.letter_gap, sim.spacing, sim.board_z, task.pen)
    allp = np.concatenate(strokes)
    lo, hi = allp.min(0) - 0.02, allp.max(0) + 0.02
    limits = ((lo[0], lo[1], sim.board_z), (hi[0], hi[1], sim.board_z + 0.1))
    start = strokes[0][0] - np.array([0.03, 0.0])

    def draw(x, stroke, path, title):  # top-down, coloured by stroke id (+1: palette colour 0 is grey)
        return render_particles(x, np.asarray(stroke) + 1, path, title=title, view=(75.0, -90.0), size=5,
                                limits=limits, figsize=(7, 4))

    return goals, strokes, start, draw


def stroke_fragments(x: np.ndarray, stroke: np.ndarray, min_points: int = 4) -> tuple[list, list]:
    """Particles (n,3) grouped by stroke id (n,): (fragments, their stroke ids)."""
    ids = [int(s) for s in np.unique(stroke) if (stroke == s).sum() >= min_points]
    return [x[stroke == s] for s in ids], ids


def cluster_check(x: np.ndarray, stroke: np.ndarray, topo_cfg=None, device: str = "cpu") -> dict:
    """Topology discovery on the written cream vs the stroke ids: clusters found and their purity."""
    from topocut.topology import discover

    res = discover(np.asarray(x), np.zeros(len(x), bool), None, cfg=topo_cfg, device=device)
    lab = np.asarray(res.labels)
    pure = 0
    for s in np.unique(stroke):
        vals, cnt = np.unique(lab[stroke == s], return_counts=True)
        pure += cnt.max()
    agree = len(np.unique(stroke)) == res.num_clusters and pure == len(stroke)
    # purity both ways: every stroke inside one cluster and every cluster holding one stroke
    back = sum(np.unique(stroke[lab == c], return_counts=True)[1].max() for c in np.unique(lab))
    return {"strokes": int(len(np.unique(stroke))), "clusters": int(res.num_clusters),
            "stroke_purity": float(pure / max(len(stroke), 1)), "cluster_purity": float(back / max(len(stroke), 1)),
            "agree": bool(agree and back == len(stroke)), "labels": lab}


def letter_distances(fragments, goals, reward_cfg=None, *, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """(F,G) distances of strokes (list of (n,3)) to letters (list of (m,3)) and the handedness part (F,G).

    d = d_spec + d_size (topocut.reward.distance_matrix: what R sees for every task) + reward.handedness_weight x
    handedness (topocut.reward.planar: a mirrored letter is a rigid motion of the letter, which the first two
    terms cannot see; on the board it is not).  inf where a stroke is below reward.min_points.

    ``spacing``: the particle spacing the pen writes at and the letters were laid at (sim.spacing; CreamPen.spacing,
    word_goal's).  The size terms take it rather than estimating it per cloud: a bead is one particle layer, not
    the 3-D lattice the estimate is calibrated on, and its neighbour distances (0.57-0.72 spacings) depend on how
    the stroke runs across the nozzle's pattern, so the estimate differed between a letter and its own stroke
    (the L: 0.569 against 0.619) and so did the volumes N s^3 and the extents they compared.
    """
    from topocut.reward import RewardConfig, distance_matrix, handedness

    cfg = (reward_cfg or RewardConfig()).validate()
    D = distance_matrix(list(fragments), list(goals), cfg, spacing=spacing)
    H = np.zeros_like(D)
    if cfg.handedness_weight > 0:
        for f, g in zip(*np.nonzero(np.isfinite(D))):
            H[f, g] = handedness(fragments[f], goals[g])
    return D + cfg.handedness_weight * H, H


def word_score(per_letter) -> float:
    """The word's total: the geometric mean of its letters' rewards.  A word is read whole: a missing letter, or one
    past R's zero (mirrored, unrecognisable), makes it 0, where a mean would still pay (G-1)/G of it."""
    r = np.asarray(per_letter, np.float64)
    return float(np.exp(np.log(r).mean())) if len(r) and (r > 0).all() else 0.0


def letter_rewards(x, stroke, goals, reward_cfg=None, *, spacing: float) -> dict:
    """Each letter scored against its own stroke (writing, not cutting: no stock, no waste).

    Strokes (particles by stroke id) and letters are paired one-to-one by the Hungarian algorithm on R(d)
    (topocut.reward.match; d: letter_distances, at the particle ``spacing`` both were made at); per_letter[i] =
    R(d) of the stroke paired with letter i, 0 if none is (a missing letter); total = word_score(per_letter).
    Strokes left unpaired (more strokes than letters) are listed in ``extra`` and not charged.
    """
    from topocut.reward import RewardConfig, match, piecewise_reward

    cfg = (reward_cfg or RewardConfig()).validate()
    frags, ids = stroke_fragments(x, stroke)
    G = len(goals)
    D, H = letter_distances(frags, goals, cfg, spacing=spacing) if frags else (np.zeros((0, G)), np.zeros((0, G)))
    pairs = match(D, cfg)
    d, hand, per = np.full(G, np.inf), np.zeros(G), np.zeros(G)
    for f, g in pairs:
        d[g], hand[g], per[g] = D[f, g], H[f, g], piecewise_reward(D[f, g], cfg)
    paired = {f for f, _ in pairs}
    return {"total": word_score(per), "per_letter": per.tolist(), "distance": d.tolist(), "handedness": hand.tolist(),
            "matching": [(ids[f], g) for f, g in pairs], "extra": [ids[f] for f in range(len(frags)) if f not in paired]}


def write_scripted(pen, strokes, goals, reward_cfg=None, on_letter=None) -> dict:
    """Write every stroke with the scripted writer in scene 0's pen; returns rewards and timings."""
    t0 = time.perf_counter()
    for i, poly in enumerate(strokes):
        execute(pen, stroke_actions([poly], pen.pos[0], pen.pen.step))
        if on_letter is not None:
            on_letter(i)
    pen.settle()
    x, stroke = pen.particles()
    out = letter_rewards(x[0], stroke, goals, reward_cfg, spacing=pen.spacing)
    out.update(particles=int(pen.n), substeps=int(pen.env.step_count), seconds=time.perf_counter() - t0)
    return out

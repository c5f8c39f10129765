"""Cream writing's scene and scripted primitives: pen moves, the scripted writer, stroke clusters and rewards.

Actions are (dx, dy, b): move the pen by (dx, dy) in a straight line, extruding iff b = 1
(topocut.sim.pen.CreamPen.move).  ``stroke_actions`` turns letter polylines into such actions
(travel with b = 0 to a stroke's start, then its segments with b = 1, split into moves of at most
pen.step).  Clusters are the strokes (by construction: CreamPen bookkeeps a stroke id per
particle); ``stroke_fragments`` groups particles by it, ``cluster_check`` compares that with
topology discovery.  The reward is topocut.reward.spectral_reward of the strokes against the
letters' goal clouds (Hungarian matching, one goal piece per letter).

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

    goals, strokes = word_goal(task.word, task.letter_height, task.letter_gap, sim.spacing, sim.board_z)
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


def letter_rewards(x, stroke, goals, reward_cfg=None) -> dict:
    """Spectral reward of the strokes against the letters; per_letter[i] = R of the stroke matched to letter i."""
    from topocut.reward import spectral_reward

    frags, ids = stroke_fragments(x, stroke)
    res = spectral_reward(frags, list(goals), reward_cfg)
    d = np.full(len(goals), np.inf)
    for f, g in res.matching:
        d[g] = res.distances[f, g]
    return {"total": float(res.total), "per_letter": [float(r) for r in res.per_goal], "distance": d.tolist(),
            "matching": [(ids[f], g) for f, g in res.matching]}


def write_scripted(pen, strokes, goals, reward_cfg=None, on_letter=None) -> dict:
    """Write every stroke with the scripted writer in scene 0's pen; returns rewards and timings."""
    t0 = time.perf_counter()
    for i, poly in enumerate(strokes):
        execute(pen, stroke_actions([poly], pen.pos[0], pen.pen.step))
        if on_letter is not None:
            on_letter(i)
    pen.settle()
    x, stroke = pen.particles()
    out = letter_rewards(x[0], stroke, goals, reward_cfg)
    out.update(particles=int(pen.n), substeps=int(pen.env.step_count), seconds=time.perf_counter() - t0)
    return out

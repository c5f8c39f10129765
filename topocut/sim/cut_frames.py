"""Frames during a cut, for the episode engine's renders (``run_episodes(..., frames=True, cut_frames=F)``).

``CuttingEnv.cut(actions, record_every=k)`` snapshots every scene of the batch every k substeps (at the ends of
its fused chunks).  The engine asks for about twice the frames it keeps (``record_interval``: the interval follows
the longest cut of the batch, whose travel it computes as ``topocut.sim.pieces.blade_sweep`` does), then keeps
exactly F per scene, evenly spaced over that scene's own budget, the last at its end (``pick_cut_frames``).  A
fixed count makes every cut of a video last as long, and the frame count of a video a function of its cuts alone.
Pure numpy: the engine stays free of Taichi.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np


class CutFrame(NamedTuple):
    """One scene part-way through a cut."""

    substep: int  # substeps of the cut done
    time_s: float  # simulated seconds since the cut started
    x: np.ndarray  # n,3 f32 positions
    damaged: np.ndarray  # n, bool: particles this cut has damaged so far (damage from earlier cuts excluded)
    knife_edge: np.ndarray  # 3, the blade's edge midpoint at that time


def cut_substeps(env, top: float, action) -> int:
    """Substeps ``env.cut`` runs for ``action`` (a canonical KnifeAction) on a scene whose highest particle is at
    ``top``: the travel from knife_clearance above it to the board (blade_sweep's depth along the blade's travel
    direction, or ``sim.cut_substeps``), plus the dwell on the board."""
    cfg = env.cfg
    if cfg.cut_substeps is not None:
        travel = int(cfg.cut_substeps)
    else:
        z_start = action.z_start if action.z_start is not None else top + cfg.knife_clearance + cfg.margin
        depth = max(z_start - cfg.board_z, 0.0) / -float(action.travel[2])
        if action.depth is not None:
            depth = min(max(action.depth, 0.0), depth)
        travel = int(math.ceil(depth / (cfg.knife_speed * env.dt)))
    return travel + cfg.substeps(cfg.dwell_time)


def record_interval(env, tops, actions, frames_per_cut: int) -> int:
    """``record_every`` for a cut of ``actions`` (None: a scene that does not cut) on scenes whose highest
    particles are ``tops``: about 2 x frames_per_cut snapshots over the longest of the cuts."""
    longest = max((cut_substeps(env, top, a.canonical()) for top, a in zip(tops, actions) if a is not None),
                  default=0)
    return max(1, longest // (2 * int(frames_per_cut)))


def pick_cut_frames(snapshots, scene: int, n: int, damage_before, budget: int, frames_per_cut: int,
                    dt: float) -> list[CutFrame]:
    """``frames_per_cut`` CutFrames of scene ``scene`` (its first ``n`` particle rows) from CutInfo.snapshots:
    evenly spaced among the snapshots within its own ``budget`` of substeps (the batch runs the longest scene's,
    frozen after its own), the last one its latest; a snapshot repeats where the cut recorded fewer.
    ``damage_before`` (n,) bool: the scene's damage before the cut, left out of ``damaged``."""
    mine = [s for s in snapshots or [] if s.substep <= budget] or list(snapshots or [])[:1]
    if not mine:
        return []
    before = np.asarray(damage_before, bool)[:n]  # n,
    picked = [mine[math.ceil((j + 1) * len(mine) / frames_per_cut) - 1] for j in range(frames_per_cut)]
    return [CutFrame(int(s.substep), float(s.substep * dt), np.asarray(s.x[scene, :n], np.float32).copy(),  # n,3
                     np.asarray(s.damage[scene, :n], bool) & ~before,  # n,
                     np.asarray(s.knife_edge[scene], np.float64).copy())  # 3,
            for s in picked]

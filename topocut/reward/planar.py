"""In-plane shape on the board: the misfit of two clouds up to a yaw and a shift, and a stroke's handedness.

The spectral and size terms (topocut.reward.spectral, .size) are invariant to every rigid motion, and a
planar letter's mirror image *is* a rigid motion of it (turn it over), so they cannot tell R from its mirror.
On the board the normal is fixed (z up, the cream cannot lie upside down), so a letter may be moved and turned
about z only: a proper in-plane rotation.

``planar_misfit(x, y)``: the clouds projected on the board (x, y), each centred on its centroid; the RMS of the
nearest-neighbour distances both ways (x to y and y to x, averaged) at the best yaw of x, divided by y's RMS
radius.  The yaw is searched on a grid of ``YAW_STEPS`` angles and refined around the best one (±half a step,
``REFINE`` angles).  The RMS rather than the mean: a misplaced part (a bowl on the wrong side) sits a large
distance away and counts more than the bead's particle-level noise spread over the whole letter.

``handedness(x, y) = max(0, misfit(x, y) - misfit(mirror x, y))``: how much closer x comes to y's mirror
image than to y itself.  Zero for a stroke that fits its letter better than the letter's mirror image; for a
letter with a mirror axis (O, or C: its mirror image is itself turned 180°) the two misfits are equal and the
term is zero up to noise.  docs/reward.md#handedness; the writing task adds reward.handedness_weight times it to
a stroke's distance to its letter (topocut.tasks.writing_scene.letter_distances).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

YAW_STEPS = 72  # 5° grid over the full turn
REFINE = 11  # angles across ±half a grid step around the best (0.5° apart)
MIRROR = np.diag([-1.0, 1.0])  # any reflection will do: with every rotation it spans all improper motions


def _rotations(angles: np.ndarray) -> np.ndarray:
    """K,2,2 rotation matrices."""
    c, s = np.cos(angles), np.sin(angles)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def _best_yaw(x: np.ndarray, y: np.ndarray, angles: np.ndarray) -> tuple[float, float]:
    """(least mean squared NN distance over angles, its angle) of R x against y; x (n,2), y (m,2), centred."""
    tx, ty = cKDTree(x), cKDTree(y)
    R = _rotations(angles)  # K,2,2
    xr = np.einsum("kab,nb->kna", R, x)  # K,n,2: R x
    yr = np.einsum("kba,mb->kma", R, y)  # K,m,2: R^T y (|R x - y| = |x - R^T y|)
    dxy = ty.query(xr.reshape(-1, 2))[0].reshape(len(angles), -1)  # K,n
    dyx = tx.query(yr.reshape(-1, 2))[0].reshape(len(angles), -1)  # K,m
    msq = 0.5 * ((dxy ** 2).mean(1) + (dyx ** 2).mean(1))  # K
    k = int(np.argmin(msq))
    return float(msq[k]), float(angles[k])


def _board(points, name: str) -> np.ndarray:
    p = np.asarray(points, np.float64)
    if p.ndim != 2 or p.shape[1] not in (2, 3) or not len(p):
        raise ValueError(f"{name}: expected a non-empty (N,2) or (N,3) cloud, got shape {p.shape}")
    p = p[:, :2]  # N,2 on the board
    return p - p.mean(0)


def planar_misfit(x, y, mirror: bool = False) -> float:
    """RMS nearest-neighbour distance of x to y on the board at x's best yaw (and shift: centroids), over y's RMS
    radius; x (n,2|3), y (m,2|3).  ``mirror``: x reflected first (module docstring)."""
    xb, yb = _board(x, "x"), _board(y, "y")
    if mirror:
        xb = xb @ MIRROR.T
    radius = float(np.sqrt((yb ** 2).sum(1).mean()))
    if not radius > 0:
        raise ValueError("y: all points coincide on the board (no radius to measure the misfit against)")
    step = 2 * np.pi / YAW_STEPS
    _, yaw = _best_yaw(xb, yb, np.arange(YAW_STEPS) * step)
    msq, _ = _best_yaw(xb, yb, yaw + np.linspace(-step / 2, step / 2, REFINE))
    return float(np.sqrt(msq) / radius)


def handedness(x, y) -> float:
    """max(0, misfit(x, y) - misfit(mirror x, y)): how much better x fits y's mirror image than y (>= 0)."""
    return max(0.0, planar_misfit(x, y) - planar_misfit(x, y, mirror=True))

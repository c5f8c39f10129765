"""Farthest point sampling (FPS), numpy and batched torch.

Both start from the point farthest from the centroid, a choice that commutes
with rotation, translation and permutation of the input: FPS of a moved or
reordered cloud selects the moved / reordered copies of the same points (up to
exact distance ties).  The spectral reward relies on this so that resampling a
fragment to a fixed size does not break its pose invariance.
"""
from __future__ import annotations

import numpy as np

STARTS = ("farthest", "random")


def _check(n: int, N: int) -> None:
    if n < 1 or n > N:
        raise ValueError(f"fps: n={n} must be in [1, {N}] (the number of input points)")


def fps(points, n: int, seed: int = 0, start: str = "farthest") -> np.ndarray:
    """Indices (n,) of ``n`` farthest-point samples of points (N,3); O(nN) time, O(N) memory.

    start="farthest" (default) begins at the point farthest from the centroid and
    is deterministic (``seed`` unused); start="random" begins at a point drawn
    with ``np.random.default_rng(seed)``.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(len(points), -1)  # N,D
    N = len(pts)
    _check(int(n), N)
    if start == "farthest":
        first = int(np.argmax(((pts - pts.mean(0)) ** 2).sum(1)))
    elif start == "random":
        first = int(np.random.default_rng(seed).integers(N))
    else:
        raise ValueError(f"fps: unknown start={start!r}; valid: {', '.join(STARTS)}")
    idx = np.empty(int(n), dtype=np.int64)
    idx[0] = first
    cols = [np.ascontiguousarray(pts[:, d]) for d in range(pts.shape[1])]  # D x (N,): fast 1-D passes
    dist = np.full(N, np.inf)  # squared distance to the chosen set
    tmp, acc = np.empty(N), np.empty(N)
    cur = first
    for i in range(int(n)):
        idx[i] = cur
        acc.fill(0.0)
        for c in cols:
            np.subtract(c, c[cur], out=tmp)
            np.multiply(tmp, tmp, out=tmp)
            acc += tmp
        np.minimum(dist, acc, out=dist)
        cur = int(np.argmax(dist))
    return idx


def fps_torch(points, n: int):
    """Batched FPS: points (B,N,3) torch tensor -> indices (B,n) long, same start rule as ``fps``."""
    import torch

    if points.dim() != 3:
        raise ValueError(f"fps_torch expects (B,N,3) points, got shape {tuple(points.shape)}")
    B, N, _ = points.shape
    _check(int(n), N)
    with torch.no_grad():
        p = points.detach()
        ar = torch.arange(B, device=p.device)
        idx = torch.empty(B, int(n), dtype=torch.long, device=p.device)
        cur = ((p - p.mean(1, keepdim=True)) ** 2).sum(-1).argmax(1)  # B,
        dist = torch.full((B, N), float("inf"), dtype=p.dtype, device=p.device)
        for i in range(int(n)):
            idx[:, i] = cur
            d = ((p - p[ar, cur][:, None, :]) ** 2).sum(-1)  # B,N
            dist = torch.minimum(dist, d)
            cur = dist.argmax(1)
    return idx


def valid_rows(idx) -> np.ndarray:
    """True on the first occurrence of each index in ``idx`` (N,): padding copies of a point, added when a
    cloud has fewer points than asked for, are False so that losses, metrics and attention count it once."""
    idx = np.asarray(idx)
    first = np.zeros(len(idx), bool)
    first[np.unique(idx, return_index=True)[1]] = True
    return first

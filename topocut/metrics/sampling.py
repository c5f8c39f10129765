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


def fps_torch(points, n: int, mask=None, start=None, method: str = "kernel"):
    """Batched FPS: points (B,N,3) tensor -> indices (B,n) long into N, same start rule as ``fps``.

    start (B,) long: each cloud's first pick (``fps``'s start="random" draws it as
    ``np.random.default_rng(seed).integers(N)``); None: the farthest-from-centroid rule below.

    mask (B,N) bool marks each cloud's valid points (None: all valid), so clouds of different sizes can be
    padded into one batch; invalid points are never selected and their coordinates are ignored.  The start
    is the valid point farthest from the valid points' centroid, and the distances use ``fps``'s float
    operations in its order, so in float64 row b equals ``fps(points[b][mask[b]], n)`` mapped back to
    padded indices (an exact tie in the start's centroid distance may break the other way: the centroid is
    summed in another order).  A cloud with m < n valid points gets its m FPS picks (all of its points when
    they are distinct) followed by n - m copies of its last pick; ``valid_rows`` flags the copies.

    method "kernel" (default): every pick of every cloud in one Warp launch (``topocut.metrics.fps_kernel``), the same
    picks bit for bit as "loop": a few tensor operations a pick, the definition (and ~8 kernel launches a pick).
    """
    import torch

    if points.dim() != 3:
        raise ValueError(f"fps_torch expects (B,N,3) points, got shape {tuple(points.shape)}")
    if method not in ("kernel", "loop"):
        raise ValueError(f"fps_torch: method={method!r}; valid: kernel, loop")
    B, N, _ = points.shape
    n = int(n)
    if mask is None:
        _check(n, N)
    elif n < 1:
        raise ValueError(f"fps: n={n} must be >= 1")
    with torch.no_grad():
        p = points.detach()
        if mask is None:
            count = None
        else:
            mask = torch.as_tensor(mask, dtype=torch.bool, device=p.device)
            if mask.shape != (B, N):
                raise ValueError(f"fps_torch: mask shape {tuple(mask.shape)} must be (B,N) = {(B, N)}")
            count = mask.sum(1)  # B,
            if B and int(count.min()) == 0:  # one sync per call: a cloud without points has no start
                raise ValueError("fps_torch: a cloud has no valid point (mask row all False)")
            p = torch.where(mask[..., None], p, torch.zeros((), dtype=p.dtype, device=p.device))  # NaN-proof padding
        ar = torch.arange(B, device=p.device)
        # both layouts give (dx^2 + dy^2) + dz^2, bit for bit as fps accumulates it (B,3 -> B,N)
        if p.is_cuda:  # launch-bound: 4 kernels per pick on the interleaved B,N,3 layout
            def sqdist(c):
                diff = p - c[:, None, :]  # B,N,3
                diff.mul_(diff)
                d = diff[..., 0] + diff[..., 1]
                d += diff[..., 2]
                return d
        else:  # on the CPU contiguous columns vectorise: about 2x faster than strided slices
            x, y, z = (p[..., d].contiguous() for d in range(3))  # 3 x (B,N)

            def sqdist(c):
                dx, dy, dz = x - c[:, :1], y - c[:, 1:2], z - c[:, 2:]
                d = dx * dx
                d += dy * dy
                d += dz * dz
                return d

        if mask is None:
            d0 = sqdist(p.mean(1)) if start is None else None  # B,N distances to the centroid
            dist = torch.full((B, N), float("inf"), dtype=p.dtype, device=p.device)
        else:
            centroid = p.sum(1) / count[:, None].to(p.dtype)  # padding is zero
            neg = torch.tensor(float("-inf"), dtype=p.dtype, device=p.device)
            d0 = torch.where(mask, sqdist(centroid), neg) if start is None else None
            # -inf on padding: torch.minimum keeps it, so argmax never returns an invalid point
            dist = torch.where(mask, torch.tensor(float("inf"), dtype=p.dtype, device=p.device), neg)
        if start is None:
            cur = d0.argmax(1)  # B, first maximum, as np.argmax
        else:
            cur = torch.as_tensor(start, dtype=torch.long, device=p.device).reshape(B).clone()
        if method == "kernel" and p.dtype in (torch.float32, torch.float64):  # one launch: the loop's picks
            from topocut.metrics.fps_kernel import fps_picks

            top = N if mask is None else torch.where(mask, torch.arange(N, device=p.device), -1).amax(1) + 1  # B,
            top = torch.as_tensor(top, device=p.device).expand(B).to(torch.int32).contiguous()
            idx = fps_picks(p.contiguous(), dist.contiguous(), top, cur.contiguous(), n)
        else:
            picks = []
            for _ in range(n):
                picks.append(cur)
                torch.minimum(dist, sqdist(p[ar, cur]), out=dist)
                cur = dist.argmax(1)
            idx = torch.stack(picks, 1) if picks else torch.empty(B, 0, dtype=torch.long, device=p.device)  # B,n
        if count is not None and n > 1:
            # past its m valid points a cloud would go on picking (zero-distance) points again: repeat pick m-1
            last = idx.gather(1, (count.clamp_max(n) - 1)[:, None])  # B,1
            idx = torch.where(torch.arange(n, device=p.device)[None] < count[:, None], idx, last)
    return idx


def fps_clouds(clouds, n: int, device: str = "cpu") -> list[np.ndarray]:
    """``fps(c, min(n, len(c)))`` of each cloud of ``clouds`` ((N_i,3) arrays, start "farthest"): the same picks
    bit for bit.  On a CUDA ``device`` every cloud's picks are one launch (``fps_torch``'s kernel on the clouds
    padded into one float64 batch, each start found on the host as ``fps`` finds it: a centroid summed on the
    device could break an exact tie the other way); elsewhere ``fps`` cloud by cloud.  The evaluation's
    observations (eval.observation=particles): 16 scenes of 69k particles to 2,048 points each, ~0.5 s a scene on
    one host core."""
    pts = [np.asarray(c, np.float64).reshape(-1, 3) for c in clouds]  # N_i,3
    if not str(device).startswith("cuda") or len(pts) == 0:
        return [np.asarray(fps(c, min(int(n), len(c))), np.int64) for c in pts]
    return _fps_padded(pts, n, device)


def _fps_padded(pts: list, n: int, device) -> list[np.ndarray]:
    """fps_clouds' one launch (any device: the tests run it on the CPU against ``fps``)."""
    import torch

    for c in pts:
        _check(1, len(c))
    counts = np.array([len(c) for c in pts])
    B, N, m = len(pts), int(counts.max()), int(min(int(n), counts.max()))
    padded = np.zeros((B, N, 3), np.float64)
    for b, c in enumerate(pts):
        padded[b, :len(c)] = c
    start = [int(np.argmax(((c - c.mean(0)) ** 2).sum(1))) for c in pts]  # fps's start, its float operations
    mask = torch.as_tensor(np.arange(N)[None] < counts[:, None], device=device)  # B,N
    idx = fps_torch(torch.as_tensor(padded, device=device), m, mask=mask, start=torch.as_tensor(start)).cpu().numpy()
    return [idx[b, :min(int(n), int(counts[b]))] for b in range(B)]


def valid_rows(idx) -> np.ndarray:
    """True on the first occurrence of each index in ``idx`` (N,): padding copies of a point, added when a
    cloud has fewer points than asked for, are False so that losses, metrics and attention count it once."""
    idx = np.asarray(idx)
    first = np.zeros(len(idx), bool)
    first[np.unique(idx, return_index=True)[1]] = True
    return first

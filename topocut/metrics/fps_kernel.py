"""Batched farthest point sampling as one Warp kernel: every pick of every cloud in a single launch.

``fps_torch``'s pick loop is ~8 small tensor kernels a pick (distances to the last pick, the running minimum, the
argmax): 512 picks of the reward's ~50 fragments cost 26-78 ms on an H200 even replayed from a captured CUDA graph,
four times a demonstration cut.  Here one block of threads owns one cloud and runs all n picks:

  each thread    walks its points j = lane, lane + block_dim, ... < top[b]: the squared distance to the last pick,
                 (dx^2 + dy^2) + dz^2 in the cloud's dtype, into the running minimum dist[b, j], and keeps its own
                 largest value at its first index
  the block      the largest value (a tile max), then the smallest index holding it (a tile min over the threads
                 that hold it): torch.argmax's and numpy.argmax's first maximum, whatever the reduction order

Compiled with ``fuse_fp`` off (no fused multiply-adds), so every distance is rounded as the torch loop and numpy's
``fps`` round it and the picks are theirs bit for bit, lattice ties included (tests/test_reward_batched.py).  Points
past ``top[b]`` (the last valid one + 1) are never read: they are padding at -inf, which argmax never picks while
a valid point exists.  Runs on the CPU too, where Warp gives a block one thread: a cloud's points in turn.
"""
from __future__ import annotations

import warp as wp

from topocut.topology.sdf import init_warp

BLOCK_DIM = 1024  # threads a cloud: the largest cloud's block bounds a call (docs/benchmarks.md "The thirty-second session")


def _make(dtype):
    @wp.kernel(enable_backward=False, module="unique", module_options={"fuse_fp": False})
    def picks(p: wp.array3d(dtype=dtype), dist: wp.array2d(dtype=dtype), top: wp.array(dtype=wp.int32),
              start: wp.array(dtype=wp.int64), n: int, idx: wp.array2d(dtype=wp.int64)):
        b, lane = wp.tid()
        step = wp.block_dim()
        hi = top[b]
        cur = int(start[b])
        for k in range(n):
            if lane == 0:
                idx[b, k] = wp.int64(cur)
            cx = p[b, cur, 0]
            cy = p[b, cur, 1]
            cz = p[b, cur, 2]
            best = dtype(-wp.inf)
            arg = hi
            for j in range(lane, hi, step):
                dx = p[b, j, 0] - cx
                dy = p[b, j, 1] - cy
                dz = p[b, j, 2] - cz
                d = dx * dx + dy * dy
                d = d + dz * dz
                dj = dist[b, j]
                if d < dj:  # torch.minimum / np.minimum (no NaN here: padding is zeros, the points are finite)
                    dj = d
                    dist[b, j] = d
                if dj > best:  # strict: a thread keeps the first index of its maximum
                    best = dj
                    arg = j
            top_value = wp.tile_max(wp.tile(best))[0]
            mine = hi
            if best == top_value:
                mine = arg
            cur = wp.tile_min(wp.tile(mine))[0]  # the first index of the block's maximum

    return picks


_KERNELS: dict = {}


def fps_picks(p, dist, top, start, n: int, block_dim: int | None = None):
    """The n picks (B,n) long of every cloud of p (B,N,3), float32 or float64, contiguous: dist (B,N) the running
    squared distances (inf on valid points, -inf on padding; updated in place), top (B,) int32 the last valid index
    + 1, start (B,) long the first picks; block_dim threads a cloud (None: ``BLOCK_DIM``).  On p's device, on torch's
    current stream."""
    import torch

    init_warp()
    dtype = {torch.float64: wp.float64, torch.float32: wp.float32}[p.dtype]
    if dtype not in _KERNELS:
        _KERNELS[dtype] = _make(dtype)
    block_dim = int(block_dim or BLOCK_DIM)
    B = p.shape[0]
    idx = torch.empty(B, n, dtype=torch.long, device=p.device)
    if B == 0 or n == 0:
        return idx
    args = [wp.from_torch(p), wp.from_torch(dist), wp.from_torch(top), wp.from_torch(start), int(n), wp.from_torch(idx)]
    if p.is_cuda:
        wp.launch_tiled(_KERNELS[dtype], dim=[B], inputs=args, block_dim=block_dim,
                        stream=wp.stream_from_torch(torch.cuda.current_stream(p.device)))
    else:
        wp.launch_tiled(_KERNELS[dtype], dim=[B], inputs=args, block_dim=block_dim, device="cpu")
    return idx

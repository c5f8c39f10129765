"""The reward's neighbour queries over cell lists as Warp kernels: one thread a query, its 27 cells walked in place.

``topocut.reward.size_batch.near`` sorts each fragment's reference particles into cells of side h[fragment] and, for
every query, reads the 27 cells around it.  Its tensor path gathers every candidate into a (rows, 27 x fullest cell)
block of float64 distances and reduces it (topk, a count, a min): at 128^3 ~10^8 distances a reward call, in
chunks.  Here each query's thread walks its cells and keeps only what the reduction needs, in registers (the size
descriptors of a 128^3 cut's 32 fragments: 64.6 -> 46.3 ms on an H200, docs/benchmarks.md):

  knn    the k smallest distances, ascending (an insertion list; inf where fewer than k candidates)
  count  how many candidates lie within radius[fragment], less one (the query itself is one of them)
  min    the smallest distance

Distances are sqrt((dx^2 + dy^2) + dz^2) in float64 without fused multiply-adds; the tensor path sums the three
squares in torch's order, so the two agree to rounding (tests/test_reward_size_batch.py).  The cells themselves
(sort, counts, starts, each query's cell) are built by ``near`` with tensor operations, shared by both paths.
"""
from __future__ import annotations

import warp as wp

from topocut.topology.sdf import init_warp

MODES = ("knn", "count", "min")
MAX_K = 8  # the knn list lives in registers


@wp.func
def _cell_of(f: wp.int64, cq: wp.array2d(dtype=wp.int64), i: int, a: int, b: int, c: int,
             base: wp.array(dtype=wp.int64), stride: wp.array2d(dtype=wp.int64)):
    return (base[f] + (cq[i, 0] + wp.int64(a)) * stride[f, 0] + (cq[i, 1] + wp.int64(b)) * stride[f, 1]
            + (cq[i, 2] + wp.int64(c)) * stride[f, 2])


@wp.func
def _distance(X: wp.array2d(dtype=wp.float64), r: wp.int64, x: wp.float64, y: wp.float64, z: wp.float64):
    dx = X[r, 0] - x
    dy = X[r, 1] - y
    dz = X[r, 2] - z
    d = dx * dx + dy * dy
    d = d + dz * dz
    return wp.sqrt(d)


def _make(mode: str, k: int):
    vec = wp.types.vector(length=k, dtype=wp.float64)

    @wp.kernel(enable_backward=False, module="unique", module_options={"fuse_fp": False})
    def walk(X: wp.array2d(dtype=wp.float64), q: wp.array(dtype=wp.int64), qseg: wp.array(dtype=wp.int64),
             cq: wp.array2d(dtype=wp.int64), inside: wp.array(dtype=wp.bool), base: wp.array(dtype=wp.int64),
             stride: wp.array2d(dtype=wp.int64), start: wp.array(dtype=wp.int64), count: wp.array(dtype=wp.int64),
             ref: wp.array(dtype=wp.int64), radius: wp.array(dtype=wp.float64), out: wp.array2d(dtype=wp.float64)):
        i = wp.tid()
        f = qseg[i]
        inf = wp.float64(wp.inf)
        best = vec()
        for j in range(k):
            best[j] = inf
        hits = wp.float64(-1.0)  # the query itself is within every radius
        if inside[i]:
            x = X[q[i], 0]
            y = X[q[i], 1]
            z = X[q[i], 2]
            for a in range(-1, 2):
                for b in range(-1, 2):
                    for c in range(-1, 2):
                        cell = _cell_of(f, cq, i, a, b, c, base, stride)
                        s0 = int(start[cell])
                        for t in range(s0, s0 + int(count[cell])):
                            d = _distance(X, ref[t], x, y, z)
                            if wp.static(mode == "count"):
                                if d <= radius[f]:
                                    hits += wp.float64(1.0)
                            elif d < best[k - 1]:  # insert, keeping best ascending
                                j = k - 1
                                while j > 0 and best[j - 1] > d:
                                    best[j] = best[j - 1]
                                    j -= 1
                                best[j] = d
        if wp.static(mode == "count"):
            out[i, 0] = hits
        else:
            for j in range(k):
                out[i, j] = best[j]

    return walk


_KERNELS: dict = {}


def walk_cells(mode: str, k: int, X, q, qseg, cq, inside, base, stride, start, count, ref, radius):
    """(Q, k) for knn, (Q, 1) for count and min: every query's reduction over the references in its 27 cells.  X (P,3)
    float64; q, qseg (Q,) long; cq (Q,3) long its cell (padded coordinates); inside (Q,) bool (else all inf, or -1
    for count); base (F,), stride (F,3), start and count (cells,), ref (n,) long: ``near``'s cell lists; radius (F,)
    float64 for count.  On X's device, on torch's current stream."""
    import torch

    if mode not in MODES:
        raise ValueError(f"walk_cells: mode={mode!r}; valid: {', '.join(MODES)}")
    k = k if mode == "knn" else 1
    if not 1 <= k <= MAX_K:
        raise ValueError(f"walk_cells: k={k}; valid: 1..{MAX_K}")
    init_warp()
    key = ("knn" if mode == "min" else mode, k)
    if key not in _KERNELS:
        _KERNELS[key] = _make(*key)
    Q = len(q)
    out = X.new_empty(Q, k)
    if Q == 0:
        return out
    if radius is None:
        radius = X.new_zeros(len(base))
    args = [wp.from_torch(t.contiguous()) for t in (X, q, qseg, cq, inside, base, stride, start, count, ref, radius)]
    args.append(wp.from_torch(out))
    if X.is_cuda:
        wp.launch(_KERNELS[key], dim=Q, inputs=args, stream=wp.stream_from_torch(torch.cuda.current_stream(X.device)))
    else:
        wp.launch(_KERNELS[key], dim=Q, inputs=args, device="cpu")
    return out

"""Particle spacing and particle SDF on a regular grid (Warp kernels, CPU or CUDA).

SDF(x) = min_p |x - x_p| - r_p is computed by *splatting*: every particle
visits the grid nodes within r_p + band of itself and lowers them with an
atomic min.  Cost is O(particles x band^3), never O(particles x voxels); nodes
farther than the band keep the clamp value `band` (positive = outside), which
is all marching cubes and the inside/outside labelling need.

The particle spacing (median distance to the 3rd nearest neighbour) is found
on the device too: a hash-grid query per sampled particle keeps its 4 nearest
points (itself included, as cKDTree's k=4 does) and a radix sort gives the
median.  The grid's size depends on it, so its one value is read back.
"""
# ruff: noqa: UP018  (int(0), float(...) declare mutable Warp kernel variables; a bare literal is a constant)
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

_READY = False
SPACING_SAMPLES = 20000  # particles whose neighbour distance enters the median


def init_warp() -> None:
    """wp.init() once, quietly."""
    global _READY
    if not _READY:
        wp.config.quiet = True  # no module-load lines
        if hasattr(wp, "LOG_WARNING"):  # Warp >= 1.12: also drop the init banner, keep warnings
            wp.config.log_level = wp.LOG_WARNING
        wp.init()
        _READY = True


def resolve_device(device: str | None) -> str:
    """"cpu", "cuda", "cuda:N"; None or "auto" -> "cuda" when Warp sees a GPU, else "cpu"."""
    init_warp()
    if device in (None, "auto"):
        return "cuda" if wp.get_cuda_device_count() > 0 else "cpu"
    if not (device == "cpu" or str(device).startswith("cuda")):
        raise ValueError(f"topology device {device!r} unknown; valid: cpu, cuda, cuda:N, auto")
    return str(device)


@dataclass
class Grid:
    """Regular grid: node (i, j, k) sits at lower + (i, j, k) * h; flat index (i * ny + j) * nz + k."""

    lower: np.ndarray  # 3,
    h: float
    shape: tuple  # (nx, ny, nz)

    @property
    def upper(self) -> np.ndarray:  # 3,
        return self.lower + (np.asarray(self.shape) - 1) * self.h

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    @property
    def wp_lower(self):
        return wp.vec3(*np.asarray(self.lower, np.float32))

    def nodes_of(self, points) -> np.ndarray:  # N,3 int: nearest node (clipped into the grid)
        g = np.rint((np.asarray(points, np.float64) - self.lower) / self.h).astype(np.int64)
        return np.clip(g, 0, np.asarray(self.shape) - 1)

    def node_positions(self, idx) -> np.ndarray:  # N,3 from N,3 int
        return self.lower + np.asarray(idx, np.float64) * self.h


def make_grid(lo, hi, margin: float, resolution: int, voxel_size: float | None = None,
              max_resolution: int = 256) -> Grid:
    """Grid over the box [lo, hi] (the particles' bounds) grown by ``margin``; cubic voxels."""
    lo = np.asarray(lo, np.float64) - margin
    hi = np.asarray(hi, np.float64) + margin
    extent = hi - lo
    if voxel_size is None:
        h = float(extent.max()) / (resolution - 1)
    else:
        h = max(float(voxel_size), float(extent.max()) / (max_resolution - 1))
    shape = tuple(int(np.ceil(e / h - 1e-6)) + 1 for e in extent)  # (the longest axis: e / h = resolution - 1)
    return Grid(lo, h, shape)


def hash_grid(points, cell: float, extent, device: str):
    """wp.HashGrid over ``points`` (warp vec3 array) with cells of width ``cell``."""
    dims = [max(1, min(128, int(np.ceil(float(e) / cell)) + 1)) for e in extent]
    hg = wp.HashGrid(*dims, device=device)
    hg.build(points, float(cell))
    return hg


# -- particle spacing ------------------------------------------------------------------------------

@wp.kernel
def _kth_neighbour(hg: wp.uint64, x: wp.array(dtype=wp.vec3), step: wp.float64, k: int, radius: float,
                   dist: wp.array(dtype=float), misses: wp.array(dtype=wp.int32)):
    # distance to the k-th nearest point (the point itself counts, as in cKDTree.query(k=4))
    i = wp.tid()
    p = int(wp.float64(i) * step)  # the same evenly spread sample as np.linspace(0, n - 1, m).astype(int)
    if i == dist.shape[0] // 2 - 1:
        p = x.shape[0] - 1  # linspace ends exactly on its stop
    xp = x[p]
    big = 2.0 * radius + 1.0
    b0 = big
    b1 = big
    b2 = big
    b3 = big
    query = wp.hash_grid_query(hg, xp, radius)
    q = int(0)
    while wp.hash_grid_query_next(query, q):
        d = wp.length(x[q] - xp)
        if d <= radius and d < b3:  # insert into the sorted b0 <= b1 <= b2 <= b3
            b3 = d
            if b3 < b2:
                t = b2
                b2 = b3
                b3 = t
            if b2 < b1:
                t = b1
                b1 = b2
                b2 = t
            if b1 < b0:
                t = b0
                b0 = b1
                b1 = t
    kth = b3
    if k == 1:
        kth = b0
    elif k == 2:
        kth = b1
    elif k == 3:
        kth = b2
    if kth > radius:
        wp.atomic_add(misses, 0, 1)
    dist[i] = kth


@wp.kernel
def _median_of_sorted(keys: wp.array(dtype=float), m: int, out: wp.array(dtype=float)):
    out[0] = 0.5 * (keys[(m - 1) // 2] + keys[m // 2])


def particle_spacing(x, lo, hi, device: str) -> float:
    """Median distance to the 3rd nearest neighbour (x: warp vec3 array; lo, hi: its bounds)."""
    n = x.shape[0]
    if n <= 1:
        return 0.01
    m, k = min(n, SPACING_SAMPLES), min(4, n)
    step = (n - 1) / (m - 1) if m > 1 else 0.0
    ext = np.asarray(hi, np.float64) - np.asarray(lo, np.float64)
    ext = np.maximum(ext, 1e-3 * max(float(ext.max()), 1e-9))  # flat clouds: no zero-volume estimate
    # the spacing of a cloud that fills its box is an upper bound of the true spacing (a cloud fills at
    # most its box); 1.6x it holds the 3rd neighbour of a jittered lattice, else the radius doubles
    radius = 1.6 * float(np.prod(ext) / n) ** (1.0 / 3.0)
    keys = wp.empty(2 * m, dtype=float, device=device)  # radix sort needs twice the length
    vals = wp.zeros(2 * m, dtype=wp.int32, device=device)
    for _ in range(40):
        misses = wp.zeros(1, dtype=wp.int32, device=device)
        hg = hash_grid(x, radius, ext, device)
        wp.launch(_kth_neighbour, dim=m, inputs=[hg.id, x, wp.float64(step), k, float(radius), keys, misses],
                  device=device)
        if int(misses.numpy()[0]) == 0:
            break
        radius *= 2.0  # some sample had fewer than k points within the radius (a sparse cloud)
    try:
        wp.utils.radix_sort_pairs(keys, vals, m)
        med = wp.zeros(1, dtype=float, device=device)
        wp.launch(_median_of_sorted, dim=1, inputs=[keys, m, med], device=device)
        return float(med.numpy()[0])
    except (RuntimeError, TypeError):  # Warp without float keys in radix_sort_pairs
        return float(np.median(keys.numpy()[:m]))


# -- SDF splat -------------------------------------------------------------------------------------

@wp.func
def _node_dist(xp: wp.vec3, lower: wp.vec3, h: float, i: int, j: int, k: int, r: float):
    node = lower + wp.vec3(float(i), float(j), float(k)) * h
    return wp.length(node - xp) - r


@wp.kernel
def _splat_sdf(x: wp.array(dtype=wp.vec3), r: float, lower: wp.vec3, h: float, reach: int,
               sdf: wp.array3d(dtype=float)):
    # one thread per (particle, slab i of its window): a few thousand particles alone would leave most of a
    # GPU idle, each thread walking (2 reach + 1)^3 nodes in turn
    p, s = wp.tid()
    xp = x[p]
    c = (xp - lower) / h
    ci = int(wp.round(c[0]))
    cj = int(wp.round(c[1]))
    ck = int(wp.round(c[2]))
    lim = (float(reach) + 0.5) * h  # skip the corners of the cube window: the band is a ball
    # (the plain cube loop: limiting each column to the ball was slower on the CPU)
    i = ci - reach + s
    if i >= 0 and i < sdf.shape[0]:
        for j in range(wp.max(cj - reach, 0), wp.min(cj + reach + 1, sdf.shape[1])):
            for k in range(wp.max(ck - reach, 0), wp.min(ck + reach + 1, sdf.shape[2])):
                d = _node_dist(xp, lower, h, i, j, k, r)
                if d + r <= lim:
                    wp.atomic_min(sdf, i, j, k, d)


@wp.kernel
def _splat_owner(x: wp.array(dtype=wp.vec3), lab: wp.array(dtype=wp.int32), r: float, lower: wp.vec3, h: float,
                 reach: int, tol: float, sdf: wp.array3d(dtype=float), owner: wp.array3d(dtype=wp.int32)):
    # second pass: a particle within ``tol`` of the min writes its label.  Not an exact tie test: on CUDA the
    # compiler may contract this kernel's arithmetic (fused multiply-adds) differently from _splat_sdf's, so the
    # same expression can differ in its last bits; then no particle matched, the node had no owner, no wall
    # was raised and two pieces an earlier cut had split merged again (128^3 slices, docs/topology.md)
    p, s = wp.tid()  # (particle, slab), as in _splat_sdf
    xp = x[p]
    c = (xp - lower) / h
    ci = int(wp.round(c[0]))
    cj = int(wp.round(c[1]))
    ck = int(wp.round(c[2]))
    i = ci - reach + s
    if i >= 0 and i < sdf.shape[0]:
        for j in range(wp.max(cj - reach, 0), wp.min(cj + reach + 1, sdf.shape[1])):
            for k in range(wp.max(ck - reach, 0), wp.min(ck + reach + 1, sdf.shape[2])):
                if _node_dist(xp, lower, h, i, j, k, r) <= sdf[i, j, k] + tol:
                    owner[i, j, k] = lab[p]


@wp.kernel
def _walls(sdf: wp.array3d(dtype=float), owner: wp.array3d(dtype=wp.int32), value: float,
           out: wp.array3d(dtype=float)):
    # an inside node next to (26-neighbourhood) an inside node of another previous cluster becomes
    # outside: 6-connected labels *and* marching cubes (whose ambiguous cases may join diagonal
    # corners) then both see the clusters apart
    i, j, k = wp.tid()
    v = sdf[i, j, k]
    out[i, j, k] = v
    o = owner[i, j, k]
    if v < 0.0 and o >= 0:
        for di in range(-1, 2):
            for dj in range(-1, 2):
                for dk in range(-1, 2):
                    a = i + di
                    b = j + dj
                    c = k + dk
                    if a >= 0 and a < sdf.shape[0] and b >= 0 and b < sdf.shape[1] and c >= 0 and c < sdf.shape[2]:
                        p = owner[a, b, c]
                        if p >= 0 and p != o and sdf[a, b, c] < 0.0:
                            out[i, j, k] = value


def particle_sdf(x, r: float, grid: Grid, band: float, device: str = "cpu", owner_labels=None):
    """SDF as a warp array3d (nx,ny,nz).  x: warp vec3 array (or numpy N,3) on ``device``.

    owner_labels (N,) int (warp int32 array or numpy), optional: the previous
    cluster of each particle; nodes where two different clusters touch are
    raised to +h/2 (a wall), so pieces split by an earlier cut stay apart even
    if only the last sweep is carved.
    """
    init_warp()
    if not isinstance(x, wp.array):
        x = wp.array(np.ascontiguousarray(x, np.float32), dtype=wp.vec3, device=device)
    reach = int(np.ceil((r + band) / grid.h))
    sdf = wp.full(grid.shape, float(band), dtype=float, device=device)
    wp.launch(_splat_sdf, dim=(x.shape[0], 2 * reach + 1), inputs=[x, float(r), grid.wp_lower, float(grid.h), reach, sdf],
              device=device)
    if owner_labels is not None:
        if not isinstance(owner_labels, wp.array):
            owner_labels = wp.array(np.ascontiguousarray(owner_labels, np.int32), dtype=wp.int32, device=device)
        ow = wp.full(grid.shape, -1, dtype=wp.int32, device=device)
        wp.launch(_splat_owner, dim=(x.shape[0], 2 * reach + 1),
                  inputs=[x, owner_labels, float(r), grid.wp_lower, float(grid.h), reach, 1e-3 * float(grid.h), sdf, ow],
                  device=device)
        walled = wp.empty_like(sdf)
        wp.launch(_walls, dim=grid.shape, inputs=[sdf, ow, 0.5 * float(grid.h), walled], device=device)
        sdf = walled
    return sdf

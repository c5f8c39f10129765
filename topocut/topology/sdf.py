"""Particle SDF on a regular grid and knife-sweep carving (Warp kernels, CPU or CUDA).

SDF(x) = min_p |x - x_p| - r_p is computed by *splatting*: every particle
visits the grid nodes within r_p + band of itself and lowers them with an
atomic min.  Cost is O(particles x band^3), never O(particles x voxels); nodes
farther than the band keep the clamp value `band` (positive = outside), which
is all marching cubes and the inside/outside labelling need.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

_READY = False


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
    """Regular grid: node (i, j, k) sits at lower + (i, j, k) * h."""

    lower: np.ndarray  # 3,
    h: float
    shape: tuple  # (nx, ny, nz)

    @property
    def upper(self) -> np.ndarray:  # 3,
        return self.lower + (np.asarray(self.shape) - 1) * self.h

    def nodes_of(self, points) -> np.ndarray:  # N,3 int: nearest node (clipped into the grid)
        g = np.rint((np.asarray(points, np.float64) - self.lower) / self.h).astype(np.int64)
        return np.clip(g, 0, np.asarray(self.shape) - 1)

    def node_positions(self, idx) -> np.ndarray:  # N,3 from N,3 int
        return self.lower + np.asarray(idx, np.float64) * self.h


def make_grid(points, margin: float, resolution: int, voxel_size: float | None = None,
              max_resolution: int = 256) -> Grid:
    """Grid over the points' bounding box grown by ``margin``; cubic voxels."""
    lo = points.min(0).astype(np.float64) - margin
    hi = points.max(0).astype(np.float64) + margin
    extent = hi - lo
    if voxel_size is None:
        h = float(extent.max()) / (resolution - 1)
    else:
        h = max(float(voxel_size), float(extent.max()) / (max_resolution - 1))
    shape = tuple(int(np.ceil(e / h)) + 1 for e in extent)
    return Grid(lo, h, shape)


@wp.func
def _node_dist(xp: wp.vec3, lower: wp.vec3, h: float, i: int, j: int, k: int, r: float):
    node = lower + wp.vec3(float(i), float(j), float(k)) * h
    return wp.length(node - xp) - r


@wp.kernel
def _splat_sdf(x: wp.array(dtype=wp.vec3), r: float, lower: wp.vec3, h: float, reach: int,
               sdf: wp.array3d(dtype=float)):
    p = wp.tid()
    xp = x[p]
    c = (xp - lower) / h
    ci = int(wp.round(c[0]))
    cj = int(wp.round(c[1]))
    ck = int(wp.round(c[2]))
    lim = (float(reach) + 0.5) * h  # skip the corners of the cube window: the band is a ball
    for i in range(wp.max(ci - reach, 0), wp.min(ci + reach + 1, sdf.shape[0])):
        for j in range(wp.max(cj - reach, 0), wp.min(cj + reach + 1, sdf.shape[1])):
            for k in range(wp.max(ck - reach, 0), wp.min(ck + reach + 1, sdf.shape[2])):
                d = _node_dist(xp, lower, h, i, j, k, r)
                if d + r <= lim:
                    wp.atomic_min(sdf, i, j, k, d)


@wp.kernel
def _splat_owner(x: wp.array(dtype=wp.vec3), lab: wp.array(dtype=int), r: float, lower: wp.vec3, h: float,
                 reach: int, sdf: wp.array3d(dtype=float), owner: wp.array3d(dtype=int)):
    # second pass: the particle that achieved the min writes its label (same float expression -> exact tie test)
    p = wp.tid()
    xp = x[p]
    c = (xp - lower) / h
    ci = int(wp.round(c[0]))
    cj = int(wp.round(c[1]))
    ck = int(wp.round(c[2]))
    for i in range(wp.max(ci - reach, 0), wp.min(ci + reach + 1, sdf.shape[0])):
        for j in range(wp.max(cj - reach, 0), wp.min(cj + reach + 1, sdf.shape[1])):
            for k in range(wp.max(ck - reach, 0), wp.min(ck + reach + 1, sdf.shape[2])):
                if _node_dist(xp, lower, h, i, j, k, r) == sdf[i, j, k]:
                    owner[i, j, k] = lab[p]


@wp.kernel
def _carve(sdf: wp.array3d(dtype=float), lower: wp.vec3, h: float,
           origin: wp.array(dtype=wp.vec3), u: wp.array(dtype=wp.vec3), w: wp.array(dtype=wp.vec3),
           n: wp.array(dtype=wp.vec3), half: wp.array(dtype=wp.vec3),
           damaged: wp.uint64, dpts: wp.array(dtype=wp.vec3), carve_radius: float,
           carved: wp.array3d(dtype=wp.uint8)):
    i, j, k = wp.tid()
    x = lower + wp.vec3(float(i), float(j), float(k)) * h
    for s in range(origin.shape[0]):
        d = x - origin[s]
        hs = half[s]
        # box SDF in the sweep frame; the box centre lies depth/2 along w
        q = wp.vec3(wp.abs(wp.dot(d, u[s])) - hs[0], wp.abs(wp.dot(d, w[s]) - hs[1]) - hs[1],
                    wp.abs(wp.dot(d, n[s])) - hs[2])
        outside = wp.length(wp.vec3(wp.max(q[0], 0.0), wp.max(q[1], 0.0), wp.max(q[2], 0.0)))
        box = outside + wp.min(wp.max(q[0], wp.max(q[1], q[2])), 0.0)
        if box < 0.0:
            # the knife only separates where it went through damaged material
            near = int(0)  # noqa: UP018 (a literal would be a Warp constant, not mutable in the loop)
            query = wp.hash_grid_query(damaged, x, carve_radius)
            idx = int(0)  # noqa: UP018
            while wp.hash_grid_query_next(query, idx):
                if wp.length(dpts[idx] - x) <= carve_radius:
                    near = 1
            if near == 1:
                sdf[i, j, k] = wp.max(sdf[i, j, k], -box)
                carved[i, j, k] = wp.uint8(1)


@wp.kernel
def _walls(sdf: wp.array3d(dtype=float), owner: wp.array3d(dtype=int), value: float,
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


def particle_sdf(x: np.ndarray, r: float, grid: Grid, band: float, device: str = "cpu",
                 owner_labels: np.ndarray | None = None):
    """SDF as a warp array3d (nx,ny,nz).  x: N,3.

    owner_labels (N,) int, optional: the previous cluster of each particle; nodes
    where two different clusters touch are raised to +h/2 (a wall), so pieces
    split by an earlier cut stay apart even if only the last sweep is carved.
    """
    init_warp()
    reach = int(np.ceil((r + band) / grid.h))
    lower = wp.vec3(*grid.lower.astype(np.float32))
    xa = wp.array(np.ascontiguousarray(x, np.float32), dtype=wp.vec3, device=device)
    sdf = wp.full(grid.shape, float(band), dtype=float, device=device)
    wp.launch(_splat_sdf, dim=len(x), inputs=[xa, float(r), lower, float(grid.h), reach, sdf], device=device)
    if owner_labels is not None:
        ow = wp.full(grid.shape, -1, dtype=int, device=device)
        la = wp.array(np.ascontiguousarray(owner_labels, np.int32), dtype=int, device=device)
        wp.launch(_splat_owner, dim=len(x), inputs=[xa, la, float(r), lower, float(grid.h), reach, sdf, ow],
                  device=device)
        walled = wp.empty_like(sdf)
        wp.launch(_walls, dim=grid.shape, inputs=[sdf, ow, 0.5 * float(grid.h), walled], device=device)
        sdf = walled
    return sdf


def carve_sweeps(sdf, grid: Grid, sweeps: list, damaged_x: np.ndarray, carve_radius: float,
                 min_half_thickness: float, device: str = "cpu") -> np.ndarray:
    """Carve sdf = max(sdf, -sweep_sdf) where a sweep passes within carve_radius of damaged particles.

    Mutates ``sdf`` (warp array3d) and returns the carved-node mask (nx,ny,nz) bool.
    Each sweep is thickened to at least ``min_half_thickness`` so that the grid resolves the gap.
    """
    init_warp()
    carved = wp.zeros(grid.shape, dtype=wp.uint8, device=device)
    if not sweeps or len(damaged_x) == 0:
        return carved.numpy().astype(bool)
    arrs = [s.as_arrays() for s in sweeps]
    half = np.array([[s.half_length, s.depth / 2.0, max(s.half_thickness, min_half_thickness)] for s in sweeps])
    vec = lambda a: wp.array(np.asarray(a, np.float32), dtype=wp.vec3, device=device)  # noqa: E731
    cells = max(1, min(128, int(np.ceil(np.ptp(damaged_x, axis=0).max() / carve_radius)) + 1))
    hg = wp.HashGrid(cells, cells, cells, device=device)
    dx = vec(damaged_x)
    hg.build(dx, float(carve_radius))
    wp.launch(_carve, dim=grid.shape, device=device,
              inputs=[sdf, wp.vec3(*grid.lower.astype(np.float32)), float(grid.h),
                      vec([a[0] for a in arrs]), vec([a[1] for a in arrs]), vec([a[2] for a in arrs]),
                      vec([a[3] for a in arrs]), vec(half), hg.id, dx, float(carve_radius), carved])
    return carved.numpy().astype(bool)

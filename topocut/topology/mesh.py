"""Marching cubes (Warp), vertex adjacency, Laplacian smoothing and the MC vertex -> inside node map.

Everything stays in warp arrays on the device: marching cubes gives welded
vertices (V,) vec3 and a flat index list (3F,) int32; the vertex adjacency is a
CSR built with atomics (count, prefix sum, scatter, then each row sorted and
deduplicated by its own thread); smoothing is one kernel launch per iteration.
The numpy functions at the end wrap these for tests and small meshes.
"""
# ruff: noqa: UP018  (int(0), float(...) declare mutable Warp kernel variables; a bare literal is a constant)
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from topocut.topology.sdf import Grid, init_warp


def extract_surface(field, grid: Grid, device: str = "cpu"):
    """Zero iso-surface of a warp array3d (negative inside) -> (verts (V,) vec3 world coords, faces (3F,) int32).

    Uses warp.geometry.IsoSurfaceMarchingCubes (Warp >= 1.18) and falls back
    to the older wp.MarchingCubes.  Winding as Warp emits it (see ``oriented``).
    """
    init_warp()
    try:
        from warp.geometry import IsoSurfaceMarchingCubes as iso
    except ImportError:
        iso = None
    if iso is not None:
        lower = tuple(float(v) for v in grid.lower)
        upper = tuple(float(v) for v in grid.upper)
        verts, idx = iso.extract(field, 0.0, lower=lower, upper=upper)
        return verts, idx.flatten() if idx.ndim > 1 else idx
    nx, ny, nz = grid.shape  # Warp < 1.18: stateful MarchingCubes with index-space output
    mc = wp.MarchingCubes(nx, ny, nz, max_verts=nx * ny * nz, max_tris=2 * nx * ny * nz, device=device)
    mc.surface(field, 0.0)
    verts = wp.empty(mc.verts.shape[0], dtype=wp.vec3, device=device)
    wp.launch(_index_to_world, dim=verts.shape[0], inputs=[mc.verts, grid.wp_lower, float(grid.h), verts],
              device=device)
    return verts, mc.indices.flatten() if mc.indices.ndim > 1 else mc.indices


@wp.kernel
def _index_to_world(src: wp.array(dtype=wp.vec3), lower: wp.vec3, h: float, out: wp.array(dtype=wp.vec3)):
    v = wp.tid()
    out[v] = lower + src[v] * h


# -- vertex adjacency (CSR) --------------------------------------------------------------------------

@wp.kernel
def _count_slots(faces: wp.array(dtype=wp.int32), deg: wp.array(dtype=wp.int32)):
    t = wp.tid()
    for c in range(3):  # each corner gets its two face neighbours
        wp.atomic_add(deg, faces[3 * t + c], 2)


@wp.kernel
def _scatter_neighbours(faces: wp.array(dtype=wp.int32), offset: wp.array(dtype=wp.int32),
                        cursor: wp.array(dtype=wp.int32), nbr: wp.array(dtype=wp.int32)):
    t = wp.tid()
    for c in range(3):
        a = faces[3 * t + c]
        slot = offset[a] + wp.atomic_add(cursor, a, 2)
        nbr[slot] = faces[3 * t + (c + 1) % 3]
        nbr[slot + 1] = faces[3 * t + (c + 2) % 3]


@wp.kernel
def _sort_unique_rows(offset: wp.array(dtype=wp.int32), deg: wp.array(dtype=wp.int32),
                      nbr: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32)):
    # each row (a vertex's neighbours, every edge seen from both of its faces) sorted, duplicates dropped:
    # a fixed order also makes the smoothing sums the same on every run and device
    v = wp.tid()
    s = offset[v]
    n = deg[v]
    for a in range(1, n):  # insertion sort (rows hold about a dozen entries)
        key = nbr[s + a]
        b = a - 1
        while b >= 0:
            if nbr[s + b] > key:
                nbr[s + b + 1] = nbr[s + b]
                b -= 1
            else:
                break
        nbr[s + b + 1] = key
    m = int(0)
    last = int(-1)  # vertex ids are >= 0
    for a in range(n):
        if nbr[s + a] != last:
            last = nbr[s + a]
            nbr[s + m] = last
            m += 1
    count[v] = m


@dataclass
class Adjacency:
    offset: object  # warp int32 (V,): row start
    count: object  # warp int32 (V,): distinct neighbours
    nbr: object  # warp int32 (6F,): neighbours, the first count[v] of each row distinct and sorted


def vertex_adjacency(faces, num_verts: int, device: str = "cpu") -> Adjacency:
    """CSR vertex adjacency from a flat (3F,) int32 warp index list."""
    nf = faces.shape[0] // 3
    deg = wp.zeros(num_verts, dtype=wp.int32, device=device)
    wp.launch(_count_slots, dim=nf, inputs=[faces, deg], device=device)
    offset = wp.empty_like(deg)
    wp.utils.array_scan(deg, offset, inclusive=False)
    cursor = wp.zeros_like(deg)
    nbr = wp.empty(6 * nf, dtype=wp.int32, device=device)
    wp.launch(_scatter_neighbours, dim=nf, inputs=[faces, offset, cursor, nbr], device=device)
    count = wp.empty_like(deg)
    wp.launch(_sort_unique_rows, dim=num_verts, inputs=[offset, deg, nbr, count], device=device)
    return Adjacency(offset, count, nbr)


@wp.kernel
def _smooth_step(v: wp.array(dtype=wp.vec3), adj_offset: wp.array(dtype=wp.int32),
                 adj_count: wp.array(dtype=wp.int32), nbr: wp.array(dtype=wp.int32), alpha: float,
                 out: wp.array(dtype=wp.vec3)):
    # umbrella operator v_i += alpha (mean_j v_j - v_i): the mean keeps the step stable for any valence
    i = wp.tid()
    c = adj_count[i]
    vi = v[i]
    if c == 0:  # a vertex in no face stays where it is
        out[i] = vi
        return
    s = wp.vec3(0.0, 0.0, 0.0)
    o = adj_offset[i]
    for a in range(c):
        s += v[nbr[o + a]]
    out[i] = vi + alpha * (s / float(c) - vi)


def smooth(verts, adj: Adjacency, iterations: int, alpha: float, device: str = "cpu"):
    """Laplacian smoothing of a warp vec3 array; returns a new array (ping-pong buffers)."""
    a = wp.clone(verts)
    if iterations <= 0 or verts.shape[0] == 0:
        return a
    b = wp.empty_like(a)
    for _ in range(iterations):
        wp.launch(_smooth_step, dim=a.shape[0], inputs=[a, adj.offset, adj.count, adj.nbr, float(alpha), b],
                  device=device)
        a, b = b, a
    return a


# -- MC vertex -> inside grid node ------------------------------------------------------------------

@wp.func
def _flat_clipped(i: int, j: int, k: int, nx: int, ny: int, nz: int):
    return (wp.clamp(i, 0, nx - 1) * ny + wp.clamp(j, 0, ny - 1)) * nz + wp.clamp(k, 0, nz - 1)


@wp.kernel
def _vertex_inside_nodes(verts: wp.array(dtype=wp.vec3), field: wp.array3d(dtype=float), lower: wp.vec3, h: float,
                         out: wp.array(dtype=wp.int32)):
    # every MC vertex lies on a grid edge between an inside and an outside node; the edge runs along the
    # axis where the vertex's grid coordinate is least integral (the rounded node is a candidate too,
    # for a vertex exactly on a node)
    v = wp.tid()
    g = (verts[v] - lower) / h
    base = wp.vec3(wp.round(g[0]), wp.round(g[1]), wp.round(g[2]))
    ax = int(0)
    fmax = wp.abs(g[0] - base[0])
    if wp.abs(g[1] - base[1]) > fmax:
        ax = 1
        fmax = wp.abs(g[1] - base[1])
    if wp.abs(g[2] - base[2]) > fmax:
        ax = 2
    bi = int(base[0])
    bj = int(base[1])
    bk = int(base[2])
    li = bi
    lj = bj
    lk = bk
    if ax == 0:
        li = int(wp.floor(g[0]))
    elif ax == 1:
        lj = int(wp.floor(g[1]))
    else:
        lk = int(wp.floor(g[2]))
    hi = li
    hj = lj
    hk = lk
    if ax == 0:
        hi = li + 1
    elif ax == 1:
        hj = lj + 1
    else:
        hk = lk + 1
    nx = field.shape[0]
    ny = field.shape[1]
    nz = field.shape[2]
    best = _flat_clipped(li, lj, lk, nx, ny, nz)
    val = field[wp.clamp(li, 0, nx - 1), wp.clamp(lj, 0, ny - 1), wp.clamp(lk, 0, nz - 1)]
    v2 = field[wp.clamp(hi, 0, nx - 1), wp.clamp(hj, 0, ny - 1), wp.clamp(hk, 0, nz - 1)]
    if v2 < val:
        val = v2
        best = _flat_clipped(hi, hj, hk, nx, ny, nz)
    v3 = field[wp.clamp(bi, 0, nx - 1), wp.clamp(bj, 0, ny - 1), wp.clamp(bk, 0, nz - 1)]
    if v3 < val:
        val = v3
        best = _flat_clipped(bi, bj, bk, nx, ny, nz)
    if val >= 0.0:
        best = -1
    out[v] = best


def vertex_inside_nodes(verts, field, grid: Grid, device: str = "cpu"):
    """warp int32 (V,): flat index of the inside (field < 0) node of each vertex's grid edge; -1 if none."""
    out = wp.empty(verts.shape[0], dtype=wp.int32, device=device)
    if verts.shape[0]:
        wp.launch(_vertex_inside_nodes, dim=verts.shape[0], inputs=[verts, field, grid.wp_lower, float(grid.h), out],
                  device=device)
    return out


# -- host side ---------------------------------------------------------------------------------------

def signed_volume(verts: np.ndarray, faces: np.ndarray) -> float:
    """Divergence-theorem volume of a closed triangle mesh (negative if faces point inwards)."""
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def oriented(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Faces with outward normals (Warp's winding for negative-inside fields is flipped when needed)."""
    if len(faces) and signed_volume(verts, faces) < 0:
        return faces[:, ::-1].copy()
    return faces


def marching_cubes(field, grid: Grid, device: str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """numpy (nx,ny,nz) or warp field -> (verts (V,3) f64, faces (F,3) int64), outward normals."""
    init_warp()
    if not isinstance(field, wp.array):
        field = wp.array(np.ascontiguousarray(field, np.float32), dtype=float, device=device)
    v, f = extract_surface(field, grid, device)
    verts = v.numpy().astype(np.float64).reshape(-1, 3)
    return verts, oriented(verts, f.numpy().astype(np.int64).reshape(-1, 3))


def laplacian_smooth(verts: np.ndarray, faces: np.ndarray, iterations: int = 5, alpha: float = 0.5,
                     device: str = "cpu") -> np.ndarray:
    """numpy wrapper of ``smooth``: v_i += alpha * (mean_{j in N(i)} v_j - v_i), ``iterations`` times."""
    init_warp()
    v = wp.array(np.asarray(verts, np.float32), dtype=wp.vec3, device=device)
    f = wp.array(np.ascontiguousarray(faces, np.int32).ravel(), dtype=wp.int32, device=device)
    adj = vertex_adjacency(f, len(verts), device)
    return smooth(v, adj, iterations, alpha, device).numpy().astype(np.float64)


def mesh_components(faces: np.ndarray, num_verts: int, device: str = "cpu") -> tuple[int, np.ndarray]:
    """Connected components of a welded mesh -> (count, vertex component ids (V,)), as scipy's csgraph."""
    from topocut.topology.components import graph_components

    f = np.asarray(faces, np.int64).reshape(-1, 3)
    return graph_components(np.concatenate([f[:, [0, 1]], f[:, [0, 2]]]), num_verts, device)

"""Marching cubes (Warp), Laplacian smoothing and mesh connected components."""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from topocut.topology.sdf import Grid, init_warp


def marching_cubes(field, grid: Grid, device: str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """Zero iso-surface of a grid field -> (verts (V,3) f64 world coords, faces (F,3) int64).

    ``field`` is a warp array3d or a numpy array (nx,ny,nz), negative inside.
    Uses warp.geometry.IsoSurfaceMarchingCubes (Warp >= 1.18) and falls back to
    the older wp.MarchingCubes.  Faces are oriented with outward normals.
    """
    import warp as wp

    init_warp()
    if not isinstance(field, wp.array):
        field = wp.array(np.ascontiguousarray(field, np.float32), dtype=float, device=device)
    lower = tuple(float(v) for v in grid.lower)
    upper = tuple(float(v) for v in grid.upper)
    try:
        from warp.geometry import IsoSurfaceMarchingCubes as iso
    except ImportError:
        iso = None
    if iso is not None:
        verts, idx = iso.extract(field, 0.0, lower=lower, upper=upper)
        verts, idx = verts.numpy(), idx.numpy()
    else:  # Warp < 1.18: stateful MarchingCubes with index-space output
        nx, ny, nz = grid.shape
        mc = wp.MarchingCubes(nx, ny, nz, max_verts=nx * ny * nz, max_tris=2 * nx * ny * nz, device=device)
        mc.surface(field, 0.0)
        verts = grid.lower + mc.verts.numpy().astype(np.float64) * grid.h
        idx = mc.indices.numpy()
    faces = idx.reshape(-1, 3).astype(np.int64)
    verts = np.asarray(verts, np.float64).reshape(-1, 3)
    if len(faces) and signed_volume(verts, faces) < 0:
        faces = faces[:, ::-1].copy()  # Warp's winding for negative-inside fields: make normals point out
    return verts, faces


def signed_volume(verts: np.ndarray, faces: np.ndarray) -> float:
    """Divergence-theorem volume of a closed triangle mesh (negative if faces point inwards)."""
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def vertex_adjacency(faces: np.ndarray, num_verts: int) -> sp.csr_matrix:
    """Binary symmetric vertex adjacency (V,V) from triangle edges."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.concatenate([e, e[:, ::-1]])
    a = sp.csr_matrix((np.ones(len(e), np.float64), (e[:, 0], e[:, 1])), shape=(num_verts, num_verts))
    a.data[:] = 1.0  # duplicate edges summed -> 1
    return a


def laplacian_smooth(verts: np.ndarray, faces: np.ndarray, iterations: int = 5, alpha: float = 0.5,
                     adjacency: sp.csr_matrix | None = None) -> np.ndarray:
    """Umbrella-operator smoothing  v_i += alpha * (mean_{j in N(i)} v_j - v_i).

    The mean (rather than the plain sum over neighbours) keeps the step stable
    for any vertex valence when alpha <= 1.
    """
    if iterations <= 0 or len(faces) == 0:
        return verts.copy()
    a = adjacency if adjacency is not None else vertex_adjacency(faces, len(verts))
    deg = np.asarray(a.sum(axis=1)).ravel()
    w = sp.diags(1.0 / np.maximum(deg, 1.0)) @ a  # row-normalised: (W v)_i = mean of neighbours
    v = verts.copy()
    for _ in range(iterations):
        v += alpha * (w @ v - v)
    return v


def mesh_components(faces: np.ndarray, num_verts: int,
                    adjacency: sp.csr_matrix | None = None) -> tuple[int, np.ndarray]:
    """Connected components of a welded mesh -> (count, vertex component ids (V,))."""
    a = adjacency if adjacency is not None else vertex_adjacency(faces, num_verts)
    return connected_components(a, directed=False)


def vertex_inside_nodes(verts: np.ndarray, sdf: np.ndarray, grid: Grid) -> np.ndarray:
    """For each marching-cubes vertex, the flat index of the inside (sdf < 0) grid node of its edge; -1 if none.

    Every MC vertex lies on a grid edge between an inside and an outside node;
    the edge runs along the axis where the vertex's grid coordinate is least
    integral.  The rounded node is also a candidate (vertex exactly on a node).
    """
    g = (verts - grid.lower) / grid.h  # V,3 grid coordinates
    base = np.rint(g).astype(np.int64)
    frac = g - base
    ax = np.argmax(np.abs(frac), axis=1)
    rows = np.arange(len(g))
    lo, hi = base.copy(), base.copy()
    lo[rows, ax] = np.floor(g[rows, ax]).astype(np.int64)
    hi[rows, ax] = lo[rows, ax] + 1
    shape = np.asarray(sdf.shape)
    cands = np.stack([np.clip(c, 0, shape - 1) for c in (lo, hi, base)], axis=1)  # V,3,3
    flat = np.ravel_multi_index(tuple(np.moveaxis(cands, -1, 0)), sdf.shape)  # V,3
    vals = sdf.ravel()[flat]  # V,3
    best = np.argmin(vals, axis=1)
    out = flat[rows, best]
    out[vals[rows, best] >= 0] = -1
    return out

"""Damage-driven topology discovery (paper §3.1 and appendix "Particle-based Damage-tracking").

particles -> SDF(x) = min_p |x - x_p| - r_p on a grid -> carve the knife sweep where it went
through damaged material -> (keep earlier splits apart) -> marching cubes -> Laplacian smoothing
-> connected components -> cluster id per particle -> ids consistent with the previous labels.

Pieces are the connected components of the inside nodes (sdf < 0, 6-connected,
scipy.ndimage.label) *united* with the marching-cubes mesh components: every MC
vertex links its mesh component to the inside node of its grid edge, and the
connected components of that bipartite graph are the pieces.  So the meshes and
the voxel labels always agree, an inner shell (cavity) joins the piece that
contains it, and a torus is one piece.  Particles are labelled through the
voxel labelling (O(1) per particle); particles whose node is outside every kept
piece (inside the carved gap, debris) take the piece of the nearest mesh vertex
if it is closer than tau, else -1.  Warp is imported only when discover() runs.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from topocut.sim.action import KnifeSweep
from topocut.topology.config import TopologyConfig
from topocut.topology.tracking import match_labels

EXPORT_FORMATS = ("ply", "obj", "stl")


@dataclass
class TopologyResult:
    labels: np.ndarray  # N, int32 cluster id per particle (-1 = unassigned)
    meshes: dict  # id -> trimesh.Trimesh (smoothed surface of that piece)
    num_clusters: int
    timings: dict = field(default_factory=dict)  # step -> seconds
    next_id: int = 0  # first id never used so far in the episode (pass it to the next discover call)

    def export(self, directory, fmt: str = "ply") -> list[Path]:
        """Write one mesh file per piece, ``piece_<id>.<fmt>``; returns the paths."""
        if fmt not in EXPORT_FORMATS:
            raise ValueError(f"unknown mesh format {fmt!r}; valid: {', '.join(EXPORT_FORMATS)}")
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        paths = []
        for cid, mesh in sorted(self.meshes.items()):
            p = d / f"piece_{cid:03d}.{fmt}"
            mesh.export(p)
            paths.append(p)
        return paths


def as_sweeps(knife_sweep) -> list[KnifeSweep]:
    """None | KnifeSweep | dict | (nested) list of those -> flat list of KnifeSweep."""
    if knife_sweep is None:
        return []
    if isinstance(knife_sweep, KnifeSweep):
        return [knife_sweep]
    if isinstance(knife_sweep, dict):
        return [KnifeSweep.fromdict(knife_sweep)]
    if isinstance(knife_sweep, (list, tuple)):
        return [s for item in knife_sweep for s in as_sweeps(item)]
    raise ValueError(f"knife_sweep must be a KnifeSweep, its dict, a list of them or None; "
                     f"got {type(knife_sweep).__name__}")


def particle_radius(x: np.ndarray, cfg: TopologyConfig) -> float:
    if cfg.particle_radius is not None:
        return float(cfg.particle_radius)
    from scipy.spatial import cKDTree

    sample = x if len(x) <= 20000 else x[np.linspace(0, len(x) - 1, 20000).astype(np.int64)]
    # the 3rd-nearest-neighbour distance is the lattice spacing for a jittered lattice and close to the
    # sampling spacing of the simulator's (blue-noise-like) object samples; the 1st is biased low by jitter
    k = min(4, len(x))
    d, _ = cKDTree(x).query(sample, k=k)
    spacing = float(np.median(d[:, k - 1])) if len(x) > 1 else 0.01
    return cfg.radius_factor * max(spacing, 1e-6)


def snap_to_board(s: KnifeSweep, board_z: float | None, tol: float) -> KnifeSweep:
    """A sweep that stopped at (or within ``tol`` of) the board is extended ``tol`` through it.

    Otherwise the thin layer of material between the blade's last position and
    the board's top face could keep the two sides connected in the grid.
    """
    if board_z is None:
        return s
    o, _, w, _ = s.as_arrays()
    bottom = o[2] + s.depth * w[2]
    if w[2] < 0 and bottom <= board_z + tol:
        return KnifeSweep(s.origin, s.u, s.w, s.n, s.half_length, s.depth + 2 * tol / -w[2], s.half_thickness)
    return s


def fill_voids(sdf: np.ndarray, max_voxels: int, value: float) -> None:
    """Fill enclosed outside regions of at most ``max_voxels`` nodes (gaps between jittered particles).

    Outside nodes not connected to the grid border are cavities; tiny ones are
    sampling artefacts that would become bubble shells in the mesh, large ones
    (a hollow object) are kept.
    """
    if max_voxels <= 0:
        return
    from scipy import ndimage

    lab, n = ndimage.label(sdf >= 0)
    if n <= 1:
        return
    border = np.unique(np.concatenate([lab[[0, -1]].ravel(), lab[:, [0, -1]].ravel(), lab[:, :, [0, -1]].ravel()]))
    size = np.bincount(lab.ravel(), minlength=n + 1)
    small = size <= max_voxels
    small[0] = False
    small[border] = False
    if small.any():
        sdf[small[lab]] = value


def discover(positions, damage, knife_sweep, previous_labels=None, cfg: TopologyConfig | None = None,
             device: str = "cpu", next_id: int | None = None) -> TopologyResult:
    """Cluster id per particle after a cut.  positions (N,3), damage (N,) bool; see module docstring."""
    from scipy import ndimage
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    from topocut.topology import mesh as M
    from topocut.topology import sdf as S

    cfg = (cfg or TopologyConfig()).validate()
    device = S.resolve_device(device)
    timings: dict[str, float] = {}
    t_all = t = time.perf_counter()

    def lap(name):
        nonlocal t
        now = time.perf_counter()
        timings[name] = timings.get(name, 0.0) + now - t
        t = now

    x = np.asarray(positions, np.float64).reshape(-1, 3)  # N,3
    n = len(x)
    dmg = np.zeros(n, bool) if damage is None else np.asarray(damage, bool).reshape(-1)
    if dmg.shape[0] != n:
        raise ValueError(f"damage has {dmg.shape[0]} entries, positions has {n}")
    if n == 0:
        return TopologyResult(np.zeros(0, np.int32), {}, 0, {"total": 0.0}, int(next_id or 0))
    sweeps = as_sweeps(knife_sweep)

    # --- grid + SDF -----------------------------------------------------------------------------
    r = particle_radius(x, cfg)
    pad = cfg.padding_voxels + cfg.band_voxels
    extent = float(np.ptp(x, axis=0).max()) + 2 * r
    if cfg.voxel_size is None:
        h_est = extent / max(cfg.resolution - 1 - 2 * pad, 1)
    else:
        h_est = max(cfg.voxel_size, extent / max(cfg.max_resolution - 1 - 2 * pad, 1))
    grid = S.make_grid(x, r + pad * h_est, cfg.resolution, cfg.voxel_size, cfg.max_resolution)
    h = grid.h
    owners_in = None
    if cfg.preserve_splits and previous_labels is not None:
        prev = np.asarray(previous_labels).reshape(-1)
        if prev.shape[0] != n:
            raise ValueError(f"previous_labels has {prev.shape[0]} entries, positions has {n}")
        if len(np.unique(prev[prev >= 0])) > 1:
            owners_in = prev.astype(np.int32)
    sdf_wp = S.particle_sdf(x, r, grid, cfg.band_voxels * h, device, owners_in)
    lap("sdf")

    # --- carve the knife's path through damaged material -----------------------------------------
    carve_radius = cfg.carve_radius if cfg.carve_radius is not None else 3.0 * r
    min_half = 0.5 * cfg.min_gap_voxels * h
    gap_half = max([max(s.half_thickness, min_half) for s in sweeps], default=0.0)
    if cfg.carve and sweeps and dmg.any():
        xd = x[dmg]
        near = np.zeros(len(xd), bool)
        for s in sweeps:
            near |= s.sdf(xd) <= carve_radius
        S.carve_sweeps(sdf_wp, grid, [snap_to_board(s, cfg.board_z, cfg.board_snap_voxels * h) for s in sweeps],
                       xd[near], carve_radius, min_half, device)
    sdf = sdf_wp.numpy()  # nx,ny,nz
    if cfg.board_z is not None:  # particle balls reach r below the board; clip them to its top face
        z = grid.lower[2] + np.arange(grid.shape[2]) * h
        np.maximum(sdf, (cfg.board_z - z)[None, None, :].astype(sdf.dtype), out=sdf)
    fill_voids(sdf, cfg.max_void_voxels, -0.5 * h)
    lap("carve")

    # --- surface ------------------------------------------------------------------------------
    verts, faces = M.marching_cubes(sdf, grid, device)
    lap("marching_cubes")
    adj = M.vertex_adjacency(faces, len(verts))
    verts_s = M.laplacian_smooth(verts, faces, cfg.smoothing_iterations, cfg.smoothing_alpha, adj)
    lap("smoothing")

    # --- pieces = inside-node components united with mesh components ----------------------------
    vox, nv = ndimage.label(sdf < 0)  # 6-connectivity
    n_mc, vcomp = M.mesh_components(faces, len(verts), adj)
    vnode = M.vertex_inside_nodes(verts, sdf, grid)
    vlab = np.where(vnode >= 0, vox.ravel()[np.maximum(vnode, 0)], 0)
    e = np.unique(np.stack([vcomp[vlab > 0], n_mc + vlab[vlab > 0] - 1], 1), axis=0)
    g = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n_mc + nv, n_mc + nv))
    n_pieces, plab = connected_components(g, directed=False)
    piece_vox = np.bincount(plab[n_mc:], weights=np.bincount(vox.ravel(), minlength=nv + 1)[1:],
                            minlength=n_pieces)
    keep = np.flatnonzero(piece_vox >= max(cfg.min_component_voxels, 1))
    compact = np.full(n_pieces, -1, np.int64)
    compact[keep] = np.arange(len(keep))
    raw_of_vox = np.concatenate([[-1], compact[plab[n_mc:]]])  # voxel label -> raw piece (-1 dropped)
    raw_of_mesh = compact[plab[:n_mc]]  # mesh component -> raw piece
    lap("components")

    # --- particles -> pieces --------------------------------------------------------------------
    nodes = grid.nodes_of(x)
    raw = raw_of_vox[vox[nodes[:, 0], nodes[:, 1], nodes[:, 2]]]  # N,
    tau = cfg.tau if cfg.tau is not None else 2.0 * r + gap_half
    todo = np.flatnonzero(raw < 0)
    vraw = raw_of_mesh[vcomp] if n_mc else np.zeros(0, np.int64)
    if len(todo) and (vraw >= 0).any():
        kept_v = np.flatnonzero(vraw >= 0)
        kk = min(16, len(kept_v))
        d, j = cKDTree(verts_s[kept_v]).query(x[todo], k=kk, distance_upper_bound=tau)  # T,kk
        d, j = d.reshape(len(todo), kk), j.reshape(len(todo), kk)
        ok = np.isfinite(d)
        cand = np.where(ok, vraw[kept_v[np.minimum(j, len(kept_v) - 1)]], -1)  # T,kk raw piece per neighbour
        if owners_in is not None:
            # a particle on the wall between two earlier pieces goes to a piece of its own earlier cluster
            res_ok = raw >= 0
            origin = np.full(len(keep), -1, np.int64)
            for k in range(len(keep)):
                o = owners_in[res_ok & (raw == k)]
                o = o[o >= 0]
                origin[k] = np.bincount(o).argmax() if len(o) else -1
            same = ok & (origin[np.maximum(cand, 0)] == owners_in[todo][:, None])
            first = np.where(same.any(1), same.argmax(1), 0)
        else:
            first = np.zeros(len(todo), np.int64)
        pick = cand[np.arange(len(todo)), first]
        raw[todo[pick >= 0]] = pick[pick >= 0]
    raw = _absorb_debris(raw, x, cfg.min_piece_particles)
    lap("assignment")

    labels, id_of, nxt = match_labels(raw, previous_labels, next_id, x)
    meshes = {}
    if len(keep):
        import trimesh

        fraw = vraw[faces[:, 0]]
        for k in range(len(keep)):
            if k >= len(id_of) or id_of[k] < 0 or not (raw == k).any():
                continue  # a surface with no particles assigned to it (e.g. a thin shell) is no piece
            f = faces[fraw == k]
            used, inv = np.unique(f, return_inverse=True)
            meshes[int(id_of[k])] = trimesh.Trimesh(verts_s[used], inv.reshape(-1, 3), process=False)
    lap("tracking")
    timings["total"] = time.perf_counter() - t_all
    present = np.unique(labels[labels >= 0])
    return TopologyResult(labels, meshes, int(len(present)), timings, int(nxt))


def _absorb_debris(raw: np.ndarray, x: np.ndarray, min_particles: int) -> np.ndarray:
    """Particles of pieces smaller than ``min_particles`` join the piece of their nearest particle in a
    larger piece: MPM sheds chips of a few particles at a cut that are no piece a robot could pick up."""
    counts = np.bincount(raw[raw >= 0], minlength=1)
    small = np.flatnonzero((counts > 0) & (counts < min_particles))
    if len(small) == 0 or not (counts >= min_particles).any():
        return raw
    from scipy.spatial import cKDTree

    big = np.flatnonzero((raw >= 0) & ~np.isin(raw, small))
    move = np.flatnonzero(np.isin(raw, small))
    _, j = cKDTree(x[big]).query(x[move])
    out = raw.copy()
    out[move] = raw[big[j]]
    return out


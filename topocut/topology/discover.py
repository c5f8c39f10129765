"""Damage-driven topology discovery (paper §3.1 and appendix "Particle-based Damage-tracking").

particles -> SDF(x) = min_p |x - x_p| - r_p on a grid -> carve the knife sweep where it went
through damaged material -> (keep earlier splits apart) -> marching cubes -> Laplacian smoothing
-> connected components -> cluster id per particle -> ids consistent with the previous labels.

Every step runs as Warp kernels on ``device`` (CPU or CUDA); the inputs go up
once and the labels come back once.  In between, only scalars and per-piece
statistics cross to the host: the particle spacing and the number of carvers
(they size the grid and a hash grid), marching cubes' vertex and face counts,
the number of pieces, and K counts plus a K x L overlap matrix for the
Hungarian id matching.  Per-piece trimesh meshes are built only when
``TopologyResult.meshes`` is first read, so callers that need labels only
(planning, evaluation) never pay for them.  See docs/topology.md.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from topocut.sim.action import KnifeSweep
from topocut.topology.config import TopologyConfig
from topocut.topology.tracking import assign_ids

EXPORT_FORMATS = ("ply", "obj", "stl")
STEPS = ("sdf", "carve", "marching_cubes", "smoothing", "components", "assignment", "tracking")
MAX_DIRECT_IDS = 1 << 16  # previous ids up to this index the overlap matrix directly; larger ones are compacted


@dataclass
class PieceSurface:
    """The smoothed marching-cubes surface on the device and which piece each vertex belongs to."""

    verts: object  # warp vec3 (V,), smoothed
    faces: object  # warp int32 (3F,)
    vpiece: object  # warp int32 (V,), raw piece of each vertex (-1: dropped)
    id_of: np.ndarray  # K, persistent id of each raw piece (-1: none)
    counts: np.ndarray  # K, particles per raw piece

    def meshes(self) -> dict:
        import trimesh

        from topocut.topology.mesh import oriented

        v = self.verts.numpy().astype(np.float64).reshape(-1, 3)
        f = oriented(v, self.faces.numpy().astype(np.int64).reshape(-1, 3))
        fpiece = self.vpiece.numpy()[f[:, 0]]
        out = {}
        for k in range(len(self.id_of)):
            if self.id_of[k] < 0 or self.counts[k] == 0:
                continue  # a surface with no particles assigned to it (e.g. a thin shell) is no piece
            used, inv = np.unique(f[fpiece == k], return_inverse=True)
            out[int(self.id_of[k])] = trimesh.Trimesh(v[used], inv.reshape(-1, 3), process=False)
        return out


@dataclass
class TopologyResult:
    labels: np.ndarray  # N, int32 cluster id per particle (-1 = unassigned)
    num_clusters: int
    timings: dict = field(default_factory=dict)  # step -> seconds
    next_id: int = 0  # first id never used so far in the episode (pass it to the next discover call)
    surface: PieceSurface | None = field(default=None, repr=False)
    _meshes: dict | None = field(default=None, repr=False)

    @property
    def meshes(self) -> dict:
        """{id: trimesh.Trimesh}: smoothed closed surface of each piece (built on first access)."""
        if self._meshes is None:
            self._meshes = self.surface.meshes() if self.surface is not None else {}
        return self._meshes

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


def as_start_positions(start_positions, n: int) -> np.ndarray:
    """``start_positions`` as an (n,3) array, or a ValueError naming what does not match."""
    s = np.asarray(start_positions, np.float64)
    if s.shape != (n, 3):
        raise ValueError(f"start_positions must be ({n}, 3), the particles before the cut; got {s.shape}")
    return s


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


def _wall_owners(x, prev_idx: np.ndarray) -> np.ndarray:
    """Each particle's earlier piece for the walls between pieces; unlabelled particles (-1) take their nearest
    labelled particle's, since a node owned by -1 is walled against nothing and would join two pieces."""
    free = prev_idx < 0
    if not free.any() or free.all():
        return prev_idx
    from scipy.spatial import cKDTree

    owners = prev_idx.copy()
    labelled = np.flatnonzero(~free)
    owners[free] = prev_idx[labelled[cKDTree(x[labelled]).query(x[free])[1]]]
    return owners


def scene_grid(lo, hi, r: float, cfg: TopologyConfig):
    """The grid (sdf.Grid) of a scene whose particles span [lo, hi], of radius r: padded by r and
    padding + band voxels (discover; discover_batch places each scene's own grid on its shared lattice)."""
    from topocut.topology.sdf import make_grid

    pad = cfg.padding_voxels + cfg.band_voxels
    extent = float((np.asarray(hi) - np.asarray(lo)).max()) + 2 * r
    if cfg.voxel_size is None:
        h_est = extent / max(cfg.resolution - 1 - 2 * pad, 1)
    else:
        h_est = max(cfg.voxel_size, extent / max(cfg.max_resolution - 1 - 2 * pad, 1))
    return make_grid(lo, hi, r + pad * h_est, cfg.resolution, cfg.voxel_size, cfg.max_resolution)


def _previous(previous_labels, n: int, preserve_splits: bool, max_direct: int = MAX_DIRECT_IDS):
    """-> (prev (N,) int64 or None, column index per particle (N,) int32, old ids (L,) or None, used, split).

    Ids up to ``max_direct`` index the overlap matrix's columns directly, larger ones are compacted (the
    same pieces and ids either way: only columns that no particle holds drop out)."""
    if previous_labels is None:
        return None, None, None, 0, False
    prev = np.asarray(previous_labels).reshape(-1).astype(np.int64)
    if prev.shape[0] != n:
        raise ValueError(f"previous_labels has {prev.shape[0]} entries, positions has {n}")
    used = int(prev.max()) + 1 if n else 0
    old = prev[prev >= 0]
    split = preserve_splits and old.size > 0 and old.min() != old.max()  # several earlier pieces
    if used <= max_direct:
        return prev, prev.astype(np.int32), None, used, split
    old_ids, col = np.unique(old, return_inverse=True)  # huge ids: compact them for the overlap matrix
    idx = np.full(n, -1, np.int32)
    idx[prev >= 0] = col.ravel()
    return prev, idx, old_ids, used, split


class StepClock:
    """``lap(step)`` books the time since the last lap under ``step`` in ``timings``.  The device runs ahead of
    Python: with ``sync`` (topology.step_timings) each lap waits for it, so each step gets its own time."""

    def __init__(self, device: str, sync: bool):
        self.device, self.sync = device, sync
        self.timings: dict[str, float] = {}
        self.started = self.t = time.perf_counter()

    def __call__(self, name: str) -> None:
        if self.sync:
            import warp as wp

            wp.synchronize_device(self.device)
        now = time.perf_counter()
        self.timings[name] = self.timings.get(name, 0.0) + now - self.t
        self.t = now


def particles(positions, damage) -> tuple[np.ndarray, np.ndarray]:
    """(positions (N,3) float32/64, damage (N,) bool; None: undamaged), checked against each other."""
    x = np.asarray(positions)
    x = (x if x.dtype in (np.float32, np.float64) else x.astype(np.float64)).reshape(-1, 3)  # N,3
    dmg = np.zeros(len(x), bool) if damage is None else np.asarray(damage, bool).reshape(-1)
    if dmg.shape[0] != len(x):
        raise ValueError(f"damage has {dmg.shape[0]} entries, positions has {len(x)}")
    return x, dmg


def surface_and_pieces(sdf, grid, cfg: TopologyConfig, device: str, lap):
    """The carved SDF -> (smoothed vertices, faces, pieces, raw piece of each vertex): tiny voids filled,
    marching cubes, Laplacian smoothing, pieces = inside-node components united with mesh components.
    ``lap(step)`` books each step's time (discover and discover_batch share this middle)."""
    import warp as wp

    from topocut.topology import components as CC
    from topocut.topology import mesh as M

    CC.fill_voids(sdf, cfg.max_void_voxels, -0.5 * grid.h, device)
    lap("carve")
    verts, faces = M.extract_surface(sdf, grid, device)
    nv = verts.shape[0]
    lap("marching_cubes")
    verts_s = M.smooth(verts, M.vertex_adjacency(faces, nv, device), cfg.smoothing_iterations,
                       cfg.smoothing_alpha, device) if nv else verts
    lap("smoothing")
    vnode = M.vertex_inside_nodes(verts, sdf, grid, device)
    pieces = CC.label_pieces(sdf, faces, vnode, nv, cfg.min_component_voxels, device)
    vpiece = wp.clone(pieces.labels[pieces.num_nodes:]) if nv else wp.zeros(0, dtype=wp.int32, device=device)
    lap("components")
    return verts_s, faces, pieces, vpiece


def discover(positions, damage, knife_sweep, previous_labels=None, cfg: TopologyConfig | None = None,
             device: str = "cpu", next_id: int | None = None, start_positions=None) -> TopologyResult:
    """Cluster id per particle after a cut.  positions (N,3), damage (N,) bool; see module docstring.

    ``start_positions`` (N,3) or None: where the particles were when the cut's blade started (the state before
    the cut); a particle left in the kerf keeps the side of the blade it had there (docs/topology.md, step 9)."""
    import warp as wp

    from topocut.topology import assign as A
    from topocut.topology import carve as C
    from topocut.topology import sdf as S

    cfg = (cfg or TopologyConfig()).validate()
    device = S.resolve_device(device)
    lap = StepClock(device, cfg.step_timings)
    timings, t_all = lap.timings, lap.started

    x, dmg = particles(positions, damage)  # N,3 and N,
    if cfg.carve_through == "swept":  # every particle by the sweep licenses its carving (the simulator's rule)
        dmg = np.ones_like(dmg)
    n = len(x)
    prev, prev_idx, old_ids, used, split = _previous(previous_labels, n, cfg.preserve_splits)
    if n == 0:
        return TopologyResult(np.zeros(0, np.int32), 0, {"total": 0.0}, int(max(next_id or 0, used)))
    sweeps = as_sweeps(knife_sweep)
    starts = None if start_positions is None else as_start_positions(start_positions, n)
    num_old = (used if old_ids is None else len(old_ids)) if prev is not None else 0

    # --- grid + SDF (inputs go up once) -----------------------------------------------------------
    # per column: numpy's axis-0 min of an (N, 3) array takes a slow strided path (0.9 ms at 22k points,
    # 25x the column-wise form), a tenth of the whole call on the GPU
    lo = np.array([x[:, i].min() for i in range(3)], np.float64)
    hi = np.array([x[:, i].max() for i in range(3)], np.float64)
    xd = wp.array(np.ascontiguousarray(x, np.float32), dtype=wp.vec3, device=device)  # N
    prev_d = wp.array(prev_idx, dtype=wp.int32, device=device) if prev is not None else None  # N
    r = float(cfg.particle_radius) if cfg.particle_radius is not None else \
        cfg.radius_factor * max(S.particle_spacing(xd, lo, hi, device), 1e-6)
    grid = scene_grid(lo, hi, r, cfg)
    h = grid.h
    walls = None
    if split:  # wall owners: an unlabelled particle (-1) between two earlier pieces must not bridge their wall
        owners = _wall_owners(x, prev_idx)
        walls = prev_d if owners is prev_idx else wp.array(owners, dtype=wp.int32, device=device)
    sdf = S.particle_sdf(xd, r, grid, cfg.band_voxels * h, device, walls)  # nx,ny,nz
    lap("sdf")

    # --- board clip, knife carving through damaged material, tiny voids ---------------------------
    carve_radius = cfg.carve_radius if cfg.carve_radius is not None else 3.0 * r
    min_half = 0.5 * cfg.min_gap_voxels * h
    gap_half = max([max(s.half_thickness, min_half) for s in sweeps], default=0.0)
    carving = cfg.carve and bool(sweeps) and bool(dmg.any())
    dmg_d = wp.array(dmg.astype(np.int32), dtype=wp.int32, device=device) if carving else None
    snapped = [snap_to_board(s, cfg.board_z, cfg.board_snap_voxels * h) for s in sweeps]
    # (the carvers' hash grid is kept until this function returns: kernels may still be queued)
    _, carvers_grid = C.carve_and_clip(sdf, grid, xd, dmg_d, sweeps if carving else [],
                                       snapped if carving else [], carve_radius, min_half, cfg.board_z, device)
    verts_s, faces, pieces, vpiece = surface_and_pieces(sdf, grid, cfg, device, lap)
    nv, k = verts_s.shape[0], pieces.count

    # --- particles -> pieces ----------------------------------------------------------------------
    tau = cfg.tau if cfg.tau is not None else 2.0 * r + gap_half
    raw = A.node_pieces(xd, grid, pieces.labels, device)
    raw = A.surface_fallback(xd, raw, verts_s, vpiece, k, tau, (np.asarray(grid.shape) - 1) * h,
                             prev_d if split else None, num_old, device, sweeps=snapped if carving else [],
                             min_half_thickness=min_half, min_held=cfg.min_piece_particles,
                             start=starts if carving else None)
    counts, sum_x, overlap = A.piece_stats(xd, raw, k, prev_d, num_old, device)
    if split:  # a cut never joins pieces (the walls' promise, checked)
        raw, k, added = A.keep_earlier_splits(raw, overlap, prev_d, cfg.min_piece_particles, device)
        if len(added):
            counts, sum_x, overlap = A.piece_stats(xd, raw, k, prev_d, num_old, device)
    small = (counts > 0) & (counts < cfg.min_piece_particles)
    if small.any() and (counts >= cfg.min_piece_particles).any():
        raw = A.absorb_chips(xd, raw, small, device)
        counts, sum_x, overlap = A.piece_stats(xd, raw, k, prev_d, num_old, device)
    lap("assignment")

    # --- persistent ids ---------------------------------------------------------------------------
    id_of, nxt = assign_ids(counts, sum_x, overlap, used, next_id, old_ids=old_ids)
    labels = A.ids_of_pieces(raw, id_of, device).numpy().astype(np.int32)  # the one N-sized read-back
    lap("tracking")
    timings["total"] = time.perf_counter() - t_all
    surface = PieceSurface(verts_s, faces, vpiece, id_of, counts) if nv else None
    return TopologyResult(labels, int((counts > 0).sum()), timings, int(nxt), surface)

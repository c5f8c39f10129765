"""One topology discovery for a batch of scenes (MPPI's rollouts: 16 scenes per simulated cut).

A discover() call costs milliseconds of kernel launches and host syncs whatever its scene's size; a batch pays
them once.  The scenes are tiled side by side along x in ONE grid: scene b is translated so that its own grid
(the one discover() builds, ``discover.scene_grid``) lands on the shared lattice at tile b, ``tile_nodes``
apart, with empty nodes between tiles beyond every reach (the SDF splat, tau, carve_radius).  Every step
(SDF, walls, carving, voids, marching cubes, smoothing, pieces, particles -> pieces) then runs once over the
whole volume, and the labels come back in one read-back.

Shared by all scenes, so that scene b equals ``discover(x_b, damage_b, sweeps_b, prev_b, cfg_b, device,
next_id_b)`` with ``cfg_b = replace(cfg, voxel_size=h, particle_radius=r)``:

- the voxel size h: the largest any scene alone would get (no scene is discovered finer than alone); every
  scene's grid is then scene_grid(...) under cfg_b, so its shape and lower corner are discover()'s exactly;
- the particle radius r: cfg.particle_radius, else radius_factor x the particle spacing estimated once over all
  scenes' particles (laid out apart, so that no particle's neighbours come from another scene).

Kept per scene (nothing leaks across tiles): a knife sweep (its box may reach far beyond its object) licenses
carvers and carves nodes of its own scene only, against its scene's board height (carve.Tiles); previous labels
become overlap columns of their own, so walls and the overlap matrix never mix scenes, and a scene without
earlier splits gets no walls; tau, the chip rule (a chip joins a piece of its own scene), the surface
fallback's preference for a particle's earlier cluster, and the id matching (assign_ids on the scene's own
pieces and columns, its used / next_id).  Centroids are summed in translated coordinates: the scene's shift is
taken off before the tie-break.  Up to float32 rounding of the translation (~1e-7 of the coordinates), every
value is discover()'s.

Results are labels only (TopologyResult.surface is None): planning scores point sets and needs no meshes.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
import warp as wp

from topocut.topology.config import TopologyConfig
from topocut.topology.discover import (
    MAX_DIRECT_IDS,
    StepClock,
    TopologyResult,
    _previous,
    _wall_owners,
    as_start_positions,
    as_sweeps,
    particles,
    scene_grid,
    snap_to_board,
    surface_and_pieces,
)
from topocut.topology.sdf import Grid
from topocut.topology.tracking import assign_ids

GAP_NODES = 2  # empty nodes between two tiles beyond the farthest reach of any step


@wp.kernel
def _shift_scenes(x: wp.array(dtype=wp.vec3), scene: wp.array(dtype=wp.int32), shift: wp.array(dtype=wp.vec3),
                  out: wp.array(dtype=wp.vec3)):
    p = wp.tid()
    out[p] = x[p] + shift[scene[p]]


@wp.kernel
def _tile_of_pieces(piece: wp.array(dtype=wp.int32), tile_size: int, tile: wp.array(dtype=wp.int32)):
    # tile_size consecutive flat node indices per tile; all nodes of a piece lie in one tile, so racing writes agree
    i = wp.tid()
    k = piece[i]
    if k >= 0:
        tile[k] = i // tile_size


@dataclass
class _Scene:
    """One scene's host-side inputs, parsed as discover() parses them."""

    x: np.ndarray  # n,3
    dmg: np.ndarray  # n, bool
    sweeps: list
    prev: np.ndarray | None  # n, int64 previous ids
    col: np.ndarray | None  # n, int32 overlap column of each particle (-1 none)
    old_ids: np.ndarray | None  # L, id of each column (None: the column is the id)
    used: int
    split: bool
    next_id: int | None
    lo: np.ndarray  # 3,
    hi: np.ndarray  # 3,
    start: np.ndarray | None = None  # n,3 where the particles were when the cut's blade started (None: unknown)

    @property
    def num_old(self) -> int:
        return (self.used if self.old_ids is None else len(self.old_ids)) if self.prev is not None else 0


def _scene(positions, damage, knife_sweep, previous, next_id, cfg: TopologyConfig, max_direct: int) -> _Scene:
    x, dmg = particles(positions, damage)  # N,3 and N,
    if cfg.carve_through == "swept":  # every particle by the sweep licenses its carving (discover's rule)
        dmg = np.ones_like(dmg)
    n = len(x)
    prev, col, old_ids, used, split = _previous(previous, n, cfg.preserve_splits, max_direct)
    # per column, as discover() (numpy's axis-0 min of an (N, 3) array is slow): the same bounds, the same grid
    lo = np.array([x[:, i].min() for i in range(3)], np.float64) if n else np.zeros(3)
    hi = np.array([x[:, i].max() for i in range(3)], np.float64) if n else np.zeros(3)
    return _Scene(x, dmg, as_sweeps(knife_sweep), prev, col, old_ids, used, split, next_id, lo, hi)


def _shifted(xw, scene_d, shift: np.ndarray, device):
    """The particles (warp vec3 (N,)) with scene s moved by shift[s] (B,3)."""
    out = wp.empty_like(xw)
    sh = wp.array(np.asarray(shift, np.float32), dtype=wp.vec3, device=device)
    wp.launch(_shift_scenes, dim=xw.shape[0], inputs=[xw, scene_d, sh, out], device=device)
    return out


def _radius(scenes: list, xw, scene_d, cfg: TopologyConfig, device) -> float:
    """cfg.particle_radius, else radius_factor x the median 3rd-neighbour distance over all scenes' particles."""
    from topocut.topology.sdf import particle_spacing

    if cfg.particle_radius is not None:
        return float(cfg.particle_radius)
    ext = np.array([s.hi - s.lo for s in scenes])  # B,3
    # scenes two largest extents apart along x: farther than any scene's diameter (sqrt(3) x its extent),
    # so a particle's 3 nearest neighbours are its own scene's (a scene of 4 particles or more)
    gap = 2.0 * max(float(ext.max()), 1e-3)
    start = np.concatenate([[0.0], np.cumsum(ext[:-1, 0] + gap)])  # B,
    shift = np.stack([start - [s.lo[0] for s in scenes], [-s.lo[1] for s in scenes], [-s.lo[2] for s in scenes]], 1)
    hi = np.array([start[-1] + ext[-1, 0], ext[:, 1].max(), ext[:, 2].max()])
    spacing = particle_spacing(_shifted(xw, scene_d, shift, device), np.zeros(3), hi, device)
    return cfg.radius_factor * max(spacing, 1e-6)


def _shared_grids(scenes: list, r: float, cfg: TopologyConfig) -> tuple[float, list[Grid]]:
    """(h, each scene's grid under voxel_size=h): h the largest voxel size a scene alone gets, and a fixed
    point of scene_grid (a voxel size below max_resolution's bound comes back larger: take that one)."""
    h = max(scene_grid(s.lo, s.hi, r, cfg).h for s in scenes)
    for attempt in range(4):
        grids = [scene_grid(s.lo, s.hi, r, replace(cfg, voxel_size=h)) for s in scenes]
        worst = max(g.h for g in grids)
        if worst == h:
            return h, grids
        h = worst * (1.0 + 1e-12 * attempt)  # (a float tie at max_resolution: a hair more is a fixed point)
    raise RuntimeError(f"discover_batch: no common voxel size for {len(scenes)} scenes near {h}")


def _layout(grids: list[Grid], h: float, reach: float) -> tuple[Grid, np.ndarray, int]:
    """(the tiled grid, shift (B,3) that puts scene b's grid at tile b, tile width in nodes)."""
    b = len(grids)
    width = max(g.shape[0] for g in grids) + int(np.ceil(reach / h)) + GAP_NODES
    ny, nz = max(g.shape[1] for g in grids), max(g.shape[2] for g in grids)
    # tiles centred on the scenes' mean x: translated coordinates stay small (float32 rounding of the shift)
    lower = np.array([np.mean([g.lower[0] for g in grids]) - (b // 2) * width * h,
                      min(g.lower[1] for g in grids), min(g.lower[2] for g in grids)])
    shift = np.array([lower + [i * width * h, 0.0, 0.0] - g.lower for i, g in enumerate(grids)])  # B,3
    return Grid(lower, h, (b * width, ny, nz)), shift, width


def _upload(scenes: list, device):
    """(particles (N,) vec3 untranslated, scene of each (N,) int32, start (B + 1,): scene s is start[s]..)."""
    counts = [len(s.x) for s in scenes]
    start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    x = np.concatenate([np.asarray(s.x, np.float32) for s in scenes])  # N,3
    scene = np.repeat(np.arange(len(scenes), dtype=np.int32), counts)  # N,
    return (wp.array(x, dtype=wp.vec3, device=device), wp.array(scene, dtype=wp.int32, device=device), start)


def batch_scale(positions: list, cfg: TopologyConfig | None = None, device: str = "cpu") -> tuple[float, float]:
    """(voxel_size h, particle_radius r) that discover_batch shares over these scenes (empty ones aside)."""
    from topocut.topology.sdf import resolve_device

    cfg = (cfg or TopologyConfig()).validate()
    device = resolve_device(device)
    scenes = [s for s in (_scene(x, None, None, None, None, cfg, MAX_DIRECT_IDS) for x in positions) if len(s.x)]
    if not scenes:
        raise ValueError("batch_scale: every scene is empty")
    xw, scene_d, _ = _upload(scenes, device)
    r = _radius(scenes, xw, scene_d, cfg, device)
    return _shared_grids(scenes, r, cfg)[0], r


def discover_batch(positions: list, damages: list, sweeps: list, previous_labels: list,
                   cfg: TopologyConfig | None = None, device: str = "cpu",
                   next_ids: list | None = None, start_positions: list | None = None) -> list[TopologyResult]:
    """discover() for B scenes in one pass: lists (B,) of positions (N_b,3), damage (N_b,) bool or None, knife
    sweeps (anything discover takes), previous labels (N_b,) or None, next ids or None, the positions before
    the cut (N_b,3) or None (discover's ``start_positions``).  See module docstring."""
    from topocut.topology import sdf as S

    cfg = (cfg or TopologyConfig()).validate()
    device = S.resolve_device(device)
    nb = len(positions)
    next_ids = [None] * nb if next_ids is None else list(next_ids)
    if not len(damages) == len(sweeps) == len(previous_labels) == len(next_ids) == nb:
        raise ValueError(f"discover_batch: {nb} positions but {len(damages)} damages, {len(sweeps)} sweeps, "
                         f"{len(previous_labels)} previous labels and {len(next_ids)} next ids")
    lap = StepClock(device, cfg.step_timings)  # as discover()
    timings, t_all = lap.timings, lap.started

    # overlap columns: each scene's ids index them directly up to its share of MAX_DIRECT_IDS
    every = [_scene(positions[b], damages[b], sweeps[b], previous_labels[b], next_ids[b], cfg,
                    MAX_DIRECT_IDS // max(nb, 1)) for b in range(nb)]
    if start_positions is not None:
        if len(start_positions) != nb:
            raise ValueError(f"discover_batch: {nb} positions but {len(start_positions)} start positions")
        for s, st in zip(every, start_positions):
            s.start = None if st is None else as_start_positions(st, len(s.x))
    results: list = [None] * nb
    for b, s in enumerate(every):
        if not len(s.x):  # as discover(): no particles, no pieces
            results[b] = TopologyResult(np.zeros(0, np.int32), 0, {"total": 0.0}, int(max(s.next_id or 0, s.used)))
    live = [b for b in range(nb) if results[b] is None]
    if not live:
        return results
    labels, found, sl = _discover_tiled([every[b] for b in live], cfg, device, lap)
    timings["total"] = time.perf_counter() - t_all
    for i, b in enumerate(live):
        results[b] = TopologyResult(labels[sl[i]], found[i][0], dict(timings), found[i][1])
    return results


def _discover_tiled(scenes: list, cfg: TopologyConfig, device, lap) -> tuple[np.ndarray, list, list]:
    """(labels (N,) of all the scenes' particles, (pieces found, next id) per scene, each scene's slice of the
    labels): the non-empty scenes discovered side by side in one grid (module docstring)."""
    from topocut.topology import assign as A
    from topocut.topology import sdf as S

    n_sc = len(scenes)
    # --- shared scale, tiles, translated particles (inputs go up once) ---------------------------
    xw, scene_d, start = _upload(scenes, device)
    r = _radius(scenes, xw, scene_d, cfg, device)
    h, grids = _shared_grids(scenes, r, cfg)
    carve_radius = cfg.carve_radius if cfg.carve_radius is not None else 3.0 * r
    min_half = 0.5 * cfg.min_gap_voxels * h
    taus = [cfg.tau if cfg.tau is not None else
            2.0 * r + max([max(w.half_thickness, min_half) for w in s.sweeps], default=0.0) for s in scenes]
    grid, shift, tile_nodes = _layout(grids, h, max(r + cfg.band_voxels * h, max(taus), carve_radius))
    xd = _shifted(xw, scene_d, shift, device)  # N, on the tiles
    n = int(start[-1])
    sl = [slice(int(start[i]), int(start[i + 1])) for i in range(n_sc)]

    # previous labels: scene i's columns follow scene i-1's; walls and the fallback's owners per scene
    offset = np.concatenate([[0], np.cumsum([s.num_old for s in scenes])]).astype(np.int64)
    num_old = int(offset[-1])
    prev_d, walls_d, owner_d = _previous_columns(scenes, sl, offset, n, device)
    sdf = S.particle_sdf(xd, r, grid, cfg.band_voxels * h, device, walls_d)  # nx,ny,nz
    lap("sdf")

    # --- board clip, knife carving through damaged material, tiny voids ---------------------------
    # (what the carvers' kernels use is kept until this function returns: kernels may still be queued)
    _carving = _carve(sdf, grid, xd, scenes, sl, shift, scene_d, tile_nodes, carve_radius, min_half, h, cfg, device)
    # --- surface and pieces: no piece crosses a tile (empty nodes between), so each has one scene -----
    verts_s, faces, pieces, vpiece = surface_and_pieces(sdf, grid, cfg, device, lap)
    k = pieces.count
    tile_d = wp.zeros(max(k, 1), dtype=wp.int32, device=device)
    wp.launch(_tile_of_pieces, dim=grid.size, inputs=[pieces.labels, tile_nodes * grid.shape[1] * grid.shape[2],
                                                      tile_d], device=device)
    tile = tile_d.numpy()[:k]  # K, scene of each piece (booked with the assignment)

    # --- particles -> pieces (the gap exceeds every tau: a particle finds no other scene's surface) ----
    raw = A.node_pieces(xd, grid, pieces.labels, device)
    carved, carved_scene = _carving[3], _carving[1].sweep_scene
    started = None  # where the blade started, on the tiles (a scene without them: its particles where they are now)
    if carved and any(s.start is not None for s in scenes):
        started = _shifted(wp.array(np.concatenate([np.asarray(s.x if s.start is None else s.start, np.float32)
                                                    for s in scenes]), dtype=wp.vec3, device=device),
                           scene_d, shift, device)
    raw = A.surface_fallback(xd, raw, verts_s, vpiece, k, max(taus), (np.asarray(grid.shape) - 1) * h, owner_d,
                             num_old, device, scene=scene_d, scene_tau=taus, sweeps=carved,
                             min_half_thickness=min_half, sweep_scene=carved_scene, min_held=cfg.min_piece_particles,
                             start=started)
    counts, sum_x, overlap = A.piece_stats(xd, raw, k, prev_d, num_old, device)
    if any(s.split for s in scenes):  # a cut never joins pieces (the walls' promise, checked), scene by scene
        raw, k, added = A.keep_earlier_splits(raw, overlap, prev_d, cfg.min_piece_particles, device,
                                              allowed=np.array([scenes[t].split for t in tile], bool))
        if len(added):
            tile = np.concatenate([tile, tile[added]])
            counts, sum_x, overlap = A.piece_stats(xd, raw, k, prev_d, num_old, device)
    small = (counts > 0) & (counts < cfg.min_piece_particles)
    big = np.zeros(n_sc, bool)
    big[tile[counts >= cfg.min_piece_particles]] = True
    small &= big[tile]  # chips only in a scene that has a larger piece for them to join
    if small.any():
        raw = A.absorb_chips(xd, raw, small, device, scene=scene_d, start=start)
        counts, sum_x, overlap = A.piece_stats(xd, raw, k, prev_d, num_old, device)
    lap("assignment")

    id_of, found = _track(scenes, tile, counts, sum_x, overlap, offset, shift)
    labels = A.ids_of_pieces(raw, id_of, device).numpy().astype(np.int32)  # the one N-sized read-back
    lap("tracking")
    return labels, found, sl


def _previous_columns(scenes: list, sl: list, offset: np.ndarray, n: int, device) -> tuple:
    """(overlap column of each particle, its wall owner, its surface fallback owner), each (N,) int32 on the
    device or None: scene i's columns follow scene i-1's (``offset``)."""
    prev_d = walls_d = owner_d = None
    if any(s.prev is not None for s in scenes):
        col = np.full(n, -1, np.int32)  # N,
        for i, s in enumerate(scenes):
            if s.prev is not None:
                col[sl[i]] = np.where(s.col >= 0, s.col + offset[i], -1)
        prev_d = wp.array(col, dtype=wp.int32, device=device)
    if any(s.split for s in scenes):
        walls = np.full(n, -1, np.int32)  # N, owner -1: walled against nothing (a scene without splits)
        owner = col.copy()  # N, owner -2: no earlier cluster to prefer in the surface fallback
        for i, s in enumerate(scenes):
            if s.split:
                o = _wall_owners(s.x, s.col)
                walls[sl[i]] = np.where(o >= 0, o + offset[i], -1)
            else:
                owner[sl[i]] = -2
        walls_d = wp.array(walls, dtype=wp.int32, device=device)
        owner_d = wp.array(owner, dtype=wp.int32, device=device)
    return prev_d, walls_d, owner_d


def _carve(sdf, grid, xd, scenes: list, sl: list, shift: np.ndarray, scene_d, tile_nodes: int, carve_radius: float,
           min_half: float, h: float, cfg: TopologyConfig, device) -> tuple:
    """Carve each scene's knife sweeps through its damaged material, clip the board, fill tiny voids (``sdf`` in
    place; carve.Tiles keeps every sweep to its own scene).  Returns what the kernels use, for the caller to keep
    until they have run (the damage, the tiles, the carvers' hash grid), and the carved sweeps (on the tiles)."""
    from topocut.topology import carve as C

    licence, carved, sweep_scene = [], [], []
    dmg = np.zeros(xd.shape[0], np.int32)  # N,
    for i, s in enumerate(scenes):
        if not (cfg.carve and s.sweeps and s.dmg.any()):
            continue
        dmg[sl[i]] = s.dmg
        move = tuple(shift[i])
        for w in s.sweeps:  # snapped to the scene's own board before the move
            licence.append(_moved(w, move))
            carved.append(_moved(snap_to_board(w, cfg.board_z, cfg.board_snap_voxels * h), move))
            sweep_scene.append(i)
    dmg_d = wp.array(dmg, dtype=wp.int32, device=device) if licence else None
    tiles = C.Tiles(scene_d, np.asarray(sweep_scene, np.int32), tile_nodes, shift[:, 2])
    _, carvers_grid = C.carve_and_clip(sdf, grid, xd, dmg_d, licence, carved, carve_radius, min_half, cfg.board_z,
                                       device, tiles)
    return dmg_d, tiles, carvers_grid, carved


def _track(scenes: list, tile: np.ndarray, counts, sum_x, overlap, offset: np.ndarray, shift: np.ndarray) -> tuple:
    """(persistent id of each piece (K,), (pieces found, next id) per scene): scene by scene, its pieces (rows, in
    discover()'s order) and its overlap columns."""
    id_of = np.full(len(tile), -1, np.int64)
    found = []
    for i, s in enumerate(scenes):
        rows = np.flatnonzero(tile == i)
        ov = overlap[rows, offset[i]:offset[i + 1]] if s.prev is not None else None
        sx = sum_x[rows] - shift[i, 0] * counts[rows]  # the centroids' tie-break in the scene's own frame
        id_of[rows], nxt = assign_ids(counts[rows], sx, ov, s.used, s.next_id, old_ids=s.old_ids)
        found.append((int((counts[rows] > 0).sum()), int(nxt)))
    return id_of, found


def _moved(s, move: tuple):
    """The sweep translated by ``move`` (3,)."""
    return replace(s, origin=tuple(float(o) + float(m) for o, m in zip(s.origin, move)))

"""Carve the knife's swept path into the SDF where it went through damaged material; clip at the board.

One pass over the grid nodes: ``sdf = max(sdf, board_z - z)`` (nothing below
the board's top face is material) and, at nodes inside a sweep box that lie
within ``carve_radius`` of a *carver* (a damaged particle within
``carve_radius`` of a sweep), ``sdf = max(sdf, -box_sdf)``.  The carvers are
flagged and packed on the device (an atomic counter gives each its slot; only
their count is read back, to build a hash grid over them).

``Tiles`` (discover_batch: several scenes side by side along x in one grid) gives every particle, sweep and
carver a scene and every node the scene of its tile: a sweep licenses carvers and carves nodes of its own
scene only, and each scene has its own board height.  Without it (discover) everything is scene 0.
"""
# ruff: noqa: UP018  (int(0), float(...) declare mutable Warp kernel variables; a bare literal is a constant)
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from topocut.topology.sdf import Grid, hash_grid, init_warp


@wp.func
def box_sdf(x: wp.vec3, o: wp.vec3, u: wp.vec3, w: wp.vec3, n: wp.vec3, half: wp.vec3):
    """Signed distance to a sweep box (KnifeSweep.sdf): half = (half_length, depth / 2, half_thickness)."""
    d = x - o
    q = wp.vec3(wp.abs(wp.dot(d, u)) - half[0], wp.abs(wp.dot(d, w) - half[1]) - half[1],
                wp.abs(wp.dot(d, n)) - half[2])
    outside = wp.length(wp.vec3(wp.max(q[0], 0.0), wp.max(q[1], 0.0), wp.max(q[2], 0.0)))
    return outside + wp.min(wp.max(q[0], wp.max(q[1], q[2])), 0.0)


@dataclass
class Tiles:
    """Scenes side by side along x in one grid (discover_batch); node (i, j, k) lies in scene i // tile_nodes."""

    scene: object  # warp int32 (N,): each particle's scene
    sweep_scene: np.ndarray  # S, each sweep's scene (sweeps and carve_sweeps alike)
    tile_nodes: int
    board_shift: np.ndarray  # B, each scene's z translation: its board's top face is at board_z + shift


@wp.func
def scene_of(index: wp.array(dtype=wp.int32), i: int):
    # an empty (None) index: one scene, discover()'s; else the scene of element i (discover_batch's tiles)
    if index.shape[0] == 0:
        return 0
    return index[i]


@wp.func
def shift_of(shift: wp.array(dtype=float), s: int):
    if shift.shape[0] == 0:
        return 0.0
    return shift[s]


@wp.kernel
def _pack_carvers(x: wp.array(dtype=wp.vec3), damaged: wp.array(dtype=wp.int32), scene: wp.array(dtype=wp.int32),
                  frames: wp.array2d(dtype=wp.vec3), sweep_scene: wp.array(dtype=wp.int32), carve_radius: float,
                  count: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.vec3), out_scene: wp.array(dtype=wp.int32)):
    # frames[s] = (origin, u, w, n, half): the sweeps as the simulator reported them (not thickened)
    p = wp.tid()
    if damaged[p] == 0:
        return
    xp = x[p]
    sp = scene_of(scene, p)
    near = int(0)
    for s in range(frames.shape[0]):
        if scene_of(sweep_scene, s) == sp:  # another scene's knife (it may be longer than its object) never licenses
            if box_sdf(xp, frames[s, 0], frames[s, 1], frames[s, 2], frames[s, 3], frames[s, 4]) <= carve_radius:
                near = int(1)
    if near == 1:
        slot = wp.atomic_add(count, 0, 1)
        out[slot] = xp
        if out_scene.shape[0] > 0:
            out_scene[slot] = sp


@wp.kernel
def _carve(sdf: wp.array3d(dtype=float), lower: wp.vec3, h: float, board_z: float, has_board: int,
           board_shift: wp.array(dtype=float), tile_nodes: int, frames: wp.array2d(dtype=wp.vec3),
           sweep_scene: wp.array(dtype=wp.int32), num_sweeps: int, carvers: wp.uint64,
           pts: wp.array(dtype=wp.vec3), carver_scene: wp.array(dtype=wp.int32), carve_radius: float):
    i, j, k = wp.tid()
    sc = i // tile_nodes  # the scene whose tile holds this node
    x = lower + wp.vec3(float(i), float(j), float(k)) * h
    v = sdf[i, j, k]
    if has_board == 1:  # particle balls reach r below the board; clip them to its top face
        v = wp.max(v, board_z + shift_of(board_shift, sc) - x[2])
    near = int(-1)  # -1: not looked up yet; 0/1: is a carver within carve_radius of this node
    for s in range(num_sweeps):
        if scene_of(sweep_scene, s) != sc:
            continue
        box = box_sdf(x, frames[s, 0], frames[s, 1], frames[s, 2], frames[s, 3], frames[s, 4])
        if box < 0.0:
            if near < 0:  # the knife only separates where it went through damaged material
                near = int(0)
                query = wp.hash_grid_query(carvers, x, carve_radius)
                q = int(0)
                while wp.hash_grid_query_next(query, q):
                    if wp.length(pts[q] - x) <= carve_radius and scene_of(carver_scene, q) == sc:
                        near = int(1)
                        break
            if near == 1:
                v = wp.max(v, -box)
    sdf[i, j, k] = v


def sweep_frames(sweeps: list, min_half_thickness: float = 0.0, device: str = "cpu"):
    """(S,5) warp vec3 array: origin, u, w, n, (half_length, depth / 2, max(half_thickness, min))."""
    rows = []
    for s in sweeps:
        o, u, w, n = s.as_arrays()
        rows.append([o, u, w, n, [s.half_length, s.depth / 2.0, max(s.half_thickness, min_half_thickness)]])
    arr = np.asarray(rows, np.float32).reshape(-1, 5, 3)
    return wp.array(arr, dtype=wp.vec3, device=device)


def carve_and_clip(sdf, grid: Grid, x, damaged, sweeps: list, carve_sweeps: list, carve_radius: float,
                   min_half_thickness: float, board_z: float | None, device: str = "cpu",
                   tiles: Tiles | None = None) -> tuple:
    """Board clip and knife carving, in place on ``sdf`` (warp array3d).

    Returns (number of carvers, the hash grid): keep the grid alive until the device has synchronised.

    x: warp vec3 (N,), damaged: warp int32 (N,) or None.  ``sweeps`` decide
    which damaged particles license a carve (within ``carve_radius`` of a
    sweep); ``carve_sweeps`` (the same sweeps, snapped to the board) are
    carved, each thickened to at least ``min_half_thickness``.  ``tiles``: the scene of each particle, sweep and
    grid node, and each scene's board (discover_batch); None: one scene.
    """
    init_warp()
    n_carvers, pts, hg, hg_id = 0, wp.zeros(1, dtype=wp.vec3, device=device), None, wp.uint64(0)
    frames = wp.zeros((1, 5), dtype=wp.vec3, device=device)
    # None: every particle, sweep and carver is in scene 0 (scene_of), the one tile is the whole grid
    scene = sweep_scene = carver_scene = board_shift = None
    tile_nodes = grid.shape[0]
    if tiles is not None:
        scene, tile_nodes = tiles.scene, int(tiles.tile_nodes)
        board_shift = wp.array(np.asarray(tiles.board_shift, np.float32), dtype=float, device=device)
        if len(tiles.sweep_scene):
            sweep_scene = wp.array(np.asarray(tiles.sweep_scene, np.int32), dtype=wp.int32, device=device)
    if sweeps and damaged is not None:
        count = wp.zeros(1, dtype=wp.int32, device=device)
        packed = wp.empty(x.shape[0], dtype=wp.vec3, device=device)
        packed_scene = wp.empty(x.shape[0], dtype=wp.int32, device=device) if tiles is not None else None
        wp.launch(_pack_carvers, dim=x.shape[0], device=device,
                  inputs=[x, damaged, scene, sweep_frames(sweeps, 0.0, device), sweep_scene, float(carve_radius),
                          count, packed, packed_scene])
        n_carvers = int(count.numpy()[0])  # the hash grid needs the count
        if n_carvers:
            pts = packed[:n_carvers]
            carver_scene = packed_scene[:n_carvers] if packed_scene is not None else None
            hg = hash_grid(pts, carve_radius, (np.asarray(grid.shape) - 1) * grid.h, device)
            hg_id = hg.id
            frames = sweep_frames(carve_sweeps, min_half_thickness, device)
    wp.launch(_carve, dim=grid.shape, device=device,
              inputs=[sdf, grid.wp_lower, float(grid.h), float(board_z if board_z is not None else 0.0),
                      int(board_z is not None), board_shift, int(tile_nodes), frames, sweep_scene,
                      len(carve_sweeps) if n_carvers else 0, hg_id, pts, carver_scene, float(carve_radius)])
    return n_carvers, hg

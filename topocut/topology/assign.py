"""Particles -> pieces on the device: grid lookup, nearest-surface fallback, debris, per-piece statistics.

A particle takes the piece of its nearest grid node.  A particle whose node is
in no kept piece (the carved gap, a wall, debris) takes the piece of the
nearest smoothed-mesh vertex closer than tau (hash-grid query), preferring a
piece that came from its own previous cluster.  Pieces of fewer than
``min_piece_particles`` particles are chips: their particles join the piece of
the nearest particle in a larger piece.  All per-particle work is a kernel;
only per-piece counts (K values) come back to the host.

discover_batch passes each particle's scene (and per-scene tau and particle ranges): a particle's surface
fallback uses its own scene's tau, and a chip joins a piece of its own scene.  Without them (None), as in
discover(), every particle is in scene 0.
"""
# ruff: noqa: UP018  (int(0), float(...) declare mutable Warp kernel variables; a bare literal is a constant)
from __future__ import annotations

import numpy as np
import warp as wp

from topocut.topology.carve import box_sdf, scene_of, sweep_frames
from topocut.topology.sdf import Grid, hash_grid


@wp.kernel
def _node_pieces(x: wp.array(dtype=wp.vec3), lower: wp.vec3, h: float, nx: int, ny: int, nz: int,
                 piece: wp.array(dtype=wp.int32), raw: wp.array(dtype=wp.int32)):
    p = wp.tid()
    c = (x[p] - lower) / h
    i = wp.clamp(int(wp.round(c[0])), 0, nx - 1)
    j = wp.clamp(int(wp.round(c[1])), 0, ny - 1)
    k = wp.clamp(int(wp.round(c[2])), 0, nz - 1)
    raw[p] = piece[(i * ny + j) * nz + k]


@wp.kernel
def _origin_histogram(raw: wp.array(dtype=wp.int32), owner: wp.array(dtype=wp.int32), num_old: int,
                      hist: wp.array(dtype=wp.int32)):
    p = wp.tid()
    k = raw[p]
    o = owner[p]
    if k >= 0 and o >= 0:
        wp.atomic_add(hist, k * num_old + o, 1)


@wp.kernel
def _origin_argmax(hist: wp.array(dtype=wp.int32), num_old: int, origin: wp.array(dtype=wp.int32)):
    # the previous cluster most of a piece's particles came from (first on ties, as np.argmax); -1 if none
    k = wp.tid()
    best = int(-1)
    best_n = int(0)
    for o in range(num_old):
        c = hist[k * num_old + o]
        if c > best_n:
            best_n = c
            best = o
    origin[k] = best


@wp.func
def _blade_side(xp: wp.vec3, sp: int, frames: wp.array2d(dtype=wp.vec3), sweep_scene: wp.array(dtype=wp.int32)):
    # (sweep, side) of a particle inside a carved sweep box of its own scene: the side of the blade's plane it
    # lies on, +1 or -1, the rule the simulator's split cuts bonds by; (-1, 0) outside every box
    for s in range(frames.shape[0]):
        if scene_of(sweep_scene, s) == sp:
            if box_sdf(xp, frames[s, 0], frames[s, 1], frames[s, 2], frames[s, 3], frames[s, 4]) <= 0.0:
                if wp.dot(xp - frames[s, 0], frames[s, 3]) >= 0.0:
                    return wp.vec2i(s, 1)
                return wp.vec2i(s, -1)
    return wp.vec2i(-1, 0)


@wp.kernel
def _node_counts(raw: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32)):
    p = wp.tid()
    if raw[p] >= 0:
        wp.atomic_add(count, raw[p], 1)


@wp.kernel
def _nearest_surface_piece(x: wp.array(dtype=wp.vec3), raw: wp.array(dtype=wp.int32), hg: wp.uint64,
                           verts: wp.array(dtype=wp.vec3), vpiece: wp.array(dtype=wp.int32), tau: float,
                           scene: wp.array(dtype=wp.int32), scene_tau: wp.array(dtype=float),
                           use_origin: int, owner: wp.array(dtype=wp.int32), origin: wp.array(dtype=wp.int32),
                           frames: wp.array2d(dtype=wp.vec3), sweep_scene: wp.array(dtype=wp.int32),
                           start: wp.array(dtype=wp.vec3), held: wp.array(dtype=wp.int32), min_held: int,
                           out: wp.array(dtype=wp.int32)):
    # tau: the query radius; scene_tau (None: tau for all) the threshold of each scene, at most tau.
    # Preference, nearest first within each: a piece of the particle's own earlier cluster on its own side of
    # the blade (a particle inside a carved sweep), one of its own earlier cluster, a piece on its own side
    # holding >= min_held particles by their grid nodes (not a sliver of surface), the nearest piece.
    p = wp.tid()
    r = raw[p]
    out[p] = r
    if r >= 0:
        return
    xp = x[p]
    sp = scene_of(scene, p)
    o = int(-1)
    if use_origin == 1:
        o = owner[p]
    near = tau
    if scene_tau.shape[0] > 0:
        near = scene_tau[sp]
    side = _blade_side(xp, sp, frames, sweep_scene)
    if side[1] != 0 and start.shape[0] > 0:  # the side it was on when the blade started: the simulator's split's
        if wp.dot(start[p] - frames[side[0], 0], frames[side[0], 3]) >= 0.0:
            side = wp.vec2i(side[0], 1)
        else:
            side = wp.vec2i(side[0], -1)
    best = wp.vec2(-1.0, near)  # (piece, distance) per rank: any, own cluster, own side, own cluster and side
    same = wp.vec2(-1.0, near)
    sided = wp.vec2(-1.0, near)
    both = wp.vec2(-1.0, near)
    query = wp.hash_grid_query(hg, xp, tau)
    q = int(0)
    while wp.hash_grid_query_next(query, q):
        k = vpiece[q]
        if k >= 0:
            d = wp.length(verts[q] - xp)
            on_side = int(0)
            if side[1] != 0:
                if wp.dot(verts[q] - frames[side[0], 0], frames[side[0], 3]) * float(side[1]) >= 0.0:
                    on_side = int(1)
            own = int(0)
            if use_origin == 1:
                if origin[k] == o:  # a particle on the wall between two earlier pieces: its own earlier cluster
                    own = int(1)
            if d < best[1]:
                best = wp.vec2(float(k), d)
            if own == 1 and d < same[1]:
                same = wp.vec2(float(k), d)
            if on_side == 1 and held[k] >= min_held and d < sided[1]:
                sided = wp.vec2(float(k), d)
            if own == 1 and on_side == 1 and d < both[1]:
                both = wp.vec2(float(k), d)
    pick = best
    if sided[0] >= 0.0:
        pick = sided
    if same[0] >= 0.0:
        pick = same
    if both[0] >= 0.0:
        pick = both
    out[p] = int(pick[0])


@wp.kernel
def _piece_stats(x: wp.array(dtype=wp.vec3), raw: wp.array(dtype=wp.int32), prev: wp.array(dtype=wp.int32),
                 num_old: int, count: wp.array(dtype=wp.int32), sum_x: wp.array(dtype=float),
                 overlap: wp.array(dtype=wp.int32)):
    p = wp.tid()
    k = raw[p]
    if k < 0:
        return
    wp.atomic_add(count, k, 1)
    wp.atomic_add(sum_x, k, x[p][0])
    if num_old > 0:
        o = prev[p]
        if o >= 0:
            wp.atomic_add(overlap, k * num_old + o, 1)


@wp.kernel
def _absorb_chips(x: wp.array(dtype=wp.vec3), raw: wp.array(dtype=wp.int32), small: wp.array(dtype=wp.int32),
                  scene: wp.array(dtype=wp.int32), start: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.int32)):
    # brute force over the particles of the chip's scene (start[s]..start[s+1]; None: all particles), but only
    # for the few particles of chips (< min_piece_particles each)
    p = wp.tid()
    r = raw[p]
    out[p] = r
    if r < 0:
        return
    if small[r] == 0:
        return
    xp = x[p]
    first = int(0)
    last = x.shape[0]
    if start.shape[0] > 0:
        s = scene_of(scene, p)
        first = start[s]
        last = start[s + 1]
    best = float(1.0e30)
    for q in range(first, last):
        rq = raw[q]
        if rq >= 0:
            if small[rq] == 0:
                d = wp.length_sq(x[q] - xp)
                if d < best:
                    best = d
                    out[p] = rq


@wp.kernel
def _ids_of_pieces(raw: wp.array(dtype=wp.int32), id_of: wp.array(dtype=wp.int32), labels: wp.array(dtype=wp.int32)):
    p = wp.tid()
    r = raw[p]
    labels[p] = -1
    if r >= 0:
        labels[p] = id_of[r]


def node_pieces(x, grid: Grid, piece_labels, device: str = "cpu"):
    """Piece of each particle's nearest grid node (warp int32 (N,), -1 none)."""
    raw = wp.empty(x.shape[0], dtype=wp.int32, device=device)
    wp.launch(_node_pieces, dim=x.shape[0], inputs=[x, grid.wp_lower, float(grid.h), *grid.shape, piece_labels, raw],
              device=device)
    return raw


def surface_fallback(x, raw, verts, vpiece, num_pieces: int, tau: float, extent, owner=None, num_old: int = 0,
                     device: str = "cpu", scene=None, scene_tau=None, sweeps=(), min_half_thickness: float = 0.0,
                     sweep_scene=None, min_held: int = 1, start=None):
    """Particles with raw < 0 take the piece of the nearest vertex within tau (own earlier cluster first).

    ``sweeps`` (the carved KnifeSweeps, thickened to ``min_half_thickness``; ``sweep_scene`` each one's scene,
    None: all scene 0): a particle inside one prefers a piece on its own side of the blade's plane, as the
    simulator's split separates the two sides: first one of its own earlier cluster there, else (after its own
    cluster on either side) one holding >= ``min_held`` particles by their grid nodes, so that a sliver of
    surface in the kerf does not become a piece (docs/topology.md#the-kerf).  ``start`` ((N,3) array or warp vec3
    (N,), in the frame of ``x``): where each particle was when the blade started; its side there is the side the simulator's
    split gives it, so a particle the blade dragged across its plane keeps it.  None: the side of ``x``.
    scene (warp int32 (N,)) and scene_tau ((B,) floats): each particle's scene and each scene's tau instead
    (discover_batch; ``tau`` is then their maximum).  A particle whose owner is below -1 has no earlier
    cluster to prefer (a scene without splits in a batch where others have them)."""
    if num_pieces == 0 or verts.shape[0] == 0:
        return raw
    taus = None
    if scene_tau is not None:
        taus = wp.array(np.asarray(scene_tau, np.float32), dtype=float, device=device)
        tau = float(np.max(scene_tau))
    origin = wp.full(num_pieces, -1, dtype=wp.int32, device=device)
    use_origin = owner is not None and num_old > 0
    if use_origin:
        hist = wp.zeros(num_pieces * num_old, dtype=wp.int32, device=device)
        wp.launch(_origin_histogram, dim=x.shape[0], inputs=[raw, owner, num_old, hist], device=device)
        wp.launch(_origin_argmax, dim=num_pieces, inputs=[hist, num_old, origin], device=device)
    hg = hash_grid(verts, tau, extent, device)
    out = wp.empty_like(raw)
    frames = sweep_frames(list(sweeps), min_half_thickness, device) if len(sweeps) else \
        wp.zeros((0, 5), dtype=wp.vec3, device=device)
    sw_scene = None if sweep_scene is None or not len(sweeps) else \
        wp.array(np.asarray(sweep_scene, np.int32), dtype=wp.int32, device=device)
    if start is not None and not isinstance(start, wp.array):  # (N,3) positions on the host
        start = wp.array(np.ascontiguousarray(start, np.float32), dtype=wp.vec3, device=device)
    held = wp.zeros(num_pieces, dtype=wp.int32, device=device)  # K, particles each piece holds by grid node
    wp.launch(_node_counts, dim=x.shape[0], inputs=[raw, held], device=device)
    wp.launch(_nearest_surface_piece, dim=x.shape[0], device=device,
              inputs=[x, raw, hg.id, verts, vpiece, float(tau), scene, taus, int(use_origin),
                      owner if use_origin else raw, origin, frames, sw_scene, start, held, int(min_held), out])
    wp.synchronize_device(device)  # the hash grid is freed when this returns
    return out


def piece_stats(x, raw, num_pieces: int, prev=None, num_old: int = 0, device: str = "cpu"):
    """(count (K,) int, sum of x (K,) float, overlap (K, num_old) int with prev) as numpy: one read-back."""
    k = max(num_pieces, 1)
    count = wp.zeros(k, dtype=wp.int32, device=device)
    sum_x = wp.zeros(k, dtype=float, device=device)
    overlap = wp.zeros(max(k * num_old, 1), dtype=wp.int32, device=device)
    wp.launch(_piece_stats, dim=x.shape[0], device=device,
              inputs=[x, raw, prev if prev is not None else raw, num_old if prev is not None else 0,
                      count, sum_x, overlap])
    ov = overlap.numpy()[: num_pieces * num_old].reshape(num_pieces, num_old) if prev is not None else None
    return count.numpy()[:num_pieces], sum_x.numpy()[:num_pieces].astype(np.float64), ov


def absorb_chips(x, raw, small: np.ndarray, device: str = "cpu", scene=None, start=None):
    """Particles of the pieces flagged in ``small`` (K,) join the piece of their nearest particle elsewhere.

    scene (warp int32 (N,)) and start ((B + 1,) ints, scene s holds particles start[s]..start[s+1]): the
    nearest particle is sought in the chip's own scene only (discover_batch)."""
    flags = wp.array(np.asarray(small, np.int32), dtype=wp.int32, device=device)
    starts = None if start is None else wp.array(np.asarray(start, np.int32), dtype=wp.int32, device=device)
    out = wp.empty_like(raw)
    wp.launch(_absorb_chips, dim=x.shape[0], inputs=[x, raw, flags, scene if starts is not None else None, starts,
                                                     out], device=device)
    return out


def ids_of_pieces(raw, id_of: np.ndarray, device: str = "cpu"):
    """labels[p] = id_of[raw[p]] (-1 stays -1), as a warp int32 array."""
    ids = wp.array(np.asarray(id_of, np.int32) if len(id_of) else np.zeros(1, np.int32), dtype=wp.int32,
                   device=device)
    labels = wp.empty_like(raw)
    wp.launch(_ids_of_pieces, dim=raw.shape[0], inputs=[raw, ids, labels], device=device)
    return labels


def keep_earlier_splits(raw, overlap, col, min_particles: int, device: str = "cpu", allowed=None):
    """A cut never joins pieces: a piece found holding ``min_particles`` or more particles of each of two or more
    earlier clusters is split back along them (docs/topology.md, step 8).  The walls in the SDF already keep earlier
    pieces apart; this is the invariant checked on the result (one H200, 128^3: 3 of 10 batched episodes had a last
    cut's discovery join two earlier pieces that discovery on the CPU, from the same inputs, kept apart).

    raw (N,) warp int32 piece per particle; overlap (K, L) particles of piece k in earlier cluster (column) l;
    col (N,) column per particle (warp or numpy, -1: none); allowed (K,) bool or None: the pieces that may be split
    (a batch's scenes without earlier splits: not).  Returns (raw, K', origin (K' - K,) of each added piece): the
    largest earlier cluster keeps the piece, each other one becomes a piece of its own (smaller shares stay)."""
    K = overlap.shape[0] if overlap is not None else 0
    if not K:
        return raw, K, np.zeros(0, np.int64)
    big = overlap >= max(int(min_particles), 1)  # K,L
    bad = np.flatnonzero((big.sum(1) >= 2) & (np.ones(K, bool) if allowed is None else np.asarray(allowed, bool)))
    if not len(bad):
        return raw, K, np.zeros(0, np.int64)
    r = raw.numpy().copy()  # N, read back only when the invariant failed
    c = col.numpy() if hasattr(col, "numpy") else np.asarray(col)
    origin = []
    for k in bad:
        owners = np.flatnonzero(big[k])
        keep = owners[np.argmax(overlap[k, owners])]
        for o in owners[owners != keep]:
            r[(r == k) & (c == o)] = K + len(origin)
            origin.append(int(k))
    return wp.array(r, dtype=wp.int32, device=device), K + len(origin), np.asarray(origin, np.int64)

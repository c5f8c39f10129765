"""Pieces: which particles the knife has separated, and which velocity field each piece moves in.

Pure numpy/scipy, run on the host once per cut (not per substep); with sim.tuning.device_split
``pieces_device`` gives ``split``'s labels from Taichi kernels and ``fields_device`` the fields, sides and cut-off
side from per-piece summaries, coloured by this module's ``greedy_colour``.  docs/sim.md, "Pieces and contact":

- ``split``: a piece's particles stay connected where two neighbours (within ``LINK`` particle spacings)
  are joined by a segment that does not cross the knife's swept surface.  The swept surface is the blade
  plane's rectangle {|u.(q-o)| <= half_length, w.(q-o) <= depth}: everything the blade passed, from above the
  object down to where its edge stopped.  The connected components of what stays linked are the new pieces,
  so the split follows the blade's geometry wherever it falls relative to the grid, and a cut that stops
  short (or misses) leaves the piece whole.
- ``colour``: pieces whose particles can share a grid node take different velocity fields (a greedy
  colouring of the "shares a stencil node" graph), so MPMSolver keeps them apart: multi-velocity-field
  contact (Bardenhagen et al. 2000) lets them press on each other and slide, never pull.  Pieces by the
  blade on opposite sides of it take different fields too, so that every field there has one side.
- ``field_sides``: for each field, the side of the blade its pieces near the blade are on (+1, -1), or 0
  where that is mixed (an uncut piece the blade is inside): the knife pushes a field to its own side.
"""
from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

LINK = 1.6  # neighbours closer than this many particle spacings are bonded (jittered lattice: 1 .. 1.5)
MIN_PIECE = 8  # components with fewer particles are flakes: they join the nearest large piece
CENTRE_BAND = 0.01  # the blade centres on the particles within this distance of its plane [units]
REACH = 3  # pieces whose base cells lie within this many cells (Chebyshev) may share a node: colour apart


def blade_sweep(action, x: np.ndarray, cfg):
    """(KnifeSweep, depth, start origin o0) of ``action`` (a KnifeAction) cutting particles x (N,3) in a scene of
    SimConfig ``cfg``: the blade centred along its long axis on the material it cuts (the particles within
    ``CENTRE_BAND`` of its plane; all of them if none is), started ``knife_clearance`` above the highest
    particle, travelling to the board (or ``action.depth``).  CuttingEnv.cut and the ideal execution of a goal's
    steps (topocut.tasks.ideal) share it, so both separate exactly the same pieces.  x may be float32 (the
    simulator's own positions): the result is then that of x.astype(float64), without converting all of x."""
    from topocut.sim.action import KnifeSweep

    a = action.canonical()
    u, w, nrm = a.blade_axis, a.travel, a.normal
    p0 = a.plane_point(cfg.board_z)
    near = _in_band(x, p0, nrm, CENTRE_BAND)
    mid = near.mean(0) if len(near) else x.astype(np.float64, copy=False).mean(0)
    p0 = p0 + u * float(u @ (mid - p0))  # centre the blade on what it cuts: a slab set far aside is cut whole
    z_start = a.z_start if a.z_start is not None else float(x[:, 2].max()) + cfg.knife_clearance + cfg.margin
    t_board = max(z_start - cfg.board_z, 0.0) / -w[2]  # travel until the edge reaches the board
    depth = t_board if a.depth is None else min(max(a.depth, 0.0), t_board)
    o0 = p0 - w * t_board
    sweep = KnifeSweep(origin=tuple(map(float, o0)), u=tuple(map(float, u)), w=tuple(map(float, w)),
                       n=tuple(map(float, nrm)), half_length=cfg.knife_half_length + cfg.osc_amplitude,
                       depth=float(depth), half_thickness=cfg.knife_half_thickness + cfg.margin)
    return sweep, float(depth), o0


BAND_SLACK = {np.dtype(np.float64): 1e-9, np.dtype(np.float32): 4e-6}  # x @ n's rounding (1 + 2 |x|), far inside


def _in_band(x: np.ndarray, p0: np.ndarray, nrm: np.ndarray, band: float) -> np.ndarray:
    """The particles x (N,3) with |(x - p0) . nrm| <= band, as float64 (n,3) in their order in x, the dot product
    taken term by term in float64 (elementwise, so a particle's value does not depend on which others are tested
    with it; a float32's float64 is exact).

    Only the candidates of a cheap pass (x @ nrm in x's own precision against p0 . nrm, within a slack far above
    that pass's rounding) are tested exactly: a demonstration cut centres 48 blades on 69k particles each at
    128^3, and the full (N,3) difference was ~1 ms a blade on the host.  Rows are gathered with np.take (x[idx]
    on (N,3) rows took 5x as long: 0.17 ms for 4.7k).  float32's pass errs by < 6e-7 (1 + |x|): three products,
    two sums and the rounded normal, each within 2^-24."""
    if x.dtype not in BAND_SLACK:  # another dtype (float16, integers): its float64 copy, whose slack is known
        x = x.astype(np.float64)
    d = x @ nrm.astype(x.dtype)  # N: one pass, no (N,3) temporary
    reach = max(float(x.max(initial=0.0)), -float(x.min(initial=0.0)), float(np.abs(p0).max()))  # largest |coordinate|
    c, slack = float(p0 @ nrm), BAND_SLACK[x.dtype] * (1.0 + 2.0 * reach)
    keep = np.flatnonzero((d >= c - band - slack) & (d <= c + band + slack))  # a superset: the sums differ by rounding
    cand = np.take(x, keep, axis=0).astype(np.float64, copy=False)  # n,3
    r = cand - p0  # n,3
    return np.take(cand, np.flatnonzero(np.abs(r[:, 0] * nrm[0] + r[:, 1] * nrm[1] + r[:, 2] * nrm[2]) <= band), axis=0)


def bonds(x: np.ndarray, spacing: float) -> np.ndarray:
    """Neighbour pairs (M,2) of particles x (N,3) closer than LINK spacings."""
    return cKDTree(x).query_pairs(LINK * spacing, output_type="ndarray")


def crosses(x: np.ndarray, pairs: np.ndarray, sweep) -> np.ndarray:
    """(M,) bool: the segment of each pair crosses the sweep's surface (its blade-plane rectangle)."""
    o, u, w, n = sweep.as_arrays()
    d = x - o  # N,3: each particle's offset once, not once per pair
    dn, du, dw = d @ n, d @ u, d @ w
    da, db = dn[pairs[:, 0]], dn[pairs[:, 1]]
    out = (da >= 0) != (db >= 0)
    i = np.flatnonzero(out)  # the few pairs on opposite sides: where does their segment meet the plane?
    a, b = pairs[i, 0], pairs[i, 1]
    t = da[i] / (da[i] - db[i])
    qu, qw = du[a] + t * (du[b] - du[a]), dw[a] + t * (dw[b] - dw[a])
    out[i] = (np.abs(qu) <= sweep.half_length) & (qw <= sweep.depth)
    return out


def split(x: np.ndarray, piece: np.ndarray, sweep, spacing: float, pairs: np.ndarray | None = None) -> np.ndarray:
    """New piece labels (N,) after ``sweep``: components of the bonds that join one piece and cross no swept
    surface.  Labels are numbered by their lowest particle index; flakes (< MIN_PIECE) join the nearest piece."""
    pairs = bonds(x, spacing) if pairs is None else pairs
    keep = (piece[pairs[:, 0]] == piece[pairs[:, 1]]) & ~crosses(x, pairs, sweep)
    e = pairs[keep]
    N = len(x)
    _, lab = connected_components(coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(N, N)), directed=False)
    size = np.bincount(lab)
    small = size[lab] < MIN_PIECE
    if small.any() and (~small).any():
        _, nearest = cKDTree(x[~small]).query(x[small])
        lab[small] = lab[~small][nearest]
    _, first = np.unique(lab, return_index=True)  # renumber by lowest particle index: stable across runs
    rank = np.empty(lab.max() + 1, np.int64)
    rank[lab[np.sort(first)]] = np.arange(len(first))
    return rank[lab].astype(np.int32)


def adjacency(x: np.ndarray, piece: np.ndarray, n_grid: int, reach: int = REACH) -> set[tuple[int, int]]:
    """Pairs of pieces whose particles' base cells lie within ``reach`` cells (Chebyshev) of each other.

    Each piece's occupied cells, dilated by ``reach`` (a separable maximum filter over the objects' box), are
    looked up at the other pieces' cells: O(pieces x cells), not a neighbour search over every cell pair."""
    from scipy.ndimage import maximum_filter

    cell = np.floor(x * n_grid - 0.5).astype(np.int64)
    cell -= cell.min(0) - reach  # into a box with room for the dilation
    shape = tuple(cell.max(0) + reach + 1)
    n_pieces = int(piece.max()) + 1
    cells = [cell[piece == p] for p in range(n_pieces)]
    out = set()
    for p in range(n_pieces - 1):
        if not len(cells[p]):
            continue
        occ = np.zeros(shape, np.uint8)
        occ[tuple(cells[p].T)] = 1
        near = maximum_filter(occ, size=2 * reach + 1, mode="constant")
        for q in range(p + 1, n_pieces):
            if len(cells[q]) and near[tuple(cells[q].T)].any():
                out.add((p, q))
    return out


def colour(x: np.ndarray, piece: np.ndarray, n_grid: int, fields: int, sweep=None,
           reach: float = 0.0) -> tuple[np.ndarray, int]:
    """Velocity field (N,) per particle: neighbouring pieces get different ones (greedy, largest piece first).

    ``sweep`` (the cut's KnifeSweep) and ``reach``: pieces lying by the blade on opposite sides of it also get
    different fields, however far apart along it, so that every field by the blade has one side (``field_sides``)
    and the wedge and the push treat it as that side's.  A field shared across the blade got side 0, and the
    push then moved its nodes by their own side of the blade: a die's face particles in the kerf were carried
    along with the pieces the push slid away (dice / donut at 128^3: the die dragged 14.5 mm, stretched 9%).

    Returns (field per particle, conflicts): a conflict is a pair of neighbouring pieces that had to share a
    field because ``fields`` ran out (they may bond where they touch; raise sim.fields)."""
    n_pieces = int(piece.max()) + 1 if len(piece) else 0
    size = np.bincount(piece, minlength=n_pieces)
    if n_pieces <= 1 or fields == 1:
        of, conflicts = greedy_colour(size, set(), fields)
        return of[piece].astype(np.int32), conflicts
    pairs = adjacency(x, piece, n_grid)
    if sweep is not None:
        pairs = pairs | side_pairs(piece_sides(x, piece, n_pieces, sweep, reach))
    of, conflicts = greedy_colour(size, pairs, fields)
    return of[piece].astype(np.int32), conflicts


def side_pairs(side: np.ndarray) -> set[tuple[int, int]]:
    """Pairs (i < j) of pieces by the blade on opposite sides of it (``piece_sides``: +1 and -1)."""
    plus, minus = np.flatnonzero(side > 0), np.flatnonzero(side < 0)
    return {(int(min(i, j)), int(max(i, j))) for i in plus for j in minus}


def greedy_colour(size: np.ndarray, pairs: set[tuple[int, int]], fields: int) -> tuple[np.ndarray, int]:
    """(field per piece (n_pieces,) int64, conflicts) of pieces of ``size`` (n_pieces,) particles whose ``pairs``
    must differ: largest piece first, each the lowest field none of its coloured neighbours holds, or the least
    held one when none is free (each neighbour on it a conflict).  ``colour`` and the device's summaries
    (fields_device) both colour with this."""
    n_pieces = len(size)
    if n_pieces <= 1 or fields == 1:
        return np.zeros(n_pieces, np.int64), 0 if fields > 1 or n_pieces <= 1 else n_pieces - 1
    nbr = [set() for _ in range(n_pieces)]
    for i, j in pairs:
        nbr[i].add(j)
        nbr[j].add(i)
    of = np.full(n_pieces, -1, np.int64)
    conflicts = 0
    for p in np.argsort(-np.asarray(size), kind="stable"):
        used = np.bincount([of[q] for q in nbr[p] if of[q] >= 0], minlength=fields)
        free = np.flatnonzero(used == 0)
        of[p] = free[0] if len(free) else int(np.argmin(used))
        conflicts += 0 if len(free) else int(used.min())
    return of, conflicts


def _near_blade(x: np.ndarray, sweep, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """(near (N,) bool: within ``reach`` of the blade's plane, inside its swept rectangle grown by ``reach``;
    the signed distance to the plane (N,))."""
    o, u, w, n = sweep.as_arrays()
    d = x - o
    dn = d @ n
    near = (np.abs(dn) < reach) & (np.abs(d @ u) <= sweep.half_length + reach) & (d @ w <= sweep.depth + reach)
    return near, dn


def sides_from_counts(plus: np.ndarray, minus: np.ndarray) -> np.ndarray:
    """+1 where only ``plus`` counts particles near the blade, -1 where only ``minus`` does, 0 where both or none."""
    return np.where((plus > 0) & (minus == 0), 1, np.where((minus > 0) & (plus == 0), -1, 0)).astype(np.int32)


def piece_sides(x: np.ndarray, piece: np.ndarray, n_pieces: int, sweep, reach: float) -> np.ndarray:
    """(n_pieces,) int: +1 / -1 where every particle of the piece near the blade is on the +n / -n side; 0 where
    it has particles on both (an uncut piece) or none near it."""
    near, dn = _near_blade(x, sweep, reach)
    plus = np.bincount(piece[near & (dn >= 0)], minlength=n_pieces)
    minus = np.bincount(piece[near & (dn < 0)], minlength=n_pieces)
    return sides_from_counts(plus, minus)


def field_sides(x: np.ndarray, field: np.ndarray, fields: int, sweep, reach: float) -> np.ndarray:
    """(fields,) int: +1 / -1 where every particle of that field near the blade (within ``reach`` of its
    plane, inside the swept rectangle grown by ``reach``) is on the +n / -n side; 0 where mixed or absent."""
    return piece_sides(x, field, fields, sweep, reach)


def cut_off_side(x: np.ndarray, before: np.ndarray, after: np.ndarray, sweep) -> int:
    """The side (+1 / -1 of the blade normal) of the material this cut separated from the rest, 0 if none.

    Of every piece the cut split, the pieces on the side with fewer particles are the ones cut off (a slice
    off the loaf), which the push slides away."""
    o, _, _, n = sweep.as_arrays()
    if not len(before):
        return 0
    m = int(before.max()) + 1
    pairs = np.unique(np.stack([before, after], 1), axis=0)  # (label before, label after) that occur
    split = np.bincount(pairs[:, 0], minlength=m) > 1  # labels before the cut it split
    return cut_off_from_counts(split, np.bincount(before[(x - o) @ n >= 0], minlength=m), np.bincount(before, minlength=m))


def cut_off_from_counts(split: np.ndarray, plus: np.ndarray, total: np.ndarray) -> int:
    """``cut_off_side`` from, per label before the cut: whether the cut split it, its particles on +n, in all."""
    if not split.any():
        return 0
    up, n = int(plus[split].sum()), int(total[split].sum())
    return 1 if up <= n - up else -1

"""The pieces' velocity fields on the device: ``pieces.colour``'s inputs for B scenes at once (issue #49).

After ``pieces_device`` has split the scenes, a few kernels reduce each scene's particles to summaries of its
pieces, as bitmasks of at most 64 pieces (one u64), which is all the host's greedy colouring reads:

- adjacency (``pieces.adjacency``): a mask of the pieces in each grid cell (the particles' base cells), dilated by
  ``REACH`` cells along x, then y, then z (a separable OR: the Chebyshev ball); each piece then ORs the dilated
  masks at its own particles' cells.  Bit q of piece p's mask is set exactly when some cell of q lies within
  ``REACH`` cells of some cell of p: the host's pairs.
- sides (``pieces.piece_sides``): each piece's count of particles near the blade on +n and on -n; a field's
  counts are its pieces' sums (``pieces.field_sides``).
- the cut-off side (``pieces.cut_off_side``): per label before the cut, the mask of its labels after it, its
  particle count and its count on +n.

The host colours the pieces from these (``pieces.greedy_colour``: the host path's own code, the same fields),
and one kernel writes each particle's field into the solver's ``body``: only B x 64 summaries cross to the
host, not the particles.  A batch where any label reaches 64 takes the host path (``colour_batch`` returns None).
The particles' base cells are clamped into the grid, which holds every particle the solver keeps (its walls
lie cells inside the domain), so the clamp changes nothing there.
"""

import numpy as np
import taichi as ti

from topocut.sim import pieces as P
from topocut.sim.runtime import _ON_RESET

MAX_PIECES = 64  # labels a u64 mask holds


@ti.func
def _bit(label):
    return ti.u64(1) << ti.cast(label, ti.u64)


@ti.data_oriented
class DeviceFields:
    """Per-scene cell masks (B, G, G, G) and per-piece summaries (B, 64); ``summarise`` fills them from a
    DeviceSplit that has just run, ``paint`` writes the fields the host chose into the solver's ``body``."""

    def __init__(self, B: int, n_grid: int, reach: int = P.REACH):
        self.B, self.G, self.R = int(B), int(n_grid), int(reach)
        fb = ti.FieldsBuilder()
        self.occ, self.tmp = ti.field(ti.u64), ti.field(ti.u64)  # B,G,G,G: pieces in a cell; the dilation passes
        fb.dense(ti.ijkl, (self.B, self.G, self.G, self.G)).place(self.occ, self.tmp)
        self.lo, self.hi = ti.Vector.field(3, ti.i32), ti.Vector.field(3, ti.i32)  # B: the occupied cells' box
        fb.dense(ti.i, self.B).place(self.lo, self.hi)
        self.adj, self.kids = ti.field(ti.u64), ti.field(ti.u64)  # B,64: pieces near each piece; labels after
        self.size, self.plus, self.minus = ti.field(ti.i32), ti.field(ti.i32), ti.field(ti.i32)  # B,64 per piece
        self.tot, self.up = ti.field(ti.i32), ti.field(ti.i32)  # B,64 per label before
        fb.dense(ti.ij, (self.B, MAX_PIECES)).place(self.adj, self.kids, self.size, self.plus, self.minus, self.tot,
                                                    self.up)
        self.tree = fb.finalize()

    def destroy(self) -> None:
        self.tree.destroy()

    @ti.func
    def _cell(self, q):  # pieces.adjacency's base cell floor(x G - 0.5), in the grid
        c = ti.cast(ti.floor(q * self.G - 0.5), ti.i32)
        return ti.max(ti.min(c, self.G - 1), 0)

    @ti.func
    def _live(self, ds: ti.template(), b, i):
        return ds.on[b] != 0 and i < ds.count[b]

    @ti.func
    def _in_box(self, b, c):  # within the occupied box grown by R: where the dilation can be non-zero
        return (c >= self.lo[b] - self.R).all() and (c <= self.hi[b] + self.R).all()

    @ti.kernel
    def _bounds(self, ds: ti.template()):
        for b, k in self.adj:
            self.adj[b, k], self.kids[b, k] = ti.u64(0), ti.u64(0)
            self.size[b, k], self.plus[b, k], self.minus[b, k], self.tot[b, k], self.up[b, k] = 0, 0, 0, 0, 0
        for b in self.lo:
            self.lo[b], self.hi[b] = ti.Vector([self.G] * 3), ti.Vector([-1] * 3)
        for b, i in ds.x:
            if self._live(ds, b, i):
                c = self._cell(ds.x[b, i])
                for a in ti.static(range(3)):  # read first: the box only grows, so most particles need no atomic
                    if c[a] < self.lo[b][a]:  # (16 scenes' particles on 96 counters: 3.2 ms a cut at 128^3)
                        ti.atomic_min(self.lo[b][a], c[a])
                    if c[a] > self.hi[b][a]:
                        ti.atomic_max(self.hi[b][a], c[a])

    @ti.kernel
    def _occupy(self, ds: ti.template()):
        for b, i, j, k in self.occ:
            if self._in_box(b, ti.Vector([i, j, k])):
                self.occ[b, i, j, k] = ti.u64(0)
        for b, i in ds.x:
            if self._live(ds, b, i):
                c = self._cell(ds.x[b, i])
                ti.atomic_or(self.occ[b, c[0], c[1], c[2]], _bit(ds.out[b, i]))

    @ti.kernel
    def _dilate(self, src: ti.template(), dst: ti.template(), axis: ti.template()):
        for b, i, j, k in dst:
            c = ti.Vector([i, j, k])
            if self._in_box(b, c):
                acc = ti.u64(0)
                for s in range(-self.R, self.R + 1):
                    e = c
                    e[axis] += s
                    if e[axis] >= 0 and e[axis] < self.G and self._in_box(b, e):
                        acc |= src[b, e[0], e[1], e[2]]
                dst[b, i, j, k] = acc

    @ti.kernel
    def _gather(self, ds: ti.template(), reach: ti.f64):
        for b, i in ds.x:
            if self._live(ds, b, i):
                c, lab, was, d = self._cell(ds.x[b, i]), ds.out[b, i], ds.piece[b, i], ds.proj[b, i]  # d: (n, u, w)
                ti.atomic_or(self.adj[b, lab], self.tmp[b, c[0], c[1], c[2]])
                ti.atomic_add(self.size[b, lab], 1)
                if ti.abs(d[0]) < reach and ti.abs(d[1]) <= ds.half[b] + reach and d[2] <= ds.depth[b] + reach:
                    if d[0] >= 0:  # pieces._near_blade, then piece_sides' two counts
                        ti.atomic_add(self.plus[b, lab], 1)
                    else:
                        ti.atomic_add(self.minus[b, lab], 1)
                ti.atomic_or(self.kids[b, was], _bit(lab))
                ti.atomic_add(self.tot[b, was], 1)
                if d[0] >= 0:
                    ti.atomic_add(self.up[b, was], 1)

    @ti.kernel
    def _paint(self, ds: ti.template(), body: ti.template(), of: ti.types.ndarray(dtype=ti.i32, ndim=2)):  # B,64
        for b, i in ds.x:
            if self._live(ds, b, i):
                body[b, i] = of[b, ds.out[b, i]]

    @ti.kernel
    def _pack(self, out: ti.types.ndarray(dtype=ti.u64, ndim=3)):  # 7,B,64: every summary in one copy
        for b, k in self.adj:
            out[0, b, k], out[1, b, k] = self.adj[b, k], self.kids[b, k]
            out[2, b, k], out[3, b, k] = ti.cast(self.size[b, k], ti.u64), ti.cast(self.plus[b, k], ti.u64)
            out[4, b, k], out[5, b, k] = ti.cast(self.minus[b, k], ti.u64), ti.cast(self.tot[b, k], ti.u64)
            out[6, b, k] = ti.cast(self.up[b, k], ti.u64)

    def summarise(self, ds, reach: float) -> dict[str, np.ndarray]:
        """The per-piece summaries (each (B, 64): u64 masks, i64 counts) of the scenes ``ds`` (a DeviceSplit) has
        just split."""
        self._bounds(ds)
        self._occupy(ds)
        self._dilate(self.occ, self.tmp, 0)
        self._dilate(self.tmp, self.occ, 1)
        self._dilate(self.occ, self.tmp, 2)
        self._gather(ds, float(reach))
        out = np.zeros((7,) + self.adj.shape, np.uint64)  # 7,B,64
        self._pack(out)  # one launch and one copy back: seven to_numpy calls were seven of each
        s = dict(zip(("adj", "kids"), out[:2]))
        s.update(zip(("size", "plus", "minus", "tot", "up"), out[2:].astype(np.int64)))  # counts < 2^31
        return s

    def paint(self, ds, body, of: np.ndarray) -> None:
        """body[b, i] = of[b, label of particle i] for every live particle of every scene ds cut."""
        self._paint(ds, body, np.ascontiguousarray(of, np.int32))


def _bits(mask) -> list[int]:
    m = int(mask)
    return [k for k in range(m.bit_length()) if m >> k & 1]


def _several(masks: np.ndarray) -> np.ndarray:
    """Which u64 masks have more than one bit set (m & (m - 1) clears the lowest; 0 - 1 wraps to all ones)."""
    return (masks & (masks - np.uint64(1))) != 0


def scene_fields(s: dict, b: int, fields: int) -> tuple[np.ndarray, int, int, np.ndarray]:
    """Scene b's (field per piece (n_pieces,), conflicts, cut-off side, field sides (fields,)) from the summaries
    ``s``: pieces.colour, cut_off_side and field_sides, from counts instead of particles."""
    size = s["size"][b]
    n = int(np.flatnonzero(size)[-1]) + 1 if size.any() else 0  # labels 0 .. n-1, every one with particles
    pairs = {(p, q) for q in range(n) for p in _bits(s["adj"][b, q]) if p < q}
    side = P.sides_from_counts(s["plus"][b, :n], s["minus"][b, :n])
    of, conflicts = P.greedy_colour(size[:n], pairs | P.side_pairs(side), fields)
    split = _several(s["kids"][b])
    cut_off = P.cut_off_from_counts(split, s["up"][b], s["tot"][b])
    plus = np.bincount(of, weights=s["plus"][b, :n], minlength=fields)
    minus = np.bincount(of, weights=s["minus"][b, :n], minlength=fields)
    return of, conflicts, cut_off, P.sides_from_counts(plus, minus)


_CACHE: dict = {}  # (B, n_grid) -> DeviceFields: fields and kernels kept between cuts
_ON_RESET.append(_CACHE.clear)  # reset_taichi frees their fields


def colour_batch(ds, body, labels: np.ndarray, before: np.ndarray, n_grid: int, fields: int, reach: float):
    """After ``ds`` (a DeviceSplit) split its scenes: each cut scene's fields written into the solver field
    ``body`` (B,N), and per scene (conflicts, cut-off side, field sides (fields,), fields used) for the scenes
    ds cut (None for the others).  ``labels``/``before`` (B,n): the labels after and before, to check that they
    fit a mask.  None: a label reaches MAX_PIECES; nothing was written and the host path colours the batch."""
    if labels.size and max(int(labels.max()), int(before.max())) >= MAX_PIECES:
        return None
    B = ds.B
    df = _CACHE.get((B, n_grid))
    if df is None:
        df = _CACHE[(B, n_grid)] = DeviceFields(B, n_grid)
    s = df.summarise(ds, reach)
    on = ds.on_host
    of = np.zeros(df.adj.shape, np.int32)  # B,64
    out = []
    for b in range(B):
        if not on[b]:
            out.append(None)
            continue
        ofb, conflicts, cut_off, sides = scene_fields(s, b, fields)
        of[b, :len(ofb)] = ofb
        out.append((conflicts, cut_off, sides, int(ofb.max()) + 1 if len(ofb) else 1))
    df.paint(ds, body, of)
    return out

"""The pieces' split on the device: ``pieces.split`` for B scenes at once in Taichi kernels (issue #49).

Same labels as the host's ``pieces.split`` for every particle (tests/test_sim_device_split.py), found another way:

- Bonds: each particle visits the 27 cells around its own in a cell list (cells of LINK spacings and a bit,
  hashed into ``T`` buckets per scene and counting-sorted), so it meets every particle within LINK spacings,
  cKDTree.query_pairs' pairs: squared distance ((dx² + dy²) + dz²) in f64 ``<=`` r·r, as scipy compares.  A hash
  collision only adds candidates the distance test rejects or repeats (a repeated union is a no-op).
- Crossing: ``pieces.crosses``' float formula in f64, with each particle's (n, u, w) offsets computed once.
  Taichi's fast math may fuse a multiply-add (FMA) where numpy rounds twice (or OpenBLAS fuses where we do not):
  a last-bit difference, which changes a bond only for a particle within ~1e-16 of the blade plane (not on an
  axis-aligned plane: its products by 0 and 1 are exact) or a pair at LINK spacings to 1 ulp.
- Components: lock-free union-find with atomic_min (Playne & Hawick 2018: a root hooks under the smaller
  root, a failed hook retries from the value it found), so each root is its component's lowest particle.
- Flakes (< MIN_PIECE particles) take the label of the nearest particle of a large component, searched in the
  27 cells (exact when the best lies within LINK spacings: anything outside is farther); a flake whose nearest
  lies farther (debris set apart) searches its whole scene, on the device too.  Ties (measure zero) go to the
  lower index.
- Renumbering by lowest particle index: each final label's lowest particle is a head; a prefix sum over the
  heads gives each its rank.

API: ``split_batch(x (B,n,3), counts (B,), piece (B,n) i32, sweeps [KnifeSweep | None] * B, spacing)`` returns
(B,n) i32; a None sweep is an idle scene, returned unchanged, as are the padding rows past counts[b].
"""

import numpy as np
import taichi as ti

from topocut.sim.pieces import LINK, MIN_PIECE
from topocut.sim.runtime import _ON_RESET, to_device, to_host

CELL_MARGIN = 1.001  # cells a bit wider than the bond length: a bond's ends lie in adjacent cells despite rounding
BIG = 1e300


@ti.data_oriented
class DeviceSplit:
    """Fields for B scenes of up to n particles each; ``run`` splits them (see the module docstring)."""

    def __init__(self, B: int, n: int):
        self.B, self.n = int(B), int(n)
        self.log_t = max(4, int(np.ceil(np.log2(max(self.n, 1)))))  # >= n buckets for ~n/4 cells (4 particles a cell)
        self.T = 1 << self.log_t
        if self.B * self.T >= 2 ** 31 or self.B * self.n >= 2 ** 31:
            raise ValueError(f"device split: {self.B} scenes of {self.n} particles overflow 32-bit indices")
        self.cuda = ti.lang.impl.current_cfg().arch == ti.cuda
        fb = ti.FieldsBuilder()
        v64 = ti.types.vector(3, ti.f64)
        self.x, self.proj = v64.field(), v64.field()  # B,n: positions; offsets from the sweep along (n, u, w)
        self.piece, self.parent, self.lab, self.size, self.first, self.near, self.key, self.out = (
            ti.field(ti.i32) for _ in range(8))  # B,n
        for f in (self.x, self.proj, self.piece, self.parent, self.lab, self.size, self.first, self.near, self.key,
                  self.out):  # an array each (not one struct per particle): a GPU warp's loads stay coalesced
            fb.dense(ti.ij, (self.B, self.n)).place(f)
        self.order, self.mark = ti.field(ti.i32), ti.field(ti.i32)  # B*n: particles in bucket order; heads
        for f in (self.order, self.mark):
            fb.dense(ti.i, self.B * self.n).place(f)
        self.slot = ti.field(ti.i32)  # B*T: particles per bucket, then (scanned) the end of each bucket's run
        fb.dense(ti.i, self.B * self.T).place(self.slot)
        self.o, self.u, self.w, self.nrm = v64.field(), v64.field(), v64.field(), v64.field()  # B: each sweep
        self.half, self.depth = ti.field(ti.f64), ti.field(ti.f64)  # B
        self.count, self.on, self.far = ti.field(ti.i32), ti.field(ti.i32), ti.field(ti.i32)  # B
        fb.dense(ti.i, self.B).place(self.o, self.u, self.w, self.nrm, self.half, self.depth, self.count,
                                     self.on, self.far)
        self.tree = fb.finalize()
        self._scans = {}
        self.on_host = np.zeros(self.B, np.int32)  # the last run's cut scenes, as the host sent them

    def destroy(self) -> None:
        self.tree.destroy()

    # -- cell list ---------------------------------------------------------------------------------------------
    @ti.func
    def _cell(self, q, h):
        return ti.cast(ti.floor(q / h), ti.i32)

    @ti.func
    def _bucket(self, b, c):  # scene b's bucket of cell c (10 bits an axis, then a multiplicative hash)
        k = ti.cast(((c[0] & 1023) << 20) | ((c[1] & 1023) << 10) | (c[2] & 1023), ti.u32)
        return b * self.T + ti.cast((k * ti.u32(2654435761)) >> ti.u32(32 - self.log_t), ti.i32)

    @ti.func
    def _run(self, f):  # [lo, hi) of bucket f's particles in ``order`` (slot holds the inclusive scan)
        lo = 0
        if f > 0:
            lo = self.slot[f - 1]
        return lo, self.slot[f]

    @ti.func
    def _live(self, b, i):
        return self.on[b] != 0 and i < self.count[b]

    @ti.kernel
    def _clear(self):
        for f in self.slot:
            self.slot[f] = 0
        for b, i in self.parent:
            self.parent[b, i], self.size[b, i], self.first[b, i], self.near[b, i] = i, 0, self.n, -1
        for b in self.far:
            self.far[b] = 0

    @ti.kernel
    def _count(self, h: ti.f64):
        for b, i in self.x:
            if self._live(b, i):
                d = self.x[b, i] - self.o[b]  # pieces.crosses: d = x - o, then d @ n, d @ u, d @ w
                self.proj[b, i] = ti.Vector([d[0] * self.nrm[b][0] + d[1] * self.nrm[b][1] + d[2] * self.nrm[b][2],
                                             d[0] * self.u[b][0] + d[1] * self.u[b][1] + d[2] * self.u[b][2],
                                             d[0] * self.w[b][0] + d[1] * self.w[b][1] + d[2] * self.w[b][2]])
                self.key[b, i] = ti.atomic_add(self.slot[self._bucket(b, self._cell(self.x[b, i], h))], 1)

    @ti.kernel
    def _place(self, h: ti.f64):
        for b, i in self.x:
            if self._live(b, i):
                lo, _ = self._run(self._bucket(b, self._cell(self.x[b, i], h)))
                self.order[lo + self.key[b, i]] = i

    @ti.kernel
    def _scan_serial(self, a: ti.template()):  # inclusive prefix sum on the CPU, where Taichi has no parallel one
        ti.loop_config(serialize=True)
        for f in range(1, a.shape[0]):
            a[f] += a[f - 1]

    def _scan(self, a) -> None:
        if not self.cuda:
            self._scan_serial(a)
            return
        if a.shape[0] not in self._scans:
            self._scans[a.shape[0]] = ti.algorithms.PrefixSumExecutor(a.shape[0])
        self._scans[a.shape[0]].run(a)

    # -- components --------------------------------------------------------------------------------------------
    @ti.func
    def _find(self, b, a):
        r = a
        while self.parent[b, r] != r:
            r = self.parent[b, r]
        return r

    @ti.func
    def _union(self, b, i, j):  # Playne & Hawick's merge: parents only decrease, so a root is its set's lowest
        p, q, done = i, j, 0
        while done == 0:
            p, q = self._find(b, p), self._find(b, q)
            if p < q:
                old = ti.atomic_min(self.parent[b, q], p)
                done, q = ti.cast(old == q, ti.i32), old
            elif q < p:
                old = ti.atomic_min(self.parent[b, p], q)
                done, p = ti.cast(old == p, ti.i32), old
            else:
                done = 1

    @ti.func
    def _crosses(self, b, i, j):  # pieces.crosses for the pair (a, b) = (i, j), i < j, as query_pairs orders it
        pa, pb = self.proj[b, i], self.proj[b, j]
        out = (pa[0] >= 0) != (pb[0] >= 0)
        if out:
            t = pa[0] / (pa[0] - pb[0])
            qu, qw = pa[1] + t * (pb[1] - pa[1]), pa[2] + t * (pb[2] - pa[2])
            out = ti.abs(qu) <= self.half[b] and qw <= self.depth[b]
        return out

    @ti.kernel
    def _bond(self, h: ti.f64, r2: ti.f64):
        for b, i in self.x:
            if self._live(b, i):
                xi, c = self.x[b, i], self._cell(self.x[b, i], h)
                for dx, dy, dz in ti.ndrange((-1, 2), (-1, 2), (-1, 2)):
                    lo, hi = self._run(self._bucket(b, c + ti.Vector([dx, dy, dz])))
                    for k in range(lo, hi):
                        j = self.order[k]
                        if j > i and self.piece[b, j] == self.piece[b, i]:
                            e = xi - self.x[b, j]
                            if e[0] * e[0] + e[1] * e[1] + e[2] * e[2] <= r2 and not self._crosses(b, i, j):
                                self._union(b, i, j)

    @ti.kernel
    def _flatten(self):
        for b, i in self.x:
            if self._live(b, i):
                r = self._find(b, i)
                self.lab[b, i] = r
                ti.atomic_add(self.size[b, r], 1)

    # -- flakes and renumbering --------------------------------------------------------------------------------
    @ti.func
    def _small(self, b, i):
        return self.size[b, self.lab[b, i]] < MIN_PIECE

    @ti.kernel
    def _near_cells(self, h: ti.f64, r2: ti.f64):
        for b, i in self.x:
            if self._live(b, i) and self._small(b, i):
                xi, c = self.x[b, i], self._cell(self.x[b, i], h)
                best, bd = -1, ti.cast(BIG, ti.f64)
                for dx, dy, dz in ti.ndrange((-1, 2), (-1, 2), (-1, 2)):
                    lo, hi = self._run(self._bucket(b, c + ti.Vector([dx, dy, dz])))
                    for k in range(lo, hi):
                        j = self.order[k]
                        if not self._small(b, j):
                            e = xi - self.x[b, j]
                            d2 = e[0] * e[0] + e[1] * e[1] + e[2] * e[2]
                            if d2 < bd or (d2 == bd and j < best):
                                best, bd = j, d2
                if bd <= r2:  # within LINK spacings < one cell: nothing outside the 27 cells is nearer
                    self.near[b, i] = best
                else:
                    self.near[b, i] = -2  # the whole scene next
                    ti.atomic_add(self.far[b], 1)

    @ti.kernel
    def _near_all(self):  # the rare flake far from every large piece: every particle of its scene
        for b, i in self.x:
            if self._live(b, i) and self.near[b, i] == -2:
                xi, best, bd = self.x[b, i], -1, ti.cast(BIG, ti.f64)
                for j in range(self.count[b]):
                    if not self._small(b, j):
                        e = xi - self.x[b, j]
                        d2 = e[0] * e[0] + e[1] * e[1] + e[2] * e[2]
                        if d2 < bd:
                            best, bd = j, d2
                self.near[b, i] = best  # -1: no large piece in the scene, the flake keeps its label

    @ti.kernel
    def _adopt(self):  # a flake takes its nearest large particle's label (never a flake's: no chains)
        for b, i in self.x:
            if self._live(b, i) and self.near[b, i] >= 0:
                self.lab[b, i] = self.lab[b, self.near[b, i]]
        for b, i in self.x:
            if self._live(b, i):
                ti.atomic_min(self.first[b, self.lab[b, i]], i)

    @ti.kernel
    def _heads(self):
        for b, i in self.x:
            self.mark[b * self.n + i] = ti.cast(self._live(b, i) and self.first[b, self.lab[b, i]] == i, ti.i32)

    @ti.kernel
    def _rank(self):
        for b, i in self.x:
            if self._live(b, i):
                before = 0  # heads of the scenes before b (the scan runs over all scenes)
                if b > 0:
                    before = self.mark[b * self.n - 1]
                self.out[b, i] = self.mark[b * self.n + self.first[b, self.lab[b, i]]] - 1 - before
            else:
                self.out[b, i] = self.piece[b, i]  # idle scene or padding: unchanged

    @ti.kernel
    def _load(self, src: ti.template()):
        for b, i in self.x:
            if i < self.count[b]:
                self.x[b, i] = ti.cast(src[b, i], ti.f64)  # exact: the host's to_numpy().astype(np.float64)

    @ti.kernel
    def _load_host(self, x: ti.types.ndarray(dtype=ti.f64, ndim=3)):  # B,m,3 (m <= n)
        for b, i in ti.ndrange(x.shape[0], x.shape[1]):
            self.x[b, i] = ti.Vector([x[b, i, 0], x[b, i, 1], x[b, i, 2]])

    @ti.kernel
    def _set(self, piece: ti.types.ndarray(dtype=ti.i32, ndim=2), geo: ti.types.ndarray(dtype=ti.f64, ndim=2),
             ints: ti.types.ndarray(dtype=ti.i32, ndim=2)):  # piece B,m (m <= n); geo B,14; ints B,2
        for b, i in ti.ndrange(piece.shape[0], piece.shape[1]):
            self.piece[b, i] = piece[b, i]
        for b in range(self.B):
            for a in ti.static(range(3)):
                self.o[b][a], self.u[b][a], self.w[b][a], self.nrm[b][a] = geo[b, a], geo[b, 3 + a], geo[b, 6 + a], \
                    geo[b, 9 + a]
            self.half[b], self.depth[b], self.count[b], self.on[b] = geo[b, 12], geo[b, 13], ints[b, 0], ints[b, 1]

    def run(self, x, counts, piece: np.ndarray, sweeps, spacing: float) -> np.ndarray:
        """Labels (B,m) after the cut of ``x``: (B,m,3) positions, or the solver's particle field (B,N) itself;
        ``piece`` (B,m) the labels before, m <= n (the rows past counts[b] are padding the kernels skip)."""
        B = self.B
        geo = np.zeros((B, 14))  # o, u, w, n, half length, depth per scene (zeros for idle scenes)
        ints = np.zeros((B, 2), np.int32)  # particles, cut or idle
        ints[:, 0] = counts
        for b, sw in enumerate(sweeps):
            if sw is not None:
                geo[b, :12] = np.concatenate(sw.as_arrays())
                geo[b, 12:], ints[b, 1] = (sw.half_length, sw.depth), 1
        self.on_host = ints[:, 1].copy()  # colour_batch reads them here, not back from the device
        # one launch for the inputs, through device tensors on CUDA (to_device): each from_numpy was a launch
        # with its own copies there and back
        self._set(to_device(np.ascontiguousarray(piece, np.int32)), to_device(geo), to_device(ints))
        if isinstance(x, np.ndarray):
            self._load_host(to_device(np.ascontiguousarray(x, np.float64)))
        else:  # the solver's own positions (B,N) f32, on the device: no round trip through the host
            self._load(x)
        r = LINK * spacing
        r2, h = r * r, r * CELL_MARGIN  # r2 = r * r in f64: cKDTree compares squared distances with it
        self._clear()
        self._count(h)
        self._scan(self.slot)
        self._place(h)
        self._bond(h, r2)
        self._flatten()
        self._near_cells(h, r2)
        if self.far.to_numpy().any():  # one host sync: the brute-force search runs only when a flake needs it
            self._near_all()
        self._adopt()
        self._heads()
        self._scan(self.mark)
        self._rank()
        return to_host(self.out)


_CACHE: dict = {}  # B -> DeviceSplit: fields and kernels kept between cuts while the capacity suffices
_ON_RESET.append(_CACHE.clear)  # reset_taichi frees their fields


def _capacity(n: int) -> int:
    """Rows to allocate for n particles: a quarter more, in steps of 4096.  The env's row count is its largest
    scene's, which changes with every episode's object and scale; a new DeviceSplit is a new field tree, whose
    kernels Taichi compiles again (3.2-3.7 s on an H200), so the fields only grow."""
    return int(np.ceil(1.25 * max(n, 1) / 4096.0)) * 4096


def device_split(B: int, n: int) -> DeviceSplit:
    """The DeviceSplit for B scenes of up to n particles, kept between calls (``_capacity``)."""
    ds = _CACHE.get(B)
    if ds is None or ds.n < n:
        # a tree per batch size (a process may hold several envs, e.g. MPPI's rollouts beside an evaluation's
        # scenes: alternating between them must not recompile); a grown one frees its predecessor
        if ds is not None:
            ds.destroy()
        ds = _CACHE[B] = DeviceSplit(B, _capacity(n))
    return ds


def split_batch(x: np.ndarray, counts, piece: np.ndarray, sweeps, spacing: float) -> np.ndarray:
    """New piece labels (B,n) i32 of B scenes (x (B,n,3), counts (B,), piece (B,n) their labels before the cut,
    sweeps: KnifeSweep per scene, None for an idle one), equal to ``pieces.split`` scene by scene."""
    piece = np.asarray(piece)
    B, n = piece.shape
    if x.shape != (B, n, 3) or len(counts) != B or len(sweeps) != B:
        raise ValueError(f"split_batch: x {x.shape}, counts {len(counts)}, sweeps {len(sweeps)} for piece {piece.shape}")
    if n == 0 or all(sw is None for sw in sweeps):
        return piece.astype(np.int32, copy=True)
    return device_split(B, n).run(x, counts, piece, sweeps, spacing)[:, :n]

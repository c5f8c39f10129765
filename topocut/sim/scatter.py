"""The scatter (particle to grid) of MPMSolver and the order it visits particles in, as methods it inherits.

``scatter`` is the p2g loop: per particle the material update (MPMSolver.particle_update) and its 27 stencil
adds into the velocity field of the particle's piece.  On CUDA ``scatter_warp`` sums a warp's same-cell stencils
by shuffles first (sim.tuning.warp_scatter), which pays off with particles visited cell by cell: ``sort_by_cell``
re-sorts the visiting order ``order`` on the device (sim.tuning.resort_every).  Apart from the p2g kernel's
clear this is all the scatter's code; mpm.py keeps the fields and the substep's physics.
"""
import taichi as ti
from taichi.lang.expr import Expr


@ti.func
def warp_run_add(grid_v: ti.template(), grid_m: ti.template(), dx: ti.template(), lane, key, g, base, fx, mass, mom,
                 affine, live):
    """Adds each lane's 27 stencil values into grid slot g at nodes base + off: one atomic per run of lanes.

    The lane's particle gives fx (3,), mass, mom (3,) and affine (3,3), as MPMSolver.particle_update returns
    them.  A run is lanes side by side in the warp with equal ``key`` (grid slot and base cell; a dead lane's
    negative key is its own): each value is summed over the run by 5 shuffle steps and the run's first lane
    alone adds it, where ``live``.  All 32 lanes of the warp must call it (a shuffle takes the whole warp).
    Scatter.scatter_warp sorts its lanes by key first; benchmarks/p2g_variants.py's WarpMPM takes them as they come.
    """
    full = ti.u32(0xFFFFFFFF)
    head = lane == 0 or ti.simt.warp.shfl_up_i32(full, key, 1) != key
    nxt = ti.simt.warp.shfl_down_i32(full, key, 1)
    last = lane if (lane == 31 or nxt != key) else 31  # last lane of my run: a suffix min over run ends
    for s in ti.static([1, 2, 4, 8, 16]):
        o = ti.simt.warp.shfl_down_i32(full, last, s)
        if lane + s < 32:
            last = ti.min(last, o)
    w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
    for off in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
        weight = w[off[0]][0] * w[off[1]][1] * w[off[2]][2]
        val = weight * (mom + affine @ ((off.cast(ti.f32) - fx) * dx))
        m = weight * mass
        for s in ti.static([1, 2, 4, 8, 16]):  # lane + s <= last: the partner's partial sum is all in my run
            o0 = ti.simt.warp.shfl_down_f32(full, val[0], s)
            o1 = ti.simt.warp.shfl_down_f32(full, val[1], s)
            o2 = ti.simt.warp.shfl_down_f32(full, val[2], s)
            om = ti.simt.warp.shfl_down_f32(full, m, s)
            if lane + s <= last:
                val += ti.Vector([o0, o1, o2])
                m += om
        if head and live:
            grid_v[g, base + off] += val
            grid_m[g, base + off] += m


@ti.data_oriented
class Scatter:
    """p2g's particle loop and its visiting order; reads the fields MPMSolver owns (x, grid_v, order, ...)."""

    @ti.func
    def scatter(self, n: ti.template(), step: ti.template()):
        if ti.static(self.use_warp):
            ti.loop_config(block_dim=self.scatter_block)  # a multiple of 32: lane = thread index % 32
            for g in range(self.B * self.lanes):
                b, i = g // self.lanes, g % self.lanes
                live = i < n and self.active(b, step)
                p = 0
                if live:
                    p = self.order[b, i]
                    live = self.live(b, p)
                self.scatter_warp(b, p, live, step)
        else:
            # one CPU thread (make test's, a bit-reproducible run's): a serial loop, whose atomic adds Taichi
            # compiles as plain ones.  The same adds in the same order, but the compiler may fuse a multiply into
            # an add it no longer has to keep atomic: float32 round-off apart from the parallel loop, the same
            # result run after run.  p2g 19.6 -> 10.9 ms a substep (64^3, 3 scenes, one thread of a 2-core CPU)
            ti.loop_config(block_dim=self.scatter_block, serialize=self.serial_scatter)
            for b, i in ti.ndrange(self.B, self.capacity):
                if i < n and self.active(b, step):  # a frozen scene scatters nothing: its grid stays empty
                    p = self.order[b, i]
                    if self.live(b, p):
                        self.scatter_particle(b, p, step)

    @ti.func
    def scatter_particle(self, b, p, step):
        base, fx, mass, mom, affine = self.particle_update(b, p, step)
        self.grow_box(base)
        g = b * self.K + self.body[b, p]  # the grid slot of the particle's piece
        w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
        for off in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
            dpos = (off.cast(ti.f32) - fx) * self.dx
            weight = w[off[0]][0] * w[off[1]][1] * w[off[2]][2]
            self.grid_v[g, base + off] += weight * (mom + affine @ dpos)
            self.grid_m[g, base + off] += weight * mass

    @ti.func
    def scatter_warp(self, b, p, live, step):
        """scatter_particle with a warp-level segmented reduction (CUDA; Gao et al. 2018, sec. 4.2).

        The scatter is bound by its global atomics (4 per stencil node, 108 per particle).  Lanes whose
        particles share scene and base cell and sit side by side in the warp form a run: each stencil value
        is summed over the run by 5 shuffle steps and only the run's first lane issues the atomics.  The
        lanes are first sorted by key inside the warp, so a run is all of the warp's particles of one cell
        wherever they sit; CuttingEnv.reset orders particles by cell, so a warp holds few cells (~8
        particles each) and keeps holding few as they drift.  All 32 lanes reach every shuffle: the loop
        covers B * lanes slots (a multiple of 32) and dead lanes (negative keys) join no run."""
        full = ti.u32(0xFFFFFFFF)
        lane = Expr(ti.global_thread_idx()) % 32
        base, fx, mass = ti.Vector([0, 0, 0]), ti.Vector.zero(ti.f32, 3), 0.0
        mom, affine = ti.Vector.zero(ti.f32, 3), ti.Matrix.zero(ti.f32, 3, 3)
        key = -1 - lane
        if live:
            base, fx, mass, mom, affine = self.particle_update(b, p, step)
            self.grow_box(base)
            g = b * self.K + self.body[b, p]  # runs are per grid slot (scene and piece field) and base cell
            key = ((g * self.n_grid + base[0]) * self.n_grid + base[1]) * self.n_grid + base[2]
        # sort the warp's lanes by key (bitonic, 15 compare-exchange stages on (key, lane)): particles of a
        # cell become one run wherever they sit in the warp; each lane then takes the particle of lane src
        src = lane
        for kk in ti.static([2, 4, 8, 16, 32]):
            for j in ti.static([h for h in (16, 8, 4, 2, 1) if h < kk]):
                pk = ti.simt.warp.shfl_xor_i32(full, key, j)
                ps = ti.simt.warp.shfl_xor_i32(full, src, j)
                keep_small = ((lane & kk) == 0) == ((lane & j) == 0)
                smaller = key < pk or (key == pk and src < ps)
                if keep_small != smaller:
                    key, src = pk, ps
        alive = key >= 0  # the particle this lane now holds is live
        n = self.n_grid
        base = ti.Vector([(key // (n * n)) % n, (key // n) % n, key % n])
        slot = key // (n * n * n)
        mass = ti.simt.warp.shfl_sync_f32(full, mass, src)
        for d in ti.static(range(3)):
            fx[d] = ti.simt.warp.shfl_sync_f32(full, fx[d], src)
            mom[d] = ti.simt.warp.shfl_sync_f32(full, mom[d], src)
            for e in ti.static(range(3)):
                affine[d, e] = ti.simt.warp.shfl_sync_f32(full, affine[d, e], src)
        warp_run_add(self.grid_v, self.grid_m, self.dx, lane, key, slot, base, fx, mass, mom, affine, alive)

    # -- the scatter's particle order ----------------------------------------------------------------------
    def sort_by_cell(self, n: int, by_cell: bool = True) -> None:
        """Let the scatter visit each scene's particles in base-cell order (by_cell=False: in memory order).

        The warp scatter's atomics fall with the length of its runs of same-cell lanes, and neighbouring cells
        in one warp share most stencil nodes.  Particles leave the cell order CuttingEnv.reset gave them as
        pieces slide (the mean run of a warp drops from 5.3 to 3.3 over a cut), so CuttingEnv re-sorts every
        ``sim.tuning.resort_every`` substeps.  A counting sort on the device, queued like any phase (no host sync):
        each particle takes a rank in its cell, a prefix sum over the cells (Taichi's PrefixSumExecutor on
        CUDA) gives each cell its first slot, each particle goes to slot + rank.  Only the visiting order
        changes: particles stay where they are (every API sees the same indices) and the grid gets the same
        sums up to float summation order.  Slots from n on keep p = i, so particles a tool appends are visited.
        """
        if by_cell:
            if not self.can_sort:
                raise RuntimeError("sort_by_cell(by_cell=True) needs sim.tuning.resort_every != 0 (the cell counters)")
            self._count_cells(n)
            if self.cfg.arch == "cuda":
                if self._scan is None:
                    self._scan = ti.algorithms.PrefixSumExecutor(self.B * self.n_grid ** 3)
                self._scan.run(self.cell_slot)
            else:
                self._scan_serial()
        self._place(n, int(by_cell))
        if by_cell:
            self._zero_counts()

    @ti.func
    def cell_index(self, b, p):
        c = self.base_node(self.x[b, p])
        return ((b * self.n_grid + c[0]) * self.n_grid + c[1]) * self.n_grid + c[2]

    @ti.kernel
    def _count_cells(self, n: ti.i32):
        for b, i in ti.ndrange(self.B, self.lanes):  # cell_key[b, i]: particle i's rank in its cell
            if i < n:
                self.cell_key[b, i] = ti.atomic_add(self.cell_slot[self.cell_index(b, i)], 1)

    @ti.kernel
    def _scan_serial(self):  # inclusive prefix sum on the CPU, where Taichi has no parallel one
        ti.loop_config(serialize=True)
        for f in range(1, self.B * self.n_grid ** 3):
            self.cell_slot[f] += self.cell_slot[f - 1]

    @ti.kernel
    def _place(self, n: ti.i32, by_cell: ti.i32):
        for b, i in ti.ndrange(self.B, self.lanes):
            if by_cell and i < n:
                f = self.cell_index(b, i)
                start = 0  # particles in cells before f (inclusive sum of f - 1), scenes before b included
                if f > 0:
                    start = self.cell_slot[f - 1]
                self.order[b, start - b * n + self.cell_key[b, i]] = i
            else:
                self.order[b, i] = i

    @ti.kernel
    def _zero_counts(self):  # for the next sort (only after one: memory order touches no counter)
        for f in self.cell_slot:
            self.cell_slot[f] = 0

"""Batched 3D MLS-MPM (APIC, quadratic B-splines) with damage, a von Mises skin and an SDF knife.

Written in the style of Taichi's mpm3d.py: fields x, v, C, F, Jp, grid_v,
grid_m, each with a leading batch axis b (B independent scenes in one set of
fields).  Each phase is a @ti.func holding one top-level loop; the kernels
p2g, grid_op, g2p launch one phase each.  ``substep`` calls them from Python
(tools can act on the grid in between); ``advance`` runs k substeps of them
through a ti.graph, one Python call for all.  Jp holds J_p = det F_p, the
quantity the damage rule reads.

Per particle: material (0 core, 1 skin), damage (0/1, permanent), the
skin's current yield stress and ``body``, the velocity field its piece moves
in.  The grid holds ``K = sim.fields`` velocity fields per node and scene
(slot b * K + f): pieces the knife separated scatter into different fields and
meet only through contact (knife.py).  Per scene: the knife (an oriented box,
one SDF evaluation per grid node), ``field_side`` and ``frozen_at``, the first
substep at which the scene stops moving (a cut's per-scene substep budget).
Materials (one class each, registered) live in materials.py, the knife and the contact between pieces in
knife.py, the scatter (p2g's particle loop, the GPU's warp scatter) and its
visiting order in scatter.py; this file holds the fields, the grid update and
the gather.  The scatter visits particles through ``order`` (per scene;
re-sorted by cell on the device by ``sort_by_cell``), every other phase in
memory order.  The host-side API lives in env.py.
"""


import warnings

import numpy as np
import taichi as ti
from taichi.lang.field import ScalarField

from topocut.sim.config import SimConfig
from topocut.sim.knife import Knife
from topocut.sim.materials import FixedCorotated, MaterialUpdate, make_materials
from topocut.sim.runtime import cpu_threads
from topocut.sim.scatter import Scatter


@ti.func
def apic_gather(grid_v: ti.template(), g, base, fx, dx: ti.template(), inv_dx: ti.template()):
    """A particle's APIC gather from the 27 nodes base + off of grid slot g: its velocity (3,) and C (3,3).

    fx (3,): the particle's position past its base node, in cells.  MPMSolver.gather_particle reads its piece's
    slot; benchmarks/sim_throughput.py's reference, with one slot per scene, reads the same way.
    """
    w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
    new_v = ti.Vector.zero(ti.f32, 3)
    new_C = ti.Matrix.zero(ti.f32, 3, 3)
    for off in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
        dpos = (off.cast(ti.f32) - fx) * dx
        weight = w[off[0]][0] * w[off[1]][1] * w[off[2]][2]
        g_v = grid_v[g, base + off]
        new_v += weight * g_v
        new_C += 4 * inv_dx * inv_dx * weight * g_v.outer_product(dpos)
    return new_v, new_C


def box_loop_threads(arch: str) -> int:
    """Threads of the grid box's clear and update on ``arch``, each reading the box's bounds; 0: ranged loops.

    A Taichi loop whose bounds are fields first runs a serial task that reads them (a launch; 6-7 us each under
    the kernel profiler, which syncs after every launch); without them a 128^3 batched substep of 443-448 us gained
    0.8-1.1% on an H200.  The CPU keeps the ranged loops (tests/test_sim_grid_box.py runs these on it too)."""
    return 2 ** 18 if arch == "cuda" else 0


@ti.data_oriented
class MPMSolver(MaterialUpdate, Knife, Scatter):
    """Fields of B scenes with room for ``capacity`` particles each; kernels read cfg constants."""

    def __init__(self, cfg: SimConfig, B: int, capacity: int):
        self.cfg, self.B, self.capacity = cfg, B, capacity
        tune = cfg.tuning  # GPU/performance switches, resolved for this backend and batch
        self.rotation = tune.core_rotation_method(cfg.arch)
        n = self.n_grid = cfg.n_grid
        self.dx, self.inv_dx, self.dt = 1.0 / n, float(n), cfg.effective_dt()
        self.vol = cfg.spacing ** 3
        self.materials = make_materials(cfg)  # the registered materials (materials.py), id order
        self.elasticity = FixedCorotated(cfg)  # their common stress law
        fb = ti.FieldsBuilder()
        f32, vec, mat = ti.f32, ti.types.vector(3, ti.f32), ti.types.matrix(3, 3, ti.f32)
        self.x, self.v = vec.field(), vec.field()  # B,N,3
        self.C, self.F = mat.field(), mat.field()  # B,N,3,3
        self.Jp, self.sigma_y = ti.field(f32), ti.field(f32)  # B,N
        self.damage = ti.field(ti.i32)  # B,N
        self.material = ti.field(ti.i32)  # B,N: 0 core, 1 skin, -1 padding (a scene with fewer particles than n)
        self.body = ti.field(ti.i32)  # B,N: the velocity field of the particle's piece (pieces.colour)
        self.K = K = cfg.fields  # velocity fields per node and scene: grid slot b * K + f
        self.grid_v, self.grid_m = vec.field(), ti.field(f32)  # B*K,n,n,n
        self.n_fields = ti.field(ti.i32, shape=())  # fields 0 .. n_fields-1 may hold mass (the rest stay empty)
        self.field_side = ti.field(ti.i32)  # B*K: the side of the blade field f's pieces are on (+1, -1, 0)
        self.lanes = -(-capacity // 32) * 32  # the warp scatter's particle slots per scene: no warp spans two
        # the particle the scatter's slot i of scene b handles: identity, or particles by base cell (sort_by_cell)
        self.order, self.cell_key = ti.field(ti.i32), ti.field(ti.i32)  # B,lanes
        self.cell_slot = ti.field(ti.i32)  # B*n^3: particles per cell, then their prefix sum (sort_by_cell)
        self._scan = None
        particle = (self.x, self.v, self.C, self.F, self.Jp, self.sigma_y, self.damage, self.body)
        if cfg.arch == "cuda":  # every scalar component in an array of its own: a warp's 32 threads read 32
            for f in particle:  # neighbouring floats (one struct per particle: B=16 substep 316 -> 253 us, H100)
                for e in f._get_field_members():
                    fb.dense(ti.ij, (B, capacity)).place(ScalarField(e))
        else:  # a CPU thread walks its particles one by one: one struct each, a cache line or two (20% faster, B=4)
            fb.dense(ti.ij, (B, capacity)).place(*particle)
        fb.dense(ti.ij, (B, capacity)).place(self.material)
        if tune.grid_layout_method(cfg.arch) == "soa":  # an array each of m, v_x, v_y, v_z: a warp's atomics on a z row
            for e in (self.grid_m, *(ScalarField(c) for c in self.grid_v._get_field_members())):  # of nodes hit
                fb.dense(ti.axes(0, 1, 2, 3), (B * K, n, n, n)).place(e)  # fewer memory sectors (10-15% on an H100)
        else:  # one struct per node: a CPU thread adds a node's four values one after another
            fb.dense(ti.axes(0, 1, 2, 3), (B * K, n, n, n)).place(self.grid_v, self.grid_m)
        fb.dense(ti.i, B * K).place(self.field_side)
        fb.dense(ti.ij, (B, self.lanes)).place(self.order, self.cell_key)
        self.can_sort = tune.resort_interval(cfg.arch) > 0  # the counters cost 4 bytes a node: only when re-sorting
        fb.dense(ti.i, B * n ** 3 if self.can_sort else 1).place(self.cell_slot)
        # knife per scene: start edge midpoint, frame (u, w, n), half extents, direction and length of travel,
        # speed, oscillation amplitude, opening speed of the wedge, smooth start/stop (the push)
        self.k_o, self.k_u, self.k_w, self.k_n, self.k_half, self.k_dir = (vec.field() for _ in range(6))
        self.k_depth, self.k_amp, self.k_speed, self.k_target = (ti.field(f32) for _ in range(4))
        self.k_on, self.k_smooth, self.k_sharp, self.k_hold = (ti.field(ti.i32) for _ in range(4))
        self.k_imp, self.k_imp_step = vec.field(), vec.field()  # momentum the knife gave the grid
        self.k_work, self.k_peak = ti.field(f32), ti.field(f32)
        self.bad_step = ti.field(ti.i32)  # first substep with NaN / runaway J (2**30 = none)
        # nodes [box[0:3], box[3:6]) of every scene hold all the scatter wrote since the last clear
        # (sim.tuning.grid_box)
        self.use_box = tune.grid_box_enabled(cfg.arch, B)
        self.box_threads = box_loop_threads(cfg.arch)
        self.use_warp = tune.warp_scatter_enabled(cfg.arch)
        self.scatter_block, self.gather_block = tune.block_dims(cfg.arch, B)  # None on the CPU: Taichi's chunking
        self.serial_scatter = not self.use_warp and cpu_threads() == 1  # Scatter.scatter
        self.box = ti.field(ti.i32)
        # substep number from which scene b is frozen (2**30 = never): every phase skips it from then on,
        # so a batched cut gives scene b its own substep budget.  A field, so ti.graph runs read it live.
        self.frozen_at = ti.field(ti.i32)
        # whether scene b scattered since its grid was last cleared: an idle scene's grid stays zero, so the clear
        # and the grid update skip it (one episode alone, MPPI's, cuts scene 0 with 15 idle; a batch's finished
        # episodes idle)
        self.wrote = ti.field(ti.i32)
        fb.dense(ti.i, B).place(self.k_o, self.k_u, self.k_w, self.k_n, self.k_half, self.k_dir, self.k_depth,
                                self.k_amp, self.k_speed, self.k_target, self.k_on, self.k_smooth, self.k_sharp, self.k_hold,
                                self.k_imp,
                                self.k_imp_step, self.k_work, self.k_peak, self.bad_step, self.frozen_at, self.wrote)
        fb.dense(ti.i, 6).place(self.box)
        self.tree = fb.finalize()
        self.bad_step.fill(2 ** 30)
        self.frozen_at.fill(2 ** 30)
        self.material.fill(-1)  # every slot is padding until particles are loaded into it
        self.n_fields[None] = 1
        self.box.from_numpy(np.array([0, 0, 0, n, n, n], np.int32))  # a fresh grid: clear it all once
        self.wrote.fill(1)
        self.order.from_numpy(np.broadcast_to(np.arange(self.lanes, dtype=np.int32), (B, self.lanes)).copy())
        self.p2g, self.grid_op, self.g2p = self._phase_kernels()
        self._graphs = {}  # k -> compiled ti.graph of k substeps

    def destroy(self) -> None:
        for slot in getattr(self, "_slots", {}).values():
            slot.destroy()
        self.tree.destroy()

    def slot(self, name: str, every_scene: bool = False):
        """The SceneSlot ``name`` (topocut.sim.slots: one scene's particle fields on the device; ``every_scene``:
        the BatchSlot, all B scenes), made on first use and freed with the solver."""
        from topocut.sim.slots import BatchSlot, SceneSlot

        slots = self.__dict__.setdefault("_slots", {})
        if name not in slots:
            slots[name] = (BatchSlot if every_scene else SceneSlot)(self)
        return slots[name]

    @ti.func
    def base_node(self, xp):
        base = ti.cast(xp * self.inv_dx - 0.5, ti.i32)
        return ti.max(ti.min(base, self.n_grid - 3), 0)  # keeps a NaN particle inside memory bounds

    # -- the phases as funcs: each is one top-level loop (one offloaded task) wherever it is inlined ----
    # Loops run over the constant capacity (not the particle count n) so no serial task computes their
    # bounds at launch; scalar arguments are ti.template() so that no serial task stores them either.
    @ti.func
    def active(self, b, step):
        """Scene b moves in substep ``step`` (it is frozen from substep frozen_at[b] on)."""
        return step < self.frozen_at[b]

    @ti.func
    def live(self, b, p):
        """Particle p of scene b exists: scenes of one batch may hold different objects, so a scene with
        fewer particles than the batch's n pads its tail with material -1, which no phase visits."""
        return self.material[b, p] >= 0

    @ti.func
    def clear_grid(self, step):
        """Zero what the last scatter wrote, then note the scenes that scatter in substep ``step``.

        Only the scenes that scattered since their last clear (``wrote``): nothing else writes a node without
        mass (grid_op, the knife, the tools act where m > 0), so an idle scene's grid is still zero."""
        if ti.static(self.use_box):  # only what the last scatter wrote; then the box is empty
            if ti.static(self.box_threads):  # CUDA: threads read the box themselves (no serial task: box_loop_threads)
                for t in range(self.box_threads):
                    lo, ext = self.box_extent()
                    per_slot = ext[0] * ext[1] * ext[2]
                    q = t
                    while q < self.B * self.n_fields[None] * per_slot:
                        s, r = q // per_slot, q % per_slot
                        b, f = s // self.n_fields[None], s % self.n_fields[None]
                        if self.wrote[b]:
                            I = self.box_node(lo, ext, r)
                            self.grid_v[b * self.K + f, I] = ti.Vector.zero(ti.f32, 3)
                            self.grid_m[b * self.K + f, I] = 0.0
                        q += self.box_threads
            else:
                for b, f, i, j, k in ti.ndrange(self.B, self.n_fields[None], (self.box[0], self.box[3]),
                                                (self.box[1], self.box[4]), (self.box[2], self.box[5])):
                    if self.wrote[b]:
                        self.grid_v[b * self.K + f, i, j, k] = ti.Vector.zero(ti.f32, 3)
                        self.grid_m[b * self.K + f, i, j, k] = 0.0
        else:
            for I in ti.grouped(self.grid_m):
                if self.wrote[I[0] // self.K]:
                    self.grid_v[I] = ti.Vector.zero(ti.f32, 3)
                    self.grid_m[I] = 0.0
        for b in range(self.B):
            self.wrote[b] = 1 if self.active(b, step) else 0
            if ti.static(self.use_box):
                if b == 0:  # empty the box for this scatter: here, not in a serial task of its own (a launch)
                    for d in ti.static(range(3)):
                        self.box[d], self.box[d + 3] = self.n_grid, 0

    @ti.func
    def box_extent(self):
        """The grid box's low corner and extent (3,) each, an empty box's extent 0."""
        lo = ti.Vector([self.box[0], self.box[1], self.box[2]])
        return lo, ti.max(ti.Vector([self.box[3], self.box[4], self.box[5]]) - lo, 0)

    @ti.func
    def box_node(self, lo, ext, r):
        """The box's r-th node (z fastest), r < ext[0] ext[1] ext[2]."""
        return lo + ti.Vector([r // (ext[1] * ext[2]), (r // ext[2]) % ext[1], r % ext[2]])

    @ti.func
    def grow_box(self, base):
        """A scatter writes nodes base .. base + 2 (one box for all scenes).  Every scatter into grid_v / grid_m
        calls it (the solver's, the spoon's sided one), so grid_op and the next clear see all it wrote."""
        if ti.static(self.use_box):
            for d in ti.static(range(3)):  # read first: the box only grows, so most particles need no atomic
                if base[d] < self.box[d]:
                    ti.atomic_min(self.box[d], base[d])
                if base[d] + 3 > self.box[d + 3]:
                    ti.atomic_max(self.box[d + 3], base[d] + 3)

    @ti.func
    def update_grid(self, t: ti.template(), contact: ti.template()):
        if ti.static(self.use_box and self.box_threads):  # CUDA: as clear_grid's, no serial task for the bounds
            for u in range(self.box_threads):
                lo, ext = self.box_extent()
                per_scene = ext[0] * ext[1] * ext[2]
                q = u
                while q < self.B * per_scene:
                    b, r = q // per_scene, q % per_scene
                    if self.wrote[b]:  # an idle scene's nodes are empty
                        self.update_node(b, self.box_node(lo, ext, r), t, contact)
                    q += self.box_threads
        elif ti.static(self.use_box):
            for b, i, j, k in ti.ndrange(self.B, (self.box[0], self.box[3]), (self.box[1], self.box[4]),
                                         (self.box[2], self.box[5])):
                if self.wrote[b]:  # an idle scene's nodes are empty
                    self.update_node(b, ti.Vector([i, j, k]), t, contact)
        else:
            for b, i, j, k in ti.ndrange(self.B, self.n_grid, self.n_grid, self.n_grid):
                if self.wrote[b]:
                    self.update_node(b, ti.Vector([i, j, k]), t, contact)

    @ti.func
    def update_node(self, b, I, t, contact: ti.template()):
        """All velocity fields of node I of scene b: gravity, contact between fields, knife, board, walls."""
        M, P, bodies = 0.0, ti.Vector.zero(ti.f32, 3), 0
        for f in range(self.n_fields[None]):  # the node's centre of mass: what contact is measured against
            m = self.grid_m[b * self.K + f, I]
            if m > 0:
                M, P, bodies = M + m, P + self.grid_v[b * self.K + f, I], bodies + 1
        if M > 0:
            pos = I.cast(ti.f32) * self.dx
            g = ti.Vector([0.0, 0.0, -self.dt * self.cfg.gravity])
            v_cm = P / M + g
            for f in range(self.n_fields[None]):
                m = self.grid_m[b * self.K + f, I]
                if m > 0:
                    v = self.grid_v[b * self.K + f, I] / m + g
                    if bodies > 1:  # pieces meet here: no pulling, no interpenetration
                        v = self.field_contact(b, f, I, v, v_cm)
                    if self.k_on[b] == 1:
                        v_old = v
                        v, touched = self.knife_contact(b, f, pos, v, t, contact)
                        if touched:  # only where the blade acted: atomics on one address contend on a GPU
                            self.k_imp_step[b] += m * (v - v_old)
                    self.grid_v[b * self.K + f, I] = self.boundaries(I, pos, v)

    @ti.func
    def boundaries(self, I, pos, v):
        if ti.static(self.cfg.board):  # the board: no downward velocity, Coulomb friction on the rest
            if pos[2] <= self.cfg.board_z and v[2] < 0:
                vt = ti.Vector([v[0], v[1], 0.0])
                vt_n = vt.norm() + 1e-12
                v = vt * ti.max(0.0, 1 + self.cfg.friction * v[2] / vt_n)
        if ti.static(self.cfg.walls):
            for d in ti.static(range(3)):
                if I[d] < 3 and v[d] < 0:
                    v[d] = 0
                if I[d] > self.n_grid - 3 and v[d] > 0:
                    v[d] = 0
        return v

    @ti.func
    def gather(self, n: ti.template(), step: ti.template(), t: ti.template()):
        ti.loop_config(block_dim=self.gather_block)
        for b, p in ti.ndrange(self.B, self.capacity):
            if self.active(b, step):  # a frozen scene keeps x, v, C and its knife totals
                if p == 0 and self.k_on[b] == 1:  # one thread per scene books the knife's impulse of this substep
                    self.record_knife(b, t)
                if p < n and self.live(b, p):
                    self.gather_particle(b, p, step)
                    self.blade_damage(b, p, t)

    @ti.func
    def record_knife(self, b, t):
        imp = self.k_imp_step[b]
        _, vk = self.knife_motion(b, t)
        self.k_imp[b] += imp
        self.k_work[b] += imp.dot(vk)
        self.k_peak[b] = ti.max(self.k_peak[b], imp.norm() / self.dt)
        self.k_imp_step[b] = ti.Vector.zero(ti.f32, 3)

    @ti.func
    def gather_particle(self, b, p, step):
        base = self.base_node(self.x[b, p])
        fx = self.x[b, p] * self.inv_dx - base.cast(ti.f32)
        new_v, new_C = apic_gather(self.grid_v, b * self.K + self.body[b, p], base, fx, self.dx, self.inv_dx)
        self.v[b, p], self.C[b, p] = new_v, new_C
        xn = self.x[b, p] + self.dt * new_v
        if not (xn.norm() < 10.0):  # NaN or escaped
            ti.atomic_min(self.bad_step[b], step)
        self.x[b, p] = xn

    # -- kernels: one per phase (tools may act on the grid between grid_op and g2p) -------------------
    def _phase_kernels(self):
        """p2g, grid_op, g2p of this solver.  Free kernels, not methods: ti.graph dispatches only those."""
        s = self

        @ti.kernel
        def p2g(n: ti.i32, step: ti.i32):
            s.clear_grid(step)
            s.scatter(n, step)

        @ti.kernel
        def grid_op(t: ti.f32, contact: ti.i32):
            s.update_grid(t, contact)

        @ti.kernel
        def g2p(n: ti.i32, step: ti.i32, t: ti.f32):
            s.gather(n, step, t)

        return p2g, grid_op, g2p

    def substep(self, n: int, step: int, t: float = 0.0, contact: int = 0) -> None:
        self.p2g(n, step)
        self.grid_op(t, contact)
        self.g2p(n, step, t)

    def advance(self, n: int, step: int, ts, contact: int = 0) -> None:
        """len(ts) substeps, numbered step, step + 1, ... at times ts, from one Python call.

        Same kernels and arguments as len(ts) ``substep`` calls (so the same result bit for bit), but a
        compiled ti.graph dispatches the 3 len(ts) launches from C++: no Python between them, no compile.
        """
        graph = self._graph(len(ts))
        if graph is None:  # no kernel graphs on this backend: the same launches from Python
            for j, t in enumerate(ts):
                self.substep(n, step + j, t, contact)
            return
        args = {"n": int(n), "contact": int(contact)}
        for j, t in enumerate(ts):
            args[f"step{j}"], args[f"t{j}"] = int(step) + j, float(t)
        graph.run(args)

    def _graph(self, k: int):
        if k not in self._graphs:
            def arg(name, dtype):
                return ti.graph.Arg(ti.graph.ArgKind.SCALAR, name, dtype)

            try:
                n, contact = arg("n", ti.i32), arg("contact", ti.i32)
                g = ti.graph.GraphBuilder()
                for j in range(k):
                    step, t = arg(f"step{j}", ti.i32), arg(f"t{j}", ti.f32)
                    g.dispatch(self.p2g, n, step)
                    g.dispatch(self.grid_op, t, contact)
                    g.dispatch(self.g2p, n, step, t)
                self._graphs[k] = g.compile()
            except Exception as e:  # noqa: BLE001 (any backend limitation: keep simulating, say so once)
                warnings.warn(f"ti.graph unavailable ({type(e).__name__}: {e}); MPMSolver.advance falls back to "
                              f"one Python call per phase", RuntimeWarning, stacklevel=3)
                self._graphs[k] = None
        return self._graphs[k]

    @ti.kernel
    def reset_knife_stats(self):
        for b in range(self.B):
            self.k_imp[b] = ti.Vector.zero(ti.f32, 3)
            self.k_imp_step[b] = ti.Vector.zero(ti.f32, 3)
            self.k_work[b] = 0.0
            self.k_peak[b] = 0.0

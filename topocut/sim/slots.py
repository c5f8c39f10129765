"""Reordering the solver's particle slots (``sim.resort_every``, CuttingEnv.resort).

Particles drift across cell borders during a cut, and the GPU warp scatter's runs of same-cell particles
shrink with it (docs/sim.md).  A new slot order moves every particle field of every scene by one
permutation (the scenes share ``material``) through one scratch field per type; ``ids`` moves with them,
so CuttingEnv can hand states back in particle order.
"""
import numpy as np
import taichi as ti


@ti.data_oriented
class SlotPermutation:
    """Scratch fields and gather kernels for an MPMSolver's B scenes of ``capacity`` slots (made on first use)."""

    def __init__(self, solver):
        self.solver, self.B, self.capacity = solver, solver.B, solver.capacity
        fb = ti.FieldsBuilder()
        self.perm, self.tmp_i = ti.field(ti.i32), ti.field(ti.i32)  # cap
        self.x_scene = ti.types.vector(3, ti.f32).field()  # cap,3: one scene's positions for the host's sort
        self.tmp = {"vec": ti.types.vector(3, ti.f32).field(), "mat": ti.types.matrix(3, 3, ti.f32).field(),
                    "f32": ti.field(ti.f32), "i32": ti.field(ti.i32)}  # B,cap,...
        fb.dense(ti.i, self.capacity).place(self.perm, self.tmp_i, self.x_scene)
        fb.dense(ti.ij, (self.B, self.capacity)).place(*self.tmp.values())
        self.tree = fb.finalize()

    def destroy(self) -> None:
        self.tree.destroy()

    def apply(self, order: np.ndarray) -> None:
        """Slot i of every scene takes what slot order[i] holds (order: a permutation of the first n slots)."""
        s = self.solver
        perm = np.arange(self.capacity, dtype=np.int32)
        perm[:len(order)] = order
        self.perm.from_numpy(perm)
        for f, t in ((s.x, "vec"), (s.v, "vec"), (s.C, "mat"), (s.F, "mat"), (s.Jp, "f32"), (s.sigma_y, "f32"),
                     (s.damage, "i32")):
            self.gather(f, self.tmp[t])
        self.gather_shared(s.material)
        self.gather_shared(s.ids)

    def positions(self, b: int, n: int) -> np.ndarray:
        """Scene b's first n positions (n,3), copying one scene to the host instead of all B."""
        self.copy_scene(b)
        return self.x_scene.to_numpy()[:n]

    @ti.kernel
    def copy_scene(self, b: ti.i32):
        for i in range(self.capacity):
            self.x_scene[i] = self.solver.x[b, i]

    @ti.kernel
    def gather(self, f: ti.template(), tmp: ti.template()):
        for b, i in ti.ndrange(self.B, self.capacity):
            tmp[b, i] = f[b, self.perm[i]]
        for b, i in ti.ndrange(self.B, self.capacity):
            f[b, i] = tmp[b, i]

    @ti.kernel
    def gather_shared(self, f: ti.template()):
        for i in range(self.capacity):
            self.tmp_i[i] = f[self.perm[i]]
        for i in range(self.capacity):
            f[i] = self.tmp_i[i]

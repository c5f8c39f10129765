"""One scene's particle state kept on the device: a saved start for rollouts, and the copy ``get_state`` reads.

An MPPI iteration restores the same start into every scene of the batch once per chunk of rollouts, and the
episode restores it again after planning.  Through numpy that is a round trip of every particle field of all B
scenes (``Scenes._write``: at 128³ with 16 scenes some 200 MB each way, and det F of every particle on the host).
A ``SceneSlot`` holds one scene's fields (x, v, C, F, J_p, sigma_y, damage, body, material) in device memory:
``save(b)`` copies scene b into it and ``load()`` copies it into every scene, one kernel each, nothing through the
host.  ``to_numpy`` brings back only the slot's one scene (``get_state(b)`` no longer copies all B).

A ``BatchSlot`` holds every scene at once (``save()``, one kernel): MPPI keeps its rollouts' states after their
first cut there, and ``SceneSlot.save_from(batch, b)`` keeps the chosen one's scene, which the episode then
restores as its executed cut instead of simulating that cut again (docs/data.md, "The executed cut").
"""

import taichi as ti

from topocut.sim.runtime import to_host

FIELDS = ("x", "v", "C", "F", "Jp", "sigma_y", "damage", "body", "material")


def _like(src):
    """A field of ``src``'s element type (its shape comes from where it is placed)."""
    n, m = getattr(src, "n", None), getattr(src, "m", 1)
    if n is None:
        return ti.field(src.dtype)
    return ti.Matrix.field(n, m, src.dtype) if m > 1 else ti.Vector.field(n, src.dtype)


class _Slot:
    """The solver's fields (B, capacity) as attributes ``s<name>``, so that a slot's kernels reach them, and the
    slot's own fields of the same types, placed ``dense(axes, shape)``."""

    def __init__(self, solver, axes, shape):
        self.B, self.capacity = solver.B, solver.capacity
        self.sx, self.sv, self.sC, self.sF, self.sJp = (getattr(solver, k) for k in FIELDS[:5])
        self.ssigma_y, self.sdamage, self.sbody, self.smaterial = (getattr(solver, k) for k in FIELDS[5:])
        fb = ti.FieldsBuilder()
        self.f = {name: _like(getattr(solver, name)) for name in FIELDS}
        fb.dense(axes, shape).place(*self.f.values())
        self.tree = fb.finalize()
        self.x, self.v, self.C, self.F, self.Jp = (self.f[k] for k in FIELDS[:5])
        self.sigma_y, self.damage, self.body, self.material = (self.f[k] for k in FIELDS[5:])

    def destroy(self) -> None:
        self.tree.destroy()


@ti.data_oriented
class SceneSlot(_Slot):
    """Room for one scene of ``solver`` (its capacity of rows, padding included)."""

    def __init__(self, solver):
        super().__init__(solver, ti.i, solver.capacity)

    @ti.kernel
    def save(self, b: ti.i32):
        """Scene b of the solver -> the slot."""
        for p in range(self.capacity):
            self.x[p], self.v[p], self.C[p], self.F[p] = self.sx[b, p], self.sv[b, p], self.sC[b, p], self.sF[b, p]
            self.Jp[p], self.sigma_y[p], self.damage[p] = self.sJp[b, p], self.ssigma_y[b, p], self.sdamage[b, p]
            self.body[p], self.material[p] = self.sbody[b, p], self.smaterial[b, p]

    @ti.kernel
    def load(self):
        """The slot -> every scene of the solver."""
        for b, p in ti.ndrange(self.B, self.capacity):
            self.sx[b, p], self.sv[b, p], self.sC[b, p], self.sF[b, p] = self.x[p], self.v[p], self.C[p], self.F[p]
            self.sJp[b, p], self.ssigma_y[b, p], self.sdamage[b, p] = self.Jp[p], self.sigma_y[p], self.damage[p]
            self.sbody[b, p], self.smaterial[b, p] = self.body[p], self.material[p]

    @ti.kernel
    def save_from(self, src: ti.template(), b: ti.i32):
        """Scene b of a BatchSlot -> the slot."""
        for p in range(self.capacity):
            self.x[p], self.v[p], self.C[p], self.F[p] = src.x[b, p], src.v[b, p], src.C[b, p], src.F[b, p]
            self.Jp[p], self.sigma_y[p], self.damage[p] = src.Jp[b, p], src.sigma_y[b, p], src.damage[b, p]
            self.body[p], self.material[p] = src.body[b, p], src.material[b, p]

    def to_numpy(self, n: int) -> dict:
        """The slot's first n rows as numpy arrays, by field name."""
        return {name: to_host(fld)[:n] for name, fld in self.f.items()}


@ti.data_oriented
class BatchSlot(_Slot):
    """Room for every scene of ``solver`` at once (B x capacity rows)."""

    def __init__(self, solver):
        super().__init__(solver, ti.ij, (solver.B, solver.capacity))

    @ti.kernel
    def save(self):
        """Every scene of the solver -> the slot."""
        for b, p in ti.ndrange(self.B, self.capacity):
            self.x[b, p], self.v[b, p], self.C[b, p], self.F[b, p] = (self.sx[b, p], self.sv[b, p], self.sC[b, p],
                                                                      self.sF[b, p])
            self.Jp[b, p], self.sigma_y[b, p], self.damage[b, p] = self.sJp[b, p], self.ssigma_y[b, p], self.sdamage[b, p]
            self.body[b, p], self.material[b, p] = self.sbody[b, p], self.smaterial[b, p]

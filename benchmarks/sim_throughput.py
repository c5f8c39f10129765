"""Particle-substeps per second of the full cutting model against a plain MLS-MPM reference.

The full model is CuttingEnv cutting a cube (two materials, damage, von Mises
skin, oscillating SDF knife, board friction).  The reference is mpm3d.py's
shape in the same process, same particles, grid and batch: one fixed-corotated
material (SVD every step), gravity, walls, no knife and no damage.

    python benchmarks/sim_throughput.py --device cpu --quick
    python benchmarks/sim_throughput.py --device cuda          # 64^3 and 128^3, B = 1 and 16

Prints particle-substeps/s, the ratio full/reference and the batching gain B_max/B_1.
"""
import argparse
import time

import numpy as np
import taichi as ti

from topocut.sim.action import KnifeAction
from topocut.sim.config import SimConfig
from topocut.sim.env import CuttingEnv
from topocut.sim.mpm import init_taichi
from topocut.sim.objects import sample_object


@ti.data_oriented
class ReferenceMPM:
    """mpm3d.py-style MLS-MPM with a leading batch axis: one elastic material, nothing else."""

    def __init__(self, x: np.ndarray, B: int, n_grid: int, dt: float, spacing: float, E=5000.0, nu=0.2, rho=4.0):
        self.B, self.N, self.n_grid, self.dt = B, len(x), n_grid, dt
        self.dx, self.inv_dx = 1.0 / n_grid, float(n_grid)
        self.vol = spacing ** 3
        self.mass = rho * self.vol
        self.mu, self.la = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
        fb = ti.FieldsBuilder()
        vec, mat = ti.types.vector(3, ti.f32), ti.types.matrix(3, 3, ti.f32)
        self.x, self.v, self.C, self.F = vec.field(), vec.field(), mat.field(), mat.field()
        self.grid_v, self.grid_m = vec.field(), ti.field(ti.f32)
        fb.dense(ti.ij, (B, self.N)).place(self.x, self.v, self.C, self.F)
        fb.dense(ti.axes(0, 1, 2, 3), (B, n_grid, n_grid, n_grid)).place(self.grid_v, self.grid_m)
        self.tree = fb.finalize()
        self.x.from_numpy(np.broadcast_to(x.astype(np.float32), (B, self.N, 3)).copy())
        self.F.from_numpy(np.broadcast_to(np.eye(3, dtype=np.float32), (B, self.N, 3, 3)).copy())

    @ti.kernel
    def p2g(self):
        for I in ti.grouped(self.grid_m):
            self.grid_v[I] = ti.Vector.zero(ti.f32, 3)
            self.grid_m[I] = 0.0
        for b, p in self.x:
            Xp = self.x[b, p] * self.inv_dx
            base = ti.cast(Xp - 0.5, ti.i32)
            fx = Xp - base
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
            F = (ti.Matrix.identity(ti.f32, 3) + self.dt * self.C[b, p]) @ self.F[b, p]
            self.F[b, p] = F
            U, sig, V = ti.svd(F)
            J = F.determinant()
            tau = 2 * self.mu * (F - U @ V.transpose()) @ F.transpose() + ti.Matrix.identity(ti.f32, 3) * self.la * J * (J - 1)
            affine = -self.dt * self.vol * 4 * self.inv_dx ** 2 * tau + self.mass * self.C[b, p]
            for off in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
                dpos = (off.cast(ti.f32) - fx) * self.dx
                weight = w[off[0]][0] * w[off[1]][1] * w[off[2]][2]
                self.grid_v[b, base + off] += weight * (self.mass * self.v[b, p] + affine @ dpos)
                self.grid_m[b, base + off] += weight * self.mass

    @ti.kernel
    def grid_op(self):
        for b, i, j, k in self.grid_m:
            if self.grid_m[b, i, j, k] > 0:
                v = self.grid_v[b, i, j, k] / self.grid_m[b, i, j, k]
                v[2] -= self.dt * 9.8
                I = ti.Vector([i, j, k])
                for d in ti.static(range(3)):
                    if I[d] < 3 and v[d] < 0:
                        v[d] = 0
                    if I[d] > self.n_grid - 3 and v[d] > 0:
                        v[d] = 0
                self.grid_v[b, i, j, k] = v

    @ti.kernel
    def g2p(self):
        for b, p in self.x:
            Xp = self.x[b, p] * self.inv_dx
            base = ti.cast(Xp - 0.5, ti.i32)
            fx = Xp - base
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
            new_v = ti.Vector.zero(ti.f32, 3)
            new_C = ti.Matrix.zero(ti.f32, 3, 3)
            for off in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
                dpos = (off.cast(ti.f32) - fx) * self.dx
                weight = w[off[0]][0] * w[off[1]][1] * w[off[2]][2]
                g_v = self.grid_v[b, base + off]
                new_v += weight * g_v
                new_C += 4 * self.inv_dx ** 2 * weight * g_v.outer_product(dpos)
            self.v[b, p], self.C[b, p] = new_v, new_C
            self.x[b, p] += self.dt * new_v

    def run(self, steps: int) -> float:
        for _ in range(3):  # compile
            self.p2g(), self.grid_op(), self.g2p()
        ti.sync()
        t = time.perf_counter()
        for _ in range(steps):
            self.p2g()
            self.grid_op()
            self.g2p()
        ti.sync()
        return self.B * self.N * steps / (time.perf_counter() - t)


def full_model(n_grid: int, B: int, arch: str) -> tuple[float, int, int]:
    """(particle-substeps/s, particles per scene, substeps) of one batched cut through a cube."""
    env = CuttingEnv(SimConfig(n_grid=n_grid, batch_size=B, arch=arch, dwell_substeps=0))
    env.reset("cube")
    env.simulate(3)  # compile
    env.cut(KnifeAction(0.5, 0.5, depth=0.002))  # compile the knife path
    env.reset("cube")
    ti.sync()
    info = env.cut([KnifeAction(0.5 + 0.02 * b / max(B - 1, 1), 0.5, yaw=0.1 * b) for b in range(B)])
    rate = B * env.n * info.substeps / info.wall_time
    n, steps = env.n, info.substeps
    env.solver.destroy()
    return rate, n, steps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--quick", action="store_true", help="small grid and batch for a CPU smoke run")
    args = ap.parse_args()
    init_taichi(args.device)
    grids, batches = ((32,), (1, 4)) if args.quick else ((64, 128), (1, 16))
    print(f"device={args.device}  grids={grids}  batches={batches}")
    print(f"{'grid':>5} {'B':>3} {'N':>7} {'steps':>6} {'full p-steps/s':>15} {'ref p-steps/s':>14} {'full/ref':>9}")
    rates = {}
    for g in grids:
        for B in batches:
            full, n, steps = full_model(g, B, args.device)
            cfg = SimConfig(n_grid=g)
            x, _ = sample_object("cube", spacing=cfg.spacing)
            ref_model = ReferenceMPM(x, B, g, cfg.effective_dt(), cfg.spacing)
            ref = ref_model.run(steps)
            ref_model.tree.destroy()
            rates[g, B] = (full, ref)
            print(f"{g:>5} {B:>3} {n:>7} {steps:>6} {full:>15.3e} {ref:>14.3e} {full / ref:>9.3f}")
    for g in grids:
        (f1, r1), (fb, rb) = rates[g, batches[0]], rates[g, batches[-1]]
        print(f"grid {g}: batching gain B{batches[-1]}/B{batches[0]} (per particle-substep): "
              f"full {fb / f1:.2f}x, reference {rb / r1:.2f}x")


if __name__ == "__main__":
    main()

"""Why batching gains little: the plain MLS-MPM reference under different particle orders and layouts.

Same physics as ``sim_throughput.ReferenceMPM`` (three kernels per substep), same cube, grid and batch;
only the order in which GPU threads visit particles changes:

- ``lattice``: particles as sampled (neighbours in memory are neighbours in space), thread = (b, p);
- ``shuffled``: one random permutation of the particles, thread = (b, p);
- ``interleaved``: fields laid out (N, B), thread = (p, b): the 32 lanes of a warp cover 32 scenes'
  copies of a few particles, so their atomics hit different scenes' grids.

Plus the grid alone (clear + grid update of all B n^3 nodes, no particles) to show what the dense
batched grid costs.

    python benchmarks/p2g_order.py --device cuda --grid 84 --batches 1 16
"""
import argparse
import time

import numpy as np
import taichi as ti

from topocut.sim.config import SimConfig
from topocut.sim.mpm import init_taichi
from topocut.sim.objects import sample_object


@ti.data_oriented
class OrderedMPM:
    def __init__(self, x: np.ndarray, B: int, n_grid: int, dt: float, spacing: float, interleave: bool,
                 run: int = 1, E=5000.0, nu=0.2, rho=4.0):
        self.B, self.N, self.n_grid, self.dt, self.il, self.run_len = B, len(x), n_grid, dt, interleave, run
        self.dx, self.inv_dx = 1.0 / n_grid, float(n_grid)
        self.vol = spacing ** 3
        self.mass = rho * self.vol
        self.mu, self.la = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
        fb = ti.FieldsBuilder()
        vec, mat = ti.types.vector(3, ti.f32), ti.types.matrix(3, 3, ti.f32)
        self.x, self.v, self.C, self.F = vec.field(), vec.field(), mat.field(), mat.field()
        self.grid_v, self.grid_m = vec.field(), ti.field(ti.f32)
        shape = (self.N, B) if interleave else (B, self.N)
        fb.dense(ti.ij, shape).place(self.x, self.v, self.C, self.F)
        fb.dense(ti.axes(0, 1, 2, 3), (B, n_grid, n_grid, n_grid)).place(self.grid_v, self.grid_m)
        self.tree = fb.finalize()
        xs = np.broadcast_to(x.astype(np.float32), (B, self.N, 3))
        Fs = np.broadcast_to(np.eye(3, dtype=np.float32), (B, self.N, 3, 3))
        if interleave:
            xs, Fs = xs.swapaxes(0, 1), Fs.swapaxes(0, 1)
        self.x.from_numpy(np.ascontiguousarray(xs))
        self.F.from_numpy(np.ascontiguousarray(Fs))

    @ti.func
    def idx(self, b, p):
        r = ti.Vector([b, p])
        if ti.static(self.il):
            r = ti.Vector([p, b])
        return r

    @ti.func
    def update_one(self, q):
        Xp = self.x[q] * self.inv_dx
        base = ti.cast(Xp - 0.5, ti.i32)
        fx = Xp - base
        F = (ti.Matrix.identity(ti.f32, 3) + self.dt * self.C[q]) @ self.F[q]
        self.F[q] = F
        U, sig, V = ti.svd(F)
        J = F.determinant()
        tau = 2 * self.mu * (F - U @ V.transpose()) @ F.transpose() + ti.Matrix.identity(ti.f32, 3) * self.la * J * (J - 1)
        affine = -self.dt * self.vol * 4 * self.inv_dx ** 2 * tau + self.mass * self.C[q]
        return base, fx, affine

    @ti.func
    def flush(self, b, node, acc, r: ti.template()):
        if acc[r, 3] != 0:
            self.grid_v[b, node] += ti.Vector([acc[r, 0], acc[r, 1], acc[r, 2]])
            self.grid_m[b, node] += acc[r, 3]

    @ti.func
    def shift(self, b, cur, acc):
        """Flush the 9 nodes of the stencil's lowest z plane and move the window up one cell."""
        for i, j in ti.static(ti.ndrange(3, 3)):
            r = i * 9 + j * 3
            self.flush(b, cur + ti.Vector([i, j, 0]), acc, r)
            for c in ti.static(range(4)):
                acc[r, c] = acc[r + 1, c]
                acc[r + 1, c] = acc[r + 2, c]
                acc[r + 2, c] = 0.0
        return acc

    @ti.func
    def scatter_run(self, b, p0):
        """Particles p0 .. p0+run-1 of scene b in one thread: contributions to the same 27 nodes add up in
        registers; a step of the stencil by one cell along z flushes only the 9 nodes it leaves (any other
        move flushes all 27, as three steps)."""
        acc = ti.Matrix.zero(ti.f32, 27, 4)
        cur = ti.Vector([-1, -1, -1])
        for r in range(self.run_len + 1):
            p = p0 + r
            base = ti.Vector([-1, -1, -1])
            fx = ti.Vector.zero(ti.f32, 3)
            affine = ti.Matrix.zero(ti.f32, 3, 3)
            q = self.idx(b, 0)
            live = r < self.run_len and p < self.N
            if live:
                q = self.idx(b, p)
                base, fx, affine = self.update_one(q)
            d = base - cur
            steps = 0
            if cur[0] >= 0 and (d[0] != 0 or d[1] != 0 or d[2] != 0):
                steps = 3
                if d[0] == 0 and d[1] == 0 and d[2] == 1:
                    steps = 1
            for _ in range(steps):
                acc = self.shift(b, cur, acc)
                cur[2] += 1
            cur = base
            if live:
                w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
                mom = self.mass * self.v[q]
                for off in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
                    dpos = (off.cast(ti.f32) - fx) * self.dx
                    weight = w[off[0]][0] * w[off[1]][1] * w[off[2]][2]
                    val = weight * (mom + affine @ dpos)
                    rr = off[0] * 9 + off[1] * 3 + off[2]
                    for c in ti.static(range(3)):
                        acc[rr, c] += val[c]
                    acc[rr, 3] += weight * self.mass

    @ti.func
    def scatter_one(self, b, p):
        q = self.idx(b, p)
        base, fx, affine = self.update_one(q)
        w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
        for off in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
            dpos = (off.cast(ti.f32) - fx) * self.dx
            weight = w[off[0]][0] * w[off[1]][1] * w[off[2]][2]
            self.grid_v[b, base + off] += weight * (self.mass * self.v[q] + affine @ dpos)
            self.grid_m[b, base + off] += weight * self.mass

    @ti.func
    def gather_one(self, b, p):
        q = self.idx(b, p)
        Xp = self.x[q] * self.inv_dx
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
        self.v[q], self.C[q] = new_v, new_C
        self.x[q] += self.dt * new_v

    @ti.kernel
    def p2g(self):
        for I in ti.grouped(self.grid_m):
            self.grid_v[I] = ti.Vector.zero(ti.f32, 3)
            self.grid_m[I] = 0.0
        if ti.static(self.run_len > 1):
            for b, t in ti.ndrange(self.B, (self.N + self.run_len - 1) // self.run_len):
                self.scatter_run(b, t * self.run_len)
        elif ti.static(self.il):
            for p, b in ti.ndrange(self.N, self.B):
                self.scatter_one(b, p)
        else:
            for b, p in ti.ndrange(self.B, self.N):
                self.scatter_one(b, p)

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
        if ti.static(self.il):
            for p, b in ti.ndrange(self.N, self.B):
                self.gather_one(b, p)
        else:
            for b, p in ti.ndrange(self.B, self.N):
                self.gather_one(b, p)

    @ti.kernel
    def grid_only(self):
        for I in ti.grouped(self.grid_m):
            self.grid_v[I] = ti.Vector.zero(ti.f32, 3)
            self.grid_m[I] = 0.0

    def run(self, steps: int, phases) -> float:
        for _ in range(3):
            for f in phases:
                f()
        ti.sync()
        t = time.perf_counter()
        for _ in range(steps):
            for f in phases:
                f()
        ti.sync()
        return (time.perf_counter() - t) / steps


@ti.data_oriented
class SparseMPM:
    """The same reference on a sparse grid: B x (n/L)^3 pointer blocks of L^3 nodes, each block holding the
    list of particles whose stencil starts in it (``pid``, rebuilt every substep), so that p2g runs one GPU
    block per grid block and accumulates in shared memory (Taichi's block-local storage), as in
    taichi_elements and Gao et al. 2018."""

    def __init__(self, x: np.ndarray, B: int, n_grid: int, dt: float, spacing: float, L: int = 4,
                 max_per_block: int = 4096, E=5000.0, nu=0.2, rho=4.0):
        self.B, self.N, self.n_grid, self.dt, self.L = B, len(x), n_grid, dt, L
        self.dx, self.inv_dx = 1.0 / n_grid, float(n_grid)
        self.vol = spacing ** 3
        self.mass = rho * self.vol
        self.mu, self.la = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
        fb = ti.FieldsBuilder()
        vec, mat = ti.types.vector(3, ti.f32), ti.types.matrix(3, 3, ti.f32)
        self.x, self.v, self.C, self.F = vec.field(), vec.field(), mat.field(), mat.field()
        self.grid_v, self.grid_m, self.pid = vec.field(), ti.field(ti.f32), ti.field(ti.i32)
        fb.dense(ti.ij, (B, self.N)).place(self.x, self.v, self.C, self.F)
        nb = -(-n_grid // L)
        self.block = fb.dense(ti.axes(0), B).pointer(ti.axes(1, 2, 3), nb)
        self.block.dense(ti.axes(1, 2, 3), L).place(self.grid_v, self.grid_m)
        self.block.dynamic(ti.axes(4), max_per_block, chunk_size=L ** 3 * 8).place(self.pid)
        self.tree = fb.finalize()
        self.x.from_numpy(np.broadcast_to(x.astype(np.float32), (B, self.N, 3)).copy())
        self.F.from_numpy(np.broadcast_to(np.eye(3, dtype=np.float32), (B, self.N, 3, 3)).copy())

    @ti.kernel
    def clear(self):
        for I in ti.grouped(self.block):
            ti.deactivate(self.block, I)

    @ti.kernel
    def build_pid(self):
        ti.loop_config(block_dim=64)
        for b, p in self.x:
            base = ti.cast(self.x[b, p] * self.inv_dx - 0.5, ti.i32)
            ti.append(self.pid.parent(), [b, base[0] // self.L, base[1] // self.L, base[2] // self.L], p)

    @ti.kernel
    def p2g(self):
        ti.loop_config(block_dim=256)
        for I in ti.grouped(self.pid):
            p = self.pid[I]
            b = I[0]
            Xp = self.x[b, p] * self.inv_dx
            base = ti.cast(Xp - 0.5, ti.i32)
            fx = Xp - base.cast(ti.f32)
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
        ti.no_activate(self.block)
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

    def phases(self):
        return (self.clear, self.build_pid, self.p2g, self.grid_op, self.g2p)

    def run(self, steps: int, phases) -> float:
        return OrderedMPM.run(self, steps, phases)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--grid", type=int, default=84)
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 16])
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--variants", nargs="+", default=["lattice", "shuffled", "interleaved", "run8", "sparse"],
                    help="lattice (first: the yardstick) | shuffled | interleaved | il+shuffled | runK (K particles per thread) | sparse")
    args = ap.parse_args()
    init_taichi(args.device)
    cfg = SimConfig(n_grid=args.grid)
    x, _ = sample_object("cube", spacing=cfg.spacing)
    perm = np.random.default_rng(0).permutation(len(x))
    print(f"device={args.device} grid={args.grid} particles/scene={len(x)} steps={args.steps}")
    print(f"{'variant':>12} {'B':>3} {'us/substep':>10} {'p-st/s':>10} {'vs lattice':>10} {'max |dx|':>9}")
    base, ref_x = {}, {}
    for B in args.batches:
        for name in args.variants:
            if name.startswith("sparse"):
                m = SparseMPM(x, B, args.grid, cfg.effective_dt(), cfg.spacing)
                phases = m.phases()
            else:
                xs = x[perm] if "shuffled" in name else x
                run = int(name[3:]) if name.startswith("run") else 1
                m = OrderedMPM(xs, B, args.grid, cfg.effective_dt(), cfg.spacing, name.startswith("i"), run)
                phases = (m.p2g, m.grid_op, m.g2p)
            s = m.run(args.steps, phases)
            xe = m.x.to_numpy()
            if name == "lattice":
                base[B], ref_x[B] = s, xe
                g = m.run(args.steps, (m.grid_only, m.grid_op))
                print(f"{'grid only':>12} {B:>3} {g * 1e6:>10.1f} {'':>10} {g / s:>10.3f}")
            err = float(np.abs(xe - ref_x[B]).max()) if name == "lattice" or name.startswith(("sparse", "run")) else float("nan")
            m.tree.destroy()
            print(f"{name:>12} {B:>3} {s * 1e6:>10.1f} {B * len(x) / s:>10.3e} {base[B] / s:>10.3f} {err:>9.2e}",
                  flush=True)
    if len(args.batches) > 1:
        print(f"lattice batching gain B{args.batches[-1]}/B{args.batches[0]}: "
              f"{args.batches[-1] * base[args.batches[0]] / (args.batches[0] * base[args.batches[-1]]):.2f}x")


if __name__ == "__main__":
    main()

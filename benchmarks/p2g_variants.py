"""Why batching gains little: the plain MLS-MPM reference with other particle orders, scatters and grids.

Every variant is ``sim_throughput.ReferenceMPM`` (three kernels per substep) on the same cube, grid and
batch; one thing changes at a time:

- ``lattice``: particles as sampled (neighbours in memory are neighbours in space): the yardstick;
- ``shuffled``: one random permutation of the particles (no two lanes of a warp hit the same node);
- ``polar``: the rotation of F by Newton's polar iteration instead of an SVD (a cheaper particle update);
- ``runK``: one thread scatters K consecutive particles, adding their contributions to the same 27
  nodes in registers and flushing a node only when the stencil leaves it (about 3x fewer atomics on
  the lattice order);
- ``split`` / ``split-polar``: the particle update (F, SVD or polar, stress) in a loop of its own that
  stores the affine matrix; a light scatter loop then reads it (few registers, so many threads per SM
  to hide the atomics' latency);
- ``warp`` / ``warp-sorted`` (CUDA only): lanes of a warp whose particles share a base cell sum their
  stencils with shuffles and one lane issues the atomics (``sorted``: particles ordered by cell first);
- ``sparse``: a pointer grid of 4^3-node blocks, each holding the list of particles whose stencil
  starts in it (the layout of taichi_elements; grid work only where particles are);
- ``tiled`` (CUDA only): particles binned per 4^3-cell tile each substep, one CUDA block per tile
  accumulating in shared memory and flushing each node once (block-local P2G, Gao et al. 2018).

Plus the dense grid alone (clear + grid update of all B n^3 nodes). Each line prints the wall time per
substep, the ratio to ``lattice`` and the largest position difference from it after the same substeps
(float summation order only). An (N, B) field layout with thread = (p, b) was measured with this
script's first revision (commit 1da7f85, ``interleaved``).

    python benchmarks/p2g_variants.py --device cuda --grid 84 --batches 1 16
"""
import argparse

import numpy as np
import taichi as ti
from sim_throughput import ReferenceMPM  # the script's own folder is on sys.path when it runs
from taichi.lang.expr import Expr

from topocut.sim.config import SimConfig
from topocut.sim.materials import polar_rotation
from topocut.sim.objects import sample_object
from topocut.sim.runtime import init_taichi
from topocut.sim.scatter import warp_run_add
from topocut.sim.scenes import cell_order


@ti.data_oriented
class PolarMPM(ReferenceMPM):
    """The reference with the rotation of F = R S by Newton's iteration instead of an SVD (the full
    model's ``sim.tuning.core_rotation=polar``): a cheaper per-particle update, same scatter."""

    @ti.func
    def rotation(self, F):
        return polar_rotation(F)


@ti.data_oriented
class SplitMPM(ReferenceMPM):
    """The reference with p2g in two loops: the heavy particle update writes the affine matrix A (B,N,3,3),
    then a scatter that holds only x, v, A and the weights in registers."""

    def place_grid(self, fb) -> None:
        super().place_grid(fb)
        self.A = ti.types.matrix(3, 3, ti.f32).field()
        fb.dense(ti.ij, (self.B, self.N)).place(self.A)

    part = "all"  # ProbeMPM runs one part of it

    @ti.kernel
    def p2g(self):
        self.clear_grid()
        if ti.static(self.part in ("all", "update")):
            for b, p in self.x:
                _base, _fx, affine = self.stress_update(b, p)
                self.A[b, p] = affine
        if ti.static(self.part in ("all", "scatter", "mass", "store")):
            for b, p in self.x:
                Xp = self.x[b, p] * self.inv_dx
                base = ti.cast(Xp - 0.5, ti.i32)
                fx = Xp - base
                affine, mom = self.A[b, p], self.mass * self.v[b, p]
                w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
                for off in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
                    dpos = (off.cast(ti.f32) - fx) * self.dx
                    weight = w[off[0]][0] * w[off[1]][1] * w[off[2]][2]
                    if ti.static(self.part in ("all", "scatter")):
                        self.grid_v[b, base + off] += weight * (mom + affine @ dpos)
                        self.grid_m[b, base + off] += weight * self.mass
                    elif ti.static(self.part == "mass"):
                        self.grid_m[b, base + off] += weight * self.mass
                    else:
                        self.grid_v[b, base + off] = weight * (mom + affine @ dpos)
                        self.grid_m[b, base + off] = weight * self.mass


@ti.data_oriented
class ProbeMPM(SplitMPM):
    """Parts of the split p2g alone, to see where its time goes (not a simulator: positions drift apart).

    ``update``: the particle update loop only; ``scatter``: the light scatter loop only (4 atomics per node);
    ``mass``: the light scatter of the mass only (1 atomic per node); ``store``: the light scatter with plain
    stores instead of atomics (racy: the memory traffic of the scatter without the atomics); ``clear``: the
    grid clear alone (every probe includes it)."""

    def __init__(self, *args, part: str = "update", **kw):
        self.part = part
        super().__init__(*args, **kw)


@ti.data_oriented
class WarpMPM(ReferenceMPM):
    """p2g with a warp-level segmented reduction (CUDA only; Gao et al. 2018 sec. 4.2).

    Lanes of a warp whose particles share a base cell (and scene) and sit side by side in the warp form a
    run; each of the 27 stencil values is summed over the run with 5 shuffle steps and the run's first lane
    alone issues the 4 atomics.  Correct for any particle order (a run is only ever contiguous lanes with
    equal keys); fast when particles are ordered by cell (``sort``: 8 per cell here; the lattice order
    pairs 2 along z).  The runs' sums are the full model's (topocut.sim.scatter.warp_run_add), without the
    in-warp sort by cell that Scatter.scatter_warp does first."""

    def __init__(self, x, B, *args, sort: bool = False, **kw):
        if sort:
            x = x[cell_order(x, args[0])]  # args[0]: n_grid
        super().__init__(x, B, *args, **kw)
        self.Np = -(-self.N // 32) * 32  # every warp holds lanes of one scene

    @ti.kernel
    def p2g(self):
        self.clear_grid()
        ti.loop_config(block_dim=128)
        for i in range(self.B * self.Np):
            b, p = i // self.Np, i % self.Np
            lane = Expr(ti.global_thread_idx()) % 32
            live = p < self.N
            base, fx, affine, mom = ti.Vector([0, 0, 0]), ti.Vector.zero(ti.f32, 3), ti.Matrix.zero(ti.f32, 3, 3), \
                ti.Vector.zero(ti.f32, 3)
            key = -1 - lane  # lanes past the end never join a run
            if live:
                base, fx, affine = self.stress_update(b, p)
                mom = self.mass * self.v[b, p]
                key = ((b * self.n_grid + base[0]) * self.n_grid + base[1]) * self.n_grid + base[2]
            mass = self.mass if live else 0.0
            warp_run_add(self.grid_v, self.grid_m, self.dx, lane, key, b, base, fx, mass, mom, affine, live)


@ti.data_oriented
class SplitPolarMPM(SplitMPM):
    @ti.func
    def rotation(self, F):
        return polar_rotation(F)


@ti.data_oriented
class RunMPM(ReferenceMPM):
    """The reference whose p2g gives each thread ``run`` consecutive particles of one scene."""

    def __init__(self, *args, run: int = 8, **kw):
        self.run_len = run
        super().__init__(*args, **kw)

    @ti.func
    def flush(self, b, node, acc, r: ti.template()):
        if acc[r, 3] != 0:
            self.grid_v[b, node] += ti.Vector([acc[r, 0], acc[r, 1], acc[r, 2]])
            self.grid_m[b, node] += acc[r, 3]

    @ti.func
    def shift(self, b, cur, acc):
        """Flush the 9 nodes of the window's lowest z plane and move the window up one cell."""
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
        """Particles p0 .. p0+run-1: the 27 nodes' momentum and mass (rows of acc) add up in registers; a
        step of the stencil by one cell along z (the lattice's fast axis) flushes the 9 nodes it leaves,
        any other move all 27 (as three steps), and so does the end of the run."""
        acc = ti.Matrix.zero(ti.f32, 27, 4)
        cur = ti.Vector([-1, -1, -1])
        for r in range(self.run_len + 1):
            p = p0 + r
            live = r < self.run_len and p < self.N
            base, fx, affine = ti.Vector([-1, -1, -1]), ti.Vector.zero(ti.f32, 3), ti.Matrix.zero(ti.f32, 3, 3)
            if live:
                base, fx, affine = self.stress_update(b, p)
            d = base - cur
            steps = 0
            if cur[0] >= 0 and (d[0] != 0 or d[1] != 0 or d[2] != 0):
                steps = 1 if d[0] == 0 and d[1] == 0 and d[2] == 1 else 3
            for _ in range(steps):
                acc = self.shift(b, cur, acc)
                cur[2] += 1
            cur = base
            if live:
                w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
                mom = self.mass * self.v[b, p]
                for off in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
                    weight = w[off[0]][0] * w[off[1]][1] * w[off[2]][2]
                    val = weight * (mom + affine @ ((off.cast(ti.f32) - fx) * self.dx))
                    for c in ti.static(range(3)):
                        acc[off[0] * 9 + off[1] * 3 + off[2], c] += val[c]
                    acc[off[0] * 9 + off[1] * 3 + off[2], 3] += weight * self.mass

    @ti.kernel
    def p2g(self):
        self.clear_grid()
        for b, t in ti.ndrange(self.B, (self.N + self.run_len - 1) // self.run_len):
            self.scatter_run(b, t * self.run_len)


@ti.data_oriented
class SparseMPM(ReferenceMPM):
    """The reference on B x (n/L)^3 pointer blocks of L^3 nodes; ``pid`` lists each block's particles."""

    L, max_per_block = 4, 4096

    def place_grid(self, fb) -> None:
        self.pid = ti.field(ti.i32)
        self.block = fb.dense(ti.axes(0), self.B).pointer(ti.axes(1, 2, 3), -(-self.n_grid // self.L))
        self.block.dense(ti.axes(1, 2, 3), self.L).place(self.grid_v, self.grid_m)
        self.block.dynamic(ti.axes(4), self.max_per_block, chunk_size=self.L ** 3 * 8).place(self.pid)

    @ti.kernel
    def clear(self):  # frees every block (and its particle list): the grid is all zero again
        for I in ti.grouped(self.block):
            ti.deactivate(self.block, I)

    @ti.kernel
    def build_pid(self):
        for b, p in self.x:
            base = ti.cast(self.x[b, p] * self.inv_dx - 0.5, ti.i32) // self.L
            ti.append(self.pid.parent(), [b, base[0], base[1], base[2]], p)

    @ti.kernel
    def p2g(self):
        ti.loop_config(block_dim=256)
        for I in ti.grouped(self.pid):  # one GPU block per grid block's particle list
            self.scatter_particle(I[0], self.pid[I])

    def phases(self):
        return self.clear, self.build_pid, self.p2g, self.grid_op, self.g2p


@ti.data_oriented
class TiledMPM(ReferenceMPM):
    """The reference with a block-local scatter (CUDA only; Gao et al. 2018's idea in plain Taichi SIMT).

    Each substep bins the particles by the 4^3-cell tile of their base node (a slot per particle in its
    tile's list, a list of non-empty tiles); then one CUDA block per tile adds its particles' 27-node
    stencils into the tile's (4+2)^3 nodes in shared memory and flushes each node to the global grid once.
    Global atomics drop from 108 per particle to at most 864 per tile.  A tile's particles beyond ``cap``
    scatter straight to the global grid while binning."""

    T, BD, cap = 4, 128, 512

    def place_grid(self, fb) -> None:
        super().place_grid(fb)
        nt = self.nt = -(-self.n_grid // self.T)
        self.count, self.order, self.act, self.n_act = (ti.field(ti.i32) for _ in range(4))
        fb.dense(ti.axes(0, 1, 2, 3), (self.B, nt, nt, nt)).place(self.count)
        fb.dense(ti.ij, (self.B * nt ** 3, self.cap)).place(self.order)
        fb.dense(ti.i, self.B * nt ** 3).place(self.act)
        fb.place(self.n_act)

    @ti.kernel
    def bin(self):
        self.clear_grid()
        self.n_act[None] = 0
        nt = self.nt
        for b, p in self.x:
            t = ti.cast(self.x[b, p] * self.inv_dx - 0.5, ti.i32) // self.T
            code = ((b * nt + t[0]) * nt + t[1]) * nt + t[2]
            slot = ti.atomic_add(self.count[b, t], 1)
            if slot == 0:
                self.act[ti.atomic_add(self.n_act[None], 1)] = code
            if slot < self.cap:
                self.order[code, slot] = p
            else:
                self.scatter_particle(b, p)

    @ti.kernel
    def p2g(self):
        nt, W, BD = ti.static(self.nt, self.T + 2, self.BD)
        ti.loop_config(block_dim=BD)
        for g in range(self.n_act[None] * BD):
            tid = g % BD
            code = self.act[g // BD]
            b = code // (nt * nt * nt)
            t = ti.Vector([(code // (nt * nt)) % nt, (code // nt) % nt, code % nt])
            corner = t * self.T
            sm = ti.simt.block.SharedArray((W * W * W * 4,), ti.f32)
            for r in range((W * W * W * 4 + BD - 1) // BD):
                if r * BD + tid < W * W * W * 4:
                    sm[r * BD + tid] = 0.0
            ti.simt.block.sync()
            cnt = ti.min(self.count[b, t], self.cap)
            for r in range((cnt + BD - 1) // BD):
                if r * BD + tid < cnt:
                    p = self.order[code, r * BD + tid]
                    base, fx, affine = self.stress_update(b, p)
                    w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
                    mom = self.mass * self.v[b, p]
                    loc = base - corner
                    for off in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
                        weight = w[off[0]][0] * w[off[1]][1] * w[off[2]][2]
                        val = weight * (mom + affine @ ((off.cast(ti.f32) - fx) * self.dx))
                        li = (((loc[0] + off[0]) * W + loc[1] + off[1]) * W + loc[2] + off[2]) * 4
                        for c in ti.static(range(3)):
                            ti.atomic_add(sm[li + c], val[c])
                        ti.atomic_add(sm[li + 3], weight * self.mass)
            ti.simt.block.sync()
            for r in range((W * W * W + BD - 1) // BD):
                i = r * BD + tid
                if i < W * W * W and sm[i * 4 + 3] != 0:
                    node = corner + ti.Vector([i // (W * W), (i // W) % W, i % W])
                    self.grid_v[b, node] += ti.Vector([sm[i * 4], sm[i * 4 + 1], sm[i * 4 + 2]])
                    self.grid_m[b, node] += sm[i * 4 + 3]
            ti.simt.block.sync()  # the block's next tile reuses sm
            if tid == 0:
                self.count[b, t] = 0

    def phases(self):
        return self.bin, self.p2g, self.grid_op, self.g2p


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--grid", type=int, default=84)
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 16])
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--variants", nargs="+", default=["lattice", "shuffled", "polar", "split", "split-polar", "warp", "warp-sorted", "run4", "run8", "sparse",
                                                      "tiled"],
                    help="lattice (always first: the yardstick) | shuffled | polar | split | split-polar | warp | warp-sorted (CUDA only) | probe-{clear,update,scatter,mass,store} (p2g parts, clear included) | runK (K particles per thread) "
                         "| sparse | tiled (CUDA only)")
    args = ap.parse_args()
    init_taichi(args.device)
    cfg = SimConfig(n_grid=args.grid)
    x, _ = sample_object("cube", spacing=cfg.spacing)
    common = (args.grid, cfg.effective_dt(), cfg.spacing)
    print(f"device={args.device} grid={args.grid} particles/scene={len(x)} steps={args.steps}")
    print(f"{'variant':>10} {'B':>3} {'us/substep':>10} {'p-st/s':>10} {'vs lattice':>10} {'max |dx|':>9}")
    for B in args.batches:
        base_s, base_x = None, None
        for name in ["lattice"] + [v for v in args.variants if v != "lattice"]:
            if name in ("sparse", "tiled"):
                if name == "tiled" and args.device != "cuda":
                    print(f"{name:>10} {B:>3}  (CUDA only: shared memory)")
                    continue
                m = (SparseMPM if name == "sparse" else TiledMPM)(x, B, *common)
                phases = m.phases()
            elif name in ("polar", "split", "split-polar"):
                m = {"polar": PolarMPM, "split": SplitMPM, "split-polar": SplitPolarMPM}[name](x, B, *common)
                phases = m.p2g, m.grid_op, m.g2p
            elif name in ("warp", "warp-sorted"):
                if args.device != "cuda":
                    print(f"{name:>10} {B:>3}  (CUDA only: warp shuffles)")
                    continue
                m = WarpMPM(x, B, *common, sort=name == "warp-sorted")
                phases = m.p2g, m.grid_op, m.g2p
            elif name.startswith("probe-"):  # p2g part alone, plus clear (compare with 'grid only' B n^3 clear)
                m = ProbeMPM(x, B, *common, part=name[6:])
                phases = (m.p2g,)
            elif name.startswith("run"):
                m = RunMPM(x, B, *common, run=int(name[3:]))
                phases = m.p2g, m.grid_op, m.g2p
            elif name in ("lattice", "shuffled"):
                xs = x[np.random.default_rng(0).permutation(len(x))] if name == "shuffled" else x
                m = ReferenceMPM(xs, B, *common)
                phases = m.p2g, m.grid_op, m.g2p
            else:
                raise SystemExit(f"unknown variant {name!r}; valid: lattice, shuffled, polar, split, split-polar, runK, sparse, tiled")
            s = m.time_phases(args.steps, phases)
            xe = m.x.to_numpy()
            if name == "lattice":
                base_s, base_x = s, xe
                g = m.time_phases(args.steps, (m.grid_clear, m.grid_op))
                print(f"{'grid only':>10} {B:>3} {g * 1e6:>10.1f} {'':>10} {g / base_s:>10.3f}  (its share of lattice)")
            # shuffled particles sit in another order: compare the sorted coordinates
            err = np.abs(np.sort(xe, axis=1) - np.sort(base_x, axis=1)).max()
            m.tree.destroy()
            print(f"{name:>10} {B:>3} {s * 1e6:>10.1f} {B * len(x) / s:>10.3e} {base_s / s:>10.3f} {err:>9.2e}",
                  flush=True)


if __name__ == "__main__":
    main()

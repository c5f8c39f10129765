"""Particle-substeps per second of the full cutting model against a plain MLS-MPM reference.

The full model is CuttingEnv cutting a cube (two materials, damage, von Mises
skin, oscillating SDF knife, board friction).  The reference is mpm3d.py's
shape in the same process, same particles, grid and batch: one fixed-corotated
material (SVD every step), gravity, walls, no knife and no damage.  It is timed
two ways: as mpm3d.py runs it (one kernel of four loops per substep, "mpm3d")
and as three kernels per substep ("ref3", the shape the full model's phases have).

    python benchmarks/sim_throughput.py --device cpu --quick
    python benchmarks/sim_throughput.py --device cuda     # 64^3, 84^3 (~20k particles), 128^3; B = 1 and 16

Prints per case the wall time per substep (the median of ``--repeats`` cuts, and their range; a cut's wall
time includes the host's piece finding before the knife moves, printed apart as "split ms" per cut, and
"us sim" is the substep without it),
particle-substeps/s, the ratios full/mpm3d and full/ref3 (references timed as often), the first-run
compile time (warm-up; the offline cache hides it on reruns) and per grid the batching gain B_max/B_1.
``--fuse 1`` times the full model with one Python call per phase (the path before kernel graphs),
``--warp-scatter``, ``--resort`` and ``--set KEY=VAL,...`` (any SimConfig keys, the switches of sim.tuning
as ``tuning.KEY``, e.g. ``--set tuning.grid_layout=aos tuning.grid_layout=soa``) take several values, each a case timed in the same process (single GPU
scenes move by tens of percent between processes).  ``--profile`` adds Taichi's kernel profiler (device
time per offloaded task; it syncs after each launch, so the wall times of that run are not comparable).
"""
import argparse
import time

import numpy as np
import taichi as ti
import yaml

from topocut.sim.action import KnifeAction
from topocut.sim.config import SimConfig, TuningConfig
from topocut.sim.env import CuttingEnv, cell_order
from topocut.sim.mpm import apic_gather
from topocut.sim.objects import sample_object
from topocut.sim.runtime import init_taichi


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
        self.place_grid(fb)
        self.tree = fb.finalize()
        self.x.from_numpy(np.broadcast_to(x.astype(np.float32), (B, self.N, 3)).copy())
        self.F.from_numpy(np.broadcast_to(np.eye(3, dtype=np.float32), (B, self.N, 3, 3)).copy())

    def place_grid(self, fb) -> None:  # benchmarks/p2g_variants.py places a sparse grid instead
        n = self.n_grid
        fb.dense(ti.axes(0, 1, 2, 3), (self.B, n, n, n)).place(self.grid_v, self.grid_m)

    @ti.func
    def rotation(self, F):
        U, sig, V = ti.svd(F)
        return U @ V.transpose()

    @ti.func
    def stress_update(self, b, p):
        """Particle p's F update; returns its base node, fx and the APIC affine matrix with the stress."""
        Xp = self.x[b, p] * self.inv_dx
        base = ti.cast(Xp - 0.5, ti.i32)
        fx = Xp - base
        F = (ti.Matrix.identity(ti.f32, 3) + self.dt * self.C[b, p]) @ self.F[b, p]
        self.F[b, p] = F
        J = F.determinant()
        tau = 2 * self.mu * (F - self.rotation(F)) @ F.transpose() + ti.Matrix.identity(ti.f32, 3) * self.la * J * (J - 1)
        return base, fx, -self.dt * self.vol * 4 * self.inv_dx ** 2 * tau + self.mass * self.C[b, p]

    @ti.func
    def clear_grid(self):
        for I in ti.grouped(self.grid_m):
            self.grid_v[I] = ti.Vector.zero(ti.f32, 3)
            self.grid_m[I] = 0.0

    @ti.func
    def scatter_particle(self, b, p):
        base, fx, affine = self.stress_update(b, p)
        w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
        for off in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
            dpos = (off.cast(ti.f32) - fx) * self.dx
            weight = w[off[0]][0] * w[off[1]][1] * w[off[2]][2]
            self.grid_v[b, base + off] += weight * (self.mass * self.v[b, p] + affine @ dpos)
            self.grid_m[b, base + off] += weight * self.mass

    @ti.func
    def scatter(self):
        self.clear_grid()
        for b, p in self.x:
            self.scatter_particle(b, p)

    @ti.func
    def update_grid(self):
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

    @ti.func
    def gather(self):
        for b, p in self.x:
            Xp = self.x[b, p] * self.inv_dx
            base = ti.cast(Xp - 0.5, ti.i32)
            fx = Xp - base
            new_v, new_C = apic_gather(self.grid_v, b, base, fx, self.dx, self.inv_dx)  # the full model's gather
            self.v[b, p], self.C[b, p] = new_v, new_C
            self.x[b, p] += self.dt * new_v

    @ti.kernel
    def substep(self):  # mpm3d.py: the whole substep is one kernel
        self.scatter()
        self.update_grid()
        self.gather()

    @ti.kernel
    def p2g(self):
        self.scatter()

    @ti.kernel
    def grid_op(self):
        self.update_grid()

    @ti.kernel
    def grid_clear(self):
        self.clear_grid()

    @ti.kernel
    def g2p(self):
        self.gather()

    def run(self, steps: int, one_kernel: bool, repeats: int = 1) -> float:
        """Particle-substeps/s, the median of ``repeats`` timed runs of ``steps`` substeps."""
        phases = (self.substep,) if one_kernel else (self.p2g, self.grid_op, self.g2p)
        return self.B * self.N / float(np.median([self.time_phases(steps, phases) for _ in range(repeats)]))

    @staticmethod
    def time_phases(steps: int, phases) -> float:
        """Seconds per substep of running ``phases`` in order (after 3 untimed substeps that compile)."""
        for _ in range(3):  # compile
            for f in phases:
                f()
        ti.sync()
        t = time.perf_counter()
        for _ in range(steps):
            for f in phases:
                f()
        ti.sync()
        return (time.perf_counter() - t) / steps


def full_model(n_grid: int, B: int, arch: str, fuse: int | None, rotation: str, profile: bool = False,
               grid_box: str = "auto", warp_scatter: str = "auto", repeats: int = 1, resort: int = -1,
               extra: dict | None = None) -> dict:
    """Rate, wall time per substep (median over ``repeats`` cuts, and its range), particles, substeps and
    warm-up time of a batched cut through a cube."""
    kw = dict(extra or {})
    tuning = dict(core_rotation=rotation, grid_box=grid_box, warp_scatter=warp_scatter, resort_every=resort)
    if fuse is not None:
        tuning["fuse_substeps"] = fuse
    tuning.update(kw.pop("tuning", {}))  # --set tuning.KEY=... wins
    t = time.perf_counter()
    env = CuttingEnv(SimConfig(n_grid=n_grid, batch_size=B, arch=arch, dwell_time=0.0, tuning=TuningConfig(**tuning),
                               **kw))
    env.reset("cube")
    env.simulate(3)  # compile the phases
    env.cut(KnifeAction(0.5, 0.5, depth=0.002))  # knife path and the kernel graph
    ti.sync()
    warmup = time.perf_counter() - t
    if profile:
        ti.profiler.clear_kernel_profiler_info()
    us, split = [], []
    for _ in range(repeats):  # a single GPU scene is launch-bound: its time moves by tens of percent per run
        env.reset("cube")
        info = env.cut([KnifeAction(0.5 + 0.02 * b / max(B - 1, 1), 0.5, yaw=0.1 * b) for b in range(B)])
        us.append(info.wall_time / info.substeps * 1e6)
        split.append(info.split_time)
    med = float(np.median(us))
    split_ms = float(np.median(split)) * 1e3  # the host's piece finding before the knife moves (once per cut)
    out = dict(rate=B * env.n / (med * 1e-6), us=med, us_min=min(us), us_max=max(us), n=env.n,
               steps=info.substeps, warmup=warmup, split_ms=split_ms, us_sim=med - split_ms * 1e3 / info.substeps)
    env.solver.destroy()
    return out


def overrides(text: str) -> dict:
    """'tuning.grid_layout=soa,cfl=0.4' -> SimConfig keyword arguments, sim.tuning's in a dict under "tuning"
    (values read as YAML scalars)."""
    valid = [k for k in SimConfig.__dataclass_fields__ if k != "tuning"]
    valid += [f"tuning.{k}" for k in TuningConfig.__dataclass_fields__]
    out = {}
    for item in filter(None, text.split(",")):
        k, _, v = item.partition("=")
        if k not in valid:
            raise SystemExit(f"--set: unknown SimConfig key {k!r}; valid: {', '.join(valid)}")
        if k.startswith("tuning."):
            out.setdefault("tuning", {})[k.removeprefix("tuning.")] = yaml.safe_load(v)
        else:
            out[k] = yaml.safe_load(v)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--quick", action="store_true", help="small grids and batch for a CPU smoke run")
    ap.add_argument("--grids", type=int, nargs="+", help="n_grid values (default 64 84 128; quick 24 32)")
    ap.add_argument("--batches", type=int, nargs="+", help="batch sizes (default 1 16; quick 1 4)")
    ap.add_argument("--fuse", type=int, default=None, help="sim.tuning.fuse_substeps (default: TuningConfig's)")
    ap.add_argument("--rotation", default="auto", help="sim.tuning.core_rotation: auto | polar | svd")
    ap.add_argument("--grid-box", default="auto", help="sim.tuning.grid_box: auto | on | off")
    ap.add_argument("--warp-scatter", nargs="+", default=["auto"],
                    help="sim.tuning.warp_scatter values, each timed in this process: auto | on | off")
    ap.add_argument("--resort", type=int, nargs="+", default=[-1],
                    help="sim.tuning.resort_every values, each timed in this process: -1 auto | 0 never | substeps")
    ap.add_argument("--set", nargs="+", default=[""], metavar="KEY=VAL,...",
                    help="further SimConfig overrides, each group a case timed in this process "
                         "(e.g. tuning.grid_layout=aos tuning.grid_layout=soa)")
    ap.add_argument("--no-ref", action="store_true", help="time the full model only (no reference kernels)")
    ap.add_argument("--profile", action="store_true", help="print Taichi's kernel profiler per case")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per case; the median is reported")
    args = ap.parse_args()
    if args.profile:
        ti.init(arch=ti.cuda if args.device == "cuda" else ti.cpu, kernel_profiler=True, offline_cache=True,
                log_level=ti.WARN)
    init_taichi(args.device)
    grids = args.grids or ((24, 32) if args.quick else (64, 84, 128))
    batches = args.batches or ((1, 4) if args.quick else (1, 16))
    # every case in one process: a single scene's time moves by tens of percent between processes
    cases = [(w, r, o) for w in args.warp_scatter for r in args.resort for o in args.set]
    dev, tune = args.device, TuningConfig(core_rotation=args.rotation, grid_box=args.grid_box)
    box = {B: tune.grid_box_enabled(dev, B) for B in batches}
    print(f"device={dev}  grids={grids}  batches={batches}  fuse={args.fuse or tune.fuse_substeps}"
          f"  rotation={tune.core_rotation_method(dev)}"
          f"  grid_box={args.grid_box} {box}"
          f"  warp_scatter={[TuningConfig(warp_scatter=w).warp_scatter_enabled(dev) for w in args.warp_scatter]}"
          f"  resort_every={[TuningConfig(warp_scatter=w, resort_every=r).resort_interval(dev) for w, r, _ in cases]}"
          f"  set={args.set}")
    print(f"{'grid':>5} {'B':>3} {'scatter':>7} {'resort':>6} {'N':>7} {'steps':>6} {'us/substep':>10} {'full p-st/s':>12} "
          f"{'mpm3d p-st/s':>13} {'ref3 p-st/s':>12} {'full/mpm3d':>10} {'full/ref3':>9} {'warm-up s':>9} {'us range':>13} "
          f"{'split ms':>8} {'us sim':>7}")
    rates = {}
    for g in grids:
        for B in batches:
            mpm3d = ref3 = float("nan")
            for ws, r, o in cases:
                f = full_model(g, B, args.device, args.fuse, args.rotation, args.profile, args.grid_box,
                               ws, args.repeats, r, overrides(o))
                if args.profile:
                    print(f"-- kernel profile of the timed cut, full model, grid {g}, B {B}, scatter {ws}, resort {r} {o}")
                    ti.profiler.print_kernel_profiler_info()
                if not args.no_ref and mpm3d != mpm3d:  # the reference once per grid and batch
                    cfg = SimConfig(n_grid=g)
                    x, _ = sample_object("cube", spacing=cfg.spacing)
                    x = x[cell_order(x, g)]  # the full model's particles, in its order (CuttingEnv.reset)
                    ref_model = ReferenceMPM(x, B, g, cfg.effective_dt(), cfg.spacing)
                    mpm3d = ref_model.run(f["steps"], one_kernel=True, repeats=args.repeats)
                    ref3 = ref_model.run(f["steps"], one_kernel=False, repeats=args.repeats)
                    ref_model.tree.destroy()
                rates[g, B, ws, r, o] = (f["rate"], mpm3d, ref3)
                print(f"{g:>5} {B:>3} {ws:>7} {r:>6} {f['n']:>7} {f['steps']:>6} {f['us']:>10.1f} {f['rate']:>12.3e} "
                      f"{mpm3d:>13.3e} {ref3:>12.3e} {f['rate'] / mpm3d:>10.3f} {f['rate'] / ref3:>9.3f} "
                      f"{f['warmup']:>9.1f} {f['us_min']:>6.1f}-{f['us_max']:<6.1f} {f['split_ms']:>8.1f} "
                      f"{f['us_sim']:>7.1f} {o}", flush=True)
        b0, b1 = batches[0], batches[-1]
        for ws, r, o in cases:
            (f0, m0, r0), (f1, m1, r1) = rates[g, b0, ws, r, o], rates[g, b1, ws, r, o]
            print(f"grid {g} scatter {ws} resort {r} {o}: batching gain B{b1}/B{b0} (per particle-substep): full {f1 / f0:.2f}x, "
                  f"mpm3d {m1 / m0:.2f}x, ref3 {r1 / r0:.2f}x", flush=True)


if __name__ == "__main__":
    main()

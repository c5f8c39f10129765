"""Topology discovery per step for 20k/50k/100k particles at 64^3 and 128^3, beside one simulated cut.

    python benchmarks/topology.py --device cpu --quick      # ~1.5 min on a 2-core CPU
    python benchmarks/topology.py --device cuda             # all six sizes, each with its cut

Topology: a cube of particles (jittered lattice, side 0.16, so that the grid is
fully used) cut through by one vertical knife sweep, damaged particles in the
blade's band; each size is run once to compile/warm up, then ``--repeats``
times, and the median per step is printed (wall seconds; ``cpu`` is the
process CPU time of the whole call, robust to other jobs sharing the cores).

Cut: the simulator's wall time for ONE cut action at the same size: a
CuttingEnv with SimConfig(n_grid=grid, arch=device) holding a lattice cube of
about as many particles at the simulator's spacing, cut through the middle
down to the board (after a shallow warm-up cut that compiles the kernels).
``topo/cut`` is total topology time / cut time; the goal is < 0.10 on the
GPU, and < 2 s of topology at 50k particles, 128^3 on the CPU.  Discovery on
the simulated state after the cut is timed too (``sim topo``, its pieces in
``sim pcs``).  ``--quick``: 20k at 64^3 and 50k at 128^3; on the CPU the cut
is then simulated at 64^3 only (a 128^3 cut takes minutes there).
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from topocut.sim.action import KnifeAction, KnifeSweep
from topocut.topology import TopologyConfig, discover

STEPS = ("sdf", "carve", "marching_cubes", "smoothing", "components", "assignment", "tracking")
SHORT = {"marching_cubes": "mc", "smoothing": "smooth", "components": "comps", "assignment": "assign",
         "tracking": "track"}
CPU_GOAL_S, GPU_GOAL_RATIO = 2.0, 0.10


def cube(n: int, seed: int = 0):
    """About n particles filling a cube (side 0.16) on the board, cut at x = 0.5."""
    s = 0.16 / n ** (1 / 3)
    ax = np.arange(-0.08, 0.08 + 1e-9, s)
    g = np.stack(np.meshgrid(ax, ax, ax + 0.08, indexing="ij"), -1).reshape(-1, 3)
    x = g + np.random.default_rng(seed).uniform(-0.15 * s, 0.15 * s, g.shape) + np.array([0.5, 0.5, 0.05 + s / 2])
    dmg = np.abs(x[:, 0] - 0.5) < 1.5 * s
    x[dmg, 0] += np.sign(x[dmg, 0] - 0.5) * 0.002  # the blade pushed the interface apart
    sweep = KnifeSweep((0.5, 0.5, 0.3), (0.0, 1.0, 0.0), (0.0, 0.0, -1.0), (1.0, 0.0, 0.0), 0.15, 0.25, 0.0015)
    return x.astype(np.float32), dmg, sweep


def time_topology(n: int, res: int, device: str, repeats: int) -> tuple[dict, int, int]:
    x, dmg, sweep = cube(n)
    cfg = TopologyConfig(resolution=res, step_timings=True)  # per step: wait for the device after each
    fast = TopologyConfig(resolution=res)  # the total as pipelines run it: host and device overlap
    discover(x, dmg, sweep, cfg=cfg, device=device)  # warm-up (kernel compile / cache load)
    runs, cpu, totals = [], [], []
    for _ in range(repeats):
        c0 = time.process_time()
        runs.append(discover(x, dmg, sweep, cfg=cfg, device=device))
        cpu.append(time.process_time() - c0)
        totals.append(discover(x, dmg, sweep, cfg=fast, device=device).timings["total"])
    med = {k: float(np.median([r.timings[k] for r in runs])) for k in STEPS}
    med["synced"] = float(np.median([r.timings["total"] for r in runs]))  # sum of the steps, each waited for
    med["total"] = float(np.median(totals))
    med["cpu"] = float(np.median(cpu))
    return med, len(x), runs[-1].num_clusters


def time_cut(n: int, res: int, device: str) -> dict:
    """Wall seconds of one cut through a lattice cube of ~n particles at the simulator's spacing."""
    from topocut.sim import CuttingEnv
    from topocut.sim.config import SimConfig

    env = CuttingEnv(SimConfig(n_grid=res, arch=device), batch_size=1)
    s, m = env.cfg.spacing, max(2, round(n ** (1 / 3)))
    ax = (np.arange(m) - (m - 1) / 2) * s
    x = np.stack(np.meshgrid(ax + 0.5, ax + 0.5, ax + (m - 1) / 2 * s + s / 2 + env.cfg.board_z, indexing="ij"),
                 -1).reshape(-1, 3)
    mat = np.zeros(len(x), np.int32)
    t0 = time.perf_counter()
    env.load_particles(x, mat)
    env.cut(KnifeAction(0.5, 0.5, depth=2 * s))  # compiles every kernel of a cut
    warm = time.perf_counter() - t0
    times = []
    for _ in range(3):  # median of three: the first cuts of a process also pay for GPU clocks ramping up
        env.load_particles(x, mat)
        t0 = time.perf_counter()
        info = env.cut(KnifeAction(0.5, 0.5))  # the blade plane x = 0.5, down to the board
        times.append(time.perf_counter() - t0)  # CutInfo reads the knife's forces back: the device has finished
    cut_s = float(np.median(times))
    st = env.state()
    topo = discover(st.x[0], st.damage[0], st.sweeps[0], cfg=TopologyConfig(resolution=res), device=device)
    env.solver.destroy()
    return {"cut": cut_s, "warm": warm, "substeps": info.substeps, "particles": len(x),
            "sim_topo": topo.timings["total"], "sim_pieces": topo.num_clusters}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    ap.add_argument("--quick", action="store_true", help="20k particles at 64^3 and 50k at 128^3 only")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-cut", action="store_true", help="skip the simulated cuts")
    args = ap.parse_args()
    configs = [(20_000, 64), (50_000, 128)] if args.quick else [(n, r) for n in (20_000, 50_000, 100_000)
                                                               for r in (64, 128)]
    if not args.no_cut:
        from topocut.sim import init_taichi

        init_taichi(arch=args.device)
    t_start = time.perf_counter()
    print(f"device={args.device}  repeats={args.repeats}  (topology: median wall seconds per step; cpu = process "
          f"CPU seconds of the whole call; cut = one simulated cut at the same size, median of 3 after a warm-up cut)")
    cols = [SHORT.get(s, s) for s in STEPS] + ["synced", "total", "cpu", "cut", "substeps", "topo/cut", "sim topo", "sim pcs"]
    print(f"{'particles':>9} {'grid':>5} {'pcs':>3} " + " ".join(f"{c:>8}" for c in cols))
    rows = []
    for n, res in configs:
        med, count, pieces = time_topology(n, res, args.device, args.repeats)
        skip = args.no_cut or (args.quick and args.device == "cpu" and res > 64)
        cut = None if skip else time_cut(count, res, args.device)
        cells = [f"{med[s]:8.4f}" for s in (*STEPS, "synced", "total", "cpu")]
        if cut is None:
            cells += [f"{'-':>8}"] * 5
        else:
            cells += [f"{cut['cut']:8.3f}", f"{cut['substeps']:8d}", f"{med['total'] / cut['cut']:8.3f}",
                      f"{cut['sim_topo']:8.4f}", f"{cut['sim_pieces']:8d}"]
        print(f"{count:9d} {res:4d}^ {pieces:3d} " + " ".join(cells), flush=True)
        rows.append((count, res, med, cut))
    print()
    for count, res, med, cut in rows:
        line = f"{count:7d} particles {res}^3: topology {med['total']:.4f} s"
        if cut is not None:
            ratio = med["total"] / cut["cut"]
            line += (f" = {100 * ratio:.1f}% of one cut ({cut['cut']:.3f} s, {cut['particles']} particles,"
                     f" warm-up {cut['warm']:.1f} s)")
            if args.device == "cuda":
                line += f"  goal < {100 * GPU_GOAL_RATIO:.0f}%: {'met' if ratio < GPU_GOAL_RATIO else 'NOT met'}"
        if args.device == "cpu" and res == 128 and 40_000 <= count <= 60_000:
            line += f"  goal < {CPU_GOAL_S:.0f} s on the CPU: {'met' if med['total'] < CPU_GOAL_S else 'NOT met'}"
        print(line)
    print(f"benchmark wall time {time.perf_counter() - t_start:.1f}s")


if __name__ == "__main__":
    main()

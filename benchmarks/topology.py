"""Topology discovery timings per step for 20k/50k/100k particles at 64^3 and 128^3.

    python benchmarks/topology.py [--device cpu|cuda] [--quick] [--repeats 3]

A cube of particles (jittered lattice, side 0.16, like the "cube" object, so
that the 128^3 grid is fully used) cut through by one vertical knife sweep,
damaged particles in the blade's band.  Each configuration is run once to compile/warm up, then ``--repeats``
times; the median per step is printed with its ratio to the reference run
(the smallest configuration) and the total against the 2 s goal.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from topocut.sim.action import KnifeSweep
from topocut.topology import TopologyConfig, discover

STEPS = ("sdf", "carve", "marching_cubes", "smoothing", "components", "assignment", "tracking", "total",
         "cpu_total")
GOAL_S = 2.0


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


def run(n: int, res: int, device: str, repeats: int) -> tuple[dict, int, int]:
    x, dmg, sweep = cube(n)
    cfg = TopologyConfig(resolution=res)
    discover(x, dmg, sweep, cfg=cfg, device=device)  # warm-up (kernel compile / cache load)
    runs, cpu = [], []
    for _ in range(repeats):
        c0 = time.process_time()  # CPU seconds of this process: robust to other jobs sharing the cores
        runs.append(discover(x, dmg, sweep, cfg=cfg, device=device))
        cpu.append(time.process_time() - c0)
    med = {k: float(np.median([r.timings.get(k, 0.0) for r in runs])) for k in STEPS}
    med["cpu_total"] = float(np.median(cpu))
    return med, len(x), runs[-1].num_clusters


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    ap.add_argument("--quick", action="store_true", help="20k particles at 64^3 and 50k at 128^3 only")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    configs = [(20_000, 64), (50_000, 128)] if args.quick else [(n, r) for n in (20_000, 50_000, 100_000)
                                                               for r in (64, 128)]
    t0 = time.perf_counter()
    ref = None
    print(f"device={args.device}  repeats={args.repeats}  (median wall seconds per step; x = ratio to the first "
          f"row; cpu_total = process CPU seconds of the whole call; last column: total / {GOAL_S:.0f} s goal)")
    print(f"{'particles':>9} {'grid':>5} {'pieces':>6} " + " ".join(f"{s[:10]:>13}" for s in STEPS) + "  /goal")
    for n, res in configs:
        med, count, pieces = run(n, res, args.device, args.repeats)
        ref = ref or med
        cells = [f"{med[s]:6.3f}({med[s] / max(ref[s], 1e-9):4.1f}x)" for s in STEPS]
        print(f"{count:9d} {res:4d}^ {pieces:6d} " + " ".join(f"{c:>13}" for c in cells)
              + f"  {med['total'] / GOAL_S:5.2f}")
    print(f"benchmark wall time {time.perf_counter() - t0:.1f}s")


if __name__ == "__main__":
    main()

"""Where a batched cut's wall time goes outside its substeps: the blade plans, the split, arming the knife.

Cuts a cube in B scenes (sim_throughput.py's cut: 16 planes of different offsets and yaws, from a reset) and
times CuttingEnv.cut's parts by wrapping them (each ends at a host sync or runs on the host):

    python benchmarks/cut_parts.py --device cuda --n-grid 128 --batch 16     # one H200: docs/benchmarks.md
    python benchmarks/cut_parts.py --device cpu --n-grid 32 --batch 2 --cuts 1

Prints per cut: wall ms, the split (CutInfo.split_time), the blade plans (env._blade_plans), arming the knife,
setting the scenes' budgets, the substeps (env.simulate) and the rest (the damage counts, the results).
"""
import argparse
import time

import taichi as ti

import topocut.sim.env as E
from topocut.sim.action import KnifeAction
from topocut.sim.config import SimConfig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda", choices=["cpu", "cuda"])
    ap.add_argument("--n-grid", type=int, default=128)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--cuts", type=int, default=4)
    args = ap.parse_args()
    spent: dict[str, float] = {}

    def timed(name, fn):
        def run(*a, **k):
            t = time.perf_counter()
            out = fn(*a, **k)
            spent[name] = spent.get(name, 0.0) + time.perf_counter() - t
            return out
        return run

    E._blade_plans = timed("plans", E._blade_plans)
    B = args.batch
    env = E.CuttingEnv(SimConfig(n_grid=args.n_grid, batch_size=B, arch=args.device, dwell_time=0.0))
    env.simulate, env._arm_knife = timed("simulate", env.simulate), timed("arm", env._arm_knife)
    env._set_frozen = timed("budgets", env._set_frozen)
    env.reset("cube")
    env.cut(KnifeAction(0.5, 0.5, depth=0.002))  # compile
    acts = [KnifeAction(0.5 + 0.02 * b / max(B - 1, 1), 0.5, yaw=0.1 * b) for b in range(B)]
    print(f"{args.n_grid}^3, {B} scenes of {env.n} particles, {args.device}")
    for _ in range(args.cuts):
        env.reset("cube")
        ti.sync()
        spent.clear()
        info = env.cut(acts)
        rest = info.wall_time - sum(spent.values()) - info.split_time
        print(f"wall {info.wall_time * 1e3:7.1f} ms  split {info.split_time * 1e3:5.1f}  "
              + "  ".join(f"{k} {v * 1e3:6.1f}" for k, v in spent.items())
              + f"  rest {rest * 1e3:5.1f}  substeps {info.substeps}")


if __name__ == "__main__":
    main()

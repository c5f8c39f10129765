"""MPPI throughput: planner iterations/s and simulated cut-actions/s, sequential (B=1) vs batched (B=K).

    python benchmarks/mppi.py --device cpu --K 8 --H 1 --iters 1
    python benchmarks/mppi.py --device cuda --K 64 --H 2 --iters 3

The reference is the sequential run (one scene, K rollouts one after another)
in the same process; the batched run simulates all K sequences as K scenes of
one CuttingEnv.  The MPPI core alone (synthetic quadratic cost) is timed first
to show the planner's own overhead.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from topocut.planning import MPPI, MPPIConfig


def time_it(fn, repeats: int) -> float:
    fn()  # warm-up: kernel compilation, caches
    t0 = time.perf_counter()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - t0) / repeats


def bench_core(cfg: MPPIConfig, repeats: int) -> float:
    target = np.array([0.55, 0.45, 0.3, 0.0])
    mppi = MPPI(cfg, lambda s: np.sum((s - target) ** 2, axis=(1, 2)), np.random.default_rng(0))
    mean = np.tile([0.5, 0.5, 0.0, 0.0], (cfg.horizon, 1))
    return time_it(lambda: mppi.plan(mean), repeats)


def bench_sim(args, cfg: MPPIConfig) -> dict:
    from topocut.planning.rollout import make_sim_rollout
    from topocut.reward.config import RewardConfig
    from topocut.sim.config import SimConfig
    from topocut.sim.env import CuttingEnv
    from topocut.sim.objects import ObjectPose
    from topocut.tasks import make_goal, task_config

    pose, out = ObjectPose(), {}
    for label, batch in (("sequential B=1", 1), (f"batched B={args.K}", args.K)):
        sim = SimConfig()
        sim.arch, sim.batch_size = args.device, batch
        if args.n_grid:
            sim.n_grid = args.n_grid
        env = CuttingEnv(sim, batch_size=batch)
        env.reset(args.object, pose, seed=0)
        goal = make_goal(task_config(args.task), args.object, pose, getattr(sim, "spacing", 0.01))
        rcfg = RewardConfig(backend=args.reward_backend,
                            device=args.device if args.reward_backend == "torch" else "cpu")
        rollout = make_sim_rollout(env, env.get_state(0), goal, reward_cfg=rcfg, board_z=sim.board_z)
        mppi = MPPI(cfg, rollout, np.random.default_rng(0))
        mean = np.stack([p.to_vector() for p in (goal.planes * cfg.horizon)[: cfg.horizon]]).astype(np.float64)
        dt = time_it(lambda m=mppi, u=mean: m.plan(u), args.repeats)
        out[label] = dt
        cuts = cfg.iterations * cfg.num_samples * cfg.horizon
        print(f"{label:>16}: {dt:8.2f} s/plan  {cfg.iterations / dt:8.3f} iterations/s  {cuts / dt:8.2f} cuts/s")
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    p.add_argument("--K", type=int, default=8, help="samples per MPPI iteration (= batched env size)")
    p.add_argument("--H", type=int, default=1, help="horizon (cuts per sampled sequence)")
    p.add_argument("--iters", type=int, default=1, help="MPPI iterations per plan")
    p.add_argument("--object", default="cube")
    p.add_argument("--task", default="slice")
    p.add_argument("--n-grid", type=int, default=0, help="override sim.n_grid (0: SimConfig default)")
    p.add_argument("--repeats", type=int, default=1)
    p.add_argument("--reward-backend", choices=("scipy", "torch"), default="scipy",
                   help="spectral reward eigensolver (torch runs on --device)")
    p.add_argument("--core-only", action="store_true", help="skip the simulator rollouts")
    args = p.parse_args()
    cfg = MPPIConfig(num_samples=args.K, horizon=args.H, iterations=args.iters)
    dt = bench_core(cfg, max(args.repeats, 20))
    print(f"MPPI core (K={args.K}, H={args.H}, {args.iters} it, synthetic cost): {dt * 1e3:.3f} ms/plan, "
          f"{args.iters / dt:.0f} iterations/s")
    if args.core_only:
        return
    try:
        out = bench_sim(args, cfg)
    except ImportError as e:
        print(f"simulator rollouts skipped: {e}")
        return
    seq, bat = out["sequential B=1"], out[f"batched B={args.K}"]
    print(f"batched / sequential speed-up: {seq / bat:.2f}x  (device={args.device}, K={args.K}, H={args.H}, "
          f"reward={args.reward_backend})")


if __name__ == "__main__":
    main()

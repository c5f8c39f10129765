"""An evaluation work unit's parts: the protocol's batched episodes as stage=eval runs them, in one process.

    python benchmarks/eval_units.py --device cpu --n-grid 64 --batch 2 --episodes 2 --policies oracle pddp --topo-resolution 64
    python benchmarks/eval_units.py --device cuda --n-grid 128 --batch 16 --episodes 16 --observe both
    python benchmarks/eval_units.py --device cuda --n-grid 128 --batch 16 --episodes 16 --policies pddp --runs 3
    python benchmarks/eval_units.py --device cuda --n-grid 128 --fps

A work unit of ``topocut.eval.runner.eval_tasks`` is ``--batch`` specs of the 405-episode protocol (a stride
through it, so tasks, objects and poses mix) run by one policy in one simulator batch: the protocol's task configs
(the stick and the dice push), ``eval.observation``'s FPS of every scene to 2,048 points, up to 5 cuts.  The policies:
the oracle, the heuristic, and PDDP with untrained weights at the paper's sizes (the time of an action does not
depend on the weights; where its untrained cuts fall does, a little).  Each policy's episodes are timed after a
warm-up batch, split into the simulator (cut, push, turn), discovery, the reward, the observations, the policy's act
and the rest (``--profile``: where the rest goes).

``--observe both`` runs every policy first as the engine did before 2026-12-01 (the reference: every policy's every
scene observed on the host, one scene at a time), then as now (no observation for the scripted policies, which read
none; the scenes' FPS in one launch on a GPU for the others), in the same process.  ``--runs 3`` runs each policy
over its episodes three times in a row, as a learned policy's work unit runs its three training seeds: before, each
run built its goals and their pieces' sizes and descriptors anew; now the later runs find them kept
(``topocut.episode.scoring.task_goal``, ``topocut.reward.distance``'s cache).
"""
from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from episodes import TIMES, instrument, timed  # noqa: E402 - the engine's timers, shared with episodes.py

PARTS = ("sim", "discovery", "reward", "observe", "act")


def policies(names, env, task_cfgs, device: str) -> dict:
    from topocut.planning.heuristic import HeuristicPolicy
    from topocut.planning.oracle import OraclePolicy

    out = {}
    for name in names:
        if name == "oracle":
            out[name] = OraclePolicy(board_z=env.cfg.board_z)
        elif name == "heuristic":
            out[name] = HeuristicPolicy(task_cfgs, spacing=env.cfg.spacing, board_z=env.cfg.board_z)
        elif name == "pddp":
            from topocut.policies.config import PolicyTrainConfig
            from topocut.policies.module import PDDPModule, PDDPPolicy

            module = PDDPModule(train=PolicyTrainConfig())  # untrained, the paper's sizes
            out[name] = PDDPPolicy(module, device=device, seed=0, board_z=env.cfg.board_z)
        else:
            raise SystemExit(f"--policies: {name!r} is not one of oracle, heuristic, pddp")
    return out


def timed_act(policy):
    """Book the policy's act (and act_batch, the engine's batched call) in TIMES["act"]."""
    cls = type(policy)
    for name in ("act", "act_batch"):
        fn = cls.__dict__.get(name)
        if fn is None or getattr(fn, "_timed", False):
            continue
        raw = fn.__func__ if isinstance(fn, (staticmethod, classmethod)) else fn

        def wrapped(*a, _fn=raw, **k):
            with timed("act"):
                return _fn(*a, **k)

        wrapped._timed = True
        setattr(cls, name, classmethod(wrapped) if isinstance(fn, classmethod)
                else staticmethod(wrapped) if isinstance(fn, staticmethod) else wrapped)


def forget_goals() -> None:
    """The goals and the goal pieces' work kept between runs (the engine before 2026-12-01 kept neither a goal nor,
    past 256 entries, a goal piece)."""
    from topocut.episode import scoring
    from topocut.reward import distance

    scoring._GOALS.clear()
    distance._CACHE.clear()


def run_unit(env, specs, warm, policy, sc, task_cfgs, observe_fn, way: str, profile: int = 0, first: bool = True) -> dict:
    from topocut.episode import run_episodes
    from topocut.eval.protocol import _episode

    if way == "before":  # every policy read the observed points, each scene's FPS on the host
        policy.observation_fields = None

        def observe(x, labels, seed):  # no batch method: scene by scene
            return observe_fn(x, labels, seed)
    else:
        policy.__dict__.pop("observation_fields", None)
        observe = observe_fn

    def counted(x, labels, seed):
        with timed("observe"):
            return observe(x, labels, seed)

    if getattr(observe, "batch", None) is not None:
        def batch(xs, labels, seeds):
            with timed("observe"):
                return observe.batch(xs, labels, seeds)

        counted.batch = batch
    if first:
        run_episodes(env, [_episode(s, task_cfgs[s.task]) for s in warm], policy, sc, max_cuts=5,
                     observe_fn=counted)  # warm-up: kernels, caches
    if way == "before" or first:  # a run's first pass over its episodes builds their goals
        forget_goals()
    TIMES.clear()
    prof = cProfile.Profile() if profile else None
    t0 = time.perf_counter()
    if prof is not None:
        prof.enable()
    logs = run_episodes(env, [_episode(s, task_cfgs[s.task]) for s in specs], policy, sc, max_cuts=5,
                        observe_fn=counted)
    wall = time.perf_counter() - t0
    if prof is not None:
        prof.disable()
        pstats.Stats(prof).sort_stats("cumulative").print_stats(profile)
    out = {"wall": wall, "episodes": len(specs), "cuts": sum(len(lg.actions) for lg in logs),
           **{k: TIMES.get(k, 0.0) for k in PARTS}}
    out["rest"] = wall - sum(out[k] for k in PARTS)
    return out


def fps_check(device: str, n_grid: int) -> None:
    """fps_clouds (one launch for all scenes) against fps scene by scene on the host: 16 posed objects at the
    grid's particle spacing to 2,048 points each, the time of each and whether every index is equal."""
    import torch

    from topocut.metrics import fps, fps_clouds
    from topocut.sim.objects import ObjectPose, sample_object

    names = ["cake", "cube", "ditto", "ham", "potato", "donut", "burger", "sushi"] * 2
    clouds = [np.asarray(sample_object(o, ObjectPose(0.5, 0.5, 0.1 * i, 0.8 + 0.025 * i), spacing=0.5 / n_grid)[0],
                         np.float32) for i, o in enumerate(names)]
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    fps_clouds(clouds[:2], 2048, device)  # warm-up: the kernel's compile
    sync()
    t = time.perf_counter()
    one = fps_clouds(clouds, 2048, device)
    sync()
    t_one = time.perf_counter() - t
    t = time.perf_counter()
    host = [fps(c, min(2048, len(c))) for c in clouds]
    t_host = time.perf_counter() - t
    print(f"fps_clouds, {len(clouds)} scenes ({min(map(len, clouds))}-{max(map(len, clouds))} particles) to 2048 on "
          f"{device}: host one by one {t_host:.3f} s, one call {t_one:.4f} s ({t_host / t_one:.1f}x); equal indices: "
          f"{all(np.array_equal(a, b) for a, b in zip(one, host))}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    p.add_argument("--n-grid", type=int, default=128)
    p.add_argument("--batch", type=int, default=16, help="scenes: the specs of a work unit")
    p.add_argument("--episodes", type=int, default=16, help="timed episodes a policy (after a warm-up batch)")
    p.add_argument("--policies", nargs="+", default=["oracle", "heuristic", "pddp"])
    p.add_argument("--observe", choices=("now", "before", "both"), default="now",
                   help="the engine as before 2026-12-01 (every scene observed on the host, no goal kept between "
                   "runs), as now, or both (before first, the reference)")
    p.add_argument("--runs", type=int, default=1, help="passes of each policy over the same episodes, one after "
                   "another (a learned policy's training seeds in a work unit: 3); the averages compare")
    p.add_argument("--topo-resolution", type=int, default=128)
    p.add_argument("--profile", type=int, default=0, help="cProfile each timed run and print this many entries of "
                   "most cumulative time (on CUDA a host sync books the queued work's wait)")
    p.add_argument("--fps", action="store_true", help="only fps_check: the scenes' FPS in one launch against the host")
    args = p.parse_args()
    if args.fps:
        return fps_check(args.device, args.n_grid)

    from topocut.episode import make_scoring
    from topocut.eval.config import EvalConfig
    from topocut.eval.protocol import episode_specs, make_observe_fn
    from topocut.eval.runner import task_configs
    from topocut.reward.config import RewardConfig
    from topocut.sim.config import SimConfig
    from topocut.sim.env import CuttingEnv
    from topocut.sim.runtime import init_taichi
    from topocut.topology.config import TopologyConfig

    init_taichi(args.device)
    ecfg = EvalConfig()
    specs = episode_specs(ecfg)
    stride = max(1, len(specs) // (args.episodes + args.batch))
    chosen = specs[::stride]
    # the warm-up: one episode of each task (the push and the turn compile on their first use)
    warm = [next(s for s in chosen if s.task == t) for t in ecfg.tasks]
    timed_specs = [s for s in chosen if s not in warm][:args.episodes]
    task_cfgs = task_configs(ecfg.tasks, ecfg.max_cuts)  # the protocol's own: push where the task pushes
    env = CuttingEnv(SimConfig(n_grid=args.n_grid, batch_size=args.batch, arch=args.device), batch_size=args.batch)
    instrument(env)
    sc = make_scoring(RewardConfig(backend="torch", device=args.device), TopologyConfig(resolution=args.topo_resolution),
                      min_fragment_points=ecfg.min_fragment_points, env=env)
    observe_fn = make_observe_fn(ecfg.observation, ecfg.num_points, device=args.device)
    ways = ("before", "now") if args.observe == "both" else (args.observe,)
    pols = policies(args.policies, env, task_cfgs, args.device)
    for pol in pols.values():
        timed_act(pol)
    print(f"{args.device}, {args.n_grid}^3, {args.batch} scenes, {len(timed_specs)} timed episodes a policy "
          f"(tasks {sorted({s.task for s in timed_specs})}, objects {sorted({s.object for s in timed_specs})}); "
          f"s an episode")
    print(f"{'policy':<10} {'way':<9} {'cuts':>5} {'wall':>7} " + " ".join(f"{k:>9}" for k in PARTS + ("rest",)))
    res = {}
    for name, pol in pols.items():
        for way in ways:
            runs = []
            for i in range(args.runs):
                r = run_unit(env, timed_specs, warm, pol, sc, task_cfgs, observe_fn, way, args.profile, first=i == 0)
                runs.append(r)
                n = r["episodes"]
                print(f"{name:<10} {way + (f' {i + 1}' if args.runs > 1 else ''):<9} {r['cuts']:>5} {r['wall'] / n:7.3f} "
                      + " ".join(f"{r[k] / n:9.3f}" for k in PARTS + ("rest",)))
            res[name, way] = {k: sum(r[k] for r in runs) / len(runs) if k != "episodes" else runs[0][k]
                              for k in runs[0]}
        if len(ways) == 2:
            a, b = res[name, "before"], res[name, "now"]
            print(f"{name}: now against before, same process: {a['wall'] / n:.3f} -> {b['wall'] / n:.3f} s an episode "
                  f"({a['wall'] / b['wall']:.2f}x), observations {a['observe'] / n:.3f} -> {b['observe'] / n:.3f} s")


if __name__ == "__main__":
    main()

"""Episode throughput of the engine (topocut.episode): a demonstration cut against the simulation inside it, and
the evaluation protocol's episodes batched against one at a time.

    python benchmarks/episodes.py --device cpu --n-grid 32 --K 4 --eval-episodes 4
    python benchmarks/episodes.py --device cuda --n-grid 64 --K 16 --eval-episodes 32

1. Demonstration (MPPI, K samples x `--iters` iterations, horizon 1, the rollouts are the K scenes of one
   batch): the wall time of each executed cut printed beside the time its rollouts spent in the simulator
   (CuttingEnv.cut/push/turn; of it the host split), topology discovery and the reward, and the rest.  The
   per-cut wall time projects 1,000 episodes of 5 cuts.
2. Evaluation: the first `--eval-episodes` episodes of the 405-episode protocol (a stride through it, so
   tasks, objects and poses mix) for the oracle and the heuristic, batched (B = `--batch` scenes) and, as the
   reference in the same process, one at a time (B = 1, the first `--ref-episodes` of them); the batched
   per-episode time projects the 405 episodes of a policy.
3. A learned policy's action (PDDP, untrained weights at the paper's sizes): one episode's ``act`` against
   ``act_batch`` of `--batch` episodes when the class has it (the evaluation's batched call).
"""
from __future__ import annotations

import argparse
import contextlib
import cProfile
import pstats
import time
from collections import defaultdict

import numpy as np

TIMES: dict[str, float] = defaultdict(float)


@contextlib.contextmanager
def timed(key: str):
    t0 = time.perf_counter()
    try:
        yield
    finally:
        TIMES[key] += time.perf_counter() - t0


def instrument(env) -> None:
    """Book the simulator's, discovery's and the reward's time in TIMES (wrapping the entry points)."""
    import topocut.reward as reward
    import topocut.topology as topology

    for name in ("cut", "push", "turn"):
        fn = getattr(env, name)

        def wrapped(*a, _fn=fn, **k):
            with timed("sim"):
                out = _fn(*a, **k)
            if getattr(out, "split_time", None) is not None:
                TIMES["sim_split"] += out.split_time
            return out

        setattr(env, name, wrapped)
    if getattr(topology, "_timed", False):  # a second env in this process: the modules are wrapped already
        return
    topology._timed = True
    disc = topology.discover

    def discover(*a, **k):
        with timed("discovery"):
            return disc(*a, **k)

    topology.discover = discover
    import topocut.topology.batch as batch  # MPPI's rollouts discover all scenes of a cut in one call

    disc_batch = batch.discover_batch

    def discover_batch(*a, **k):
        with timed("discovery"):
            return disc_batch(*a, **k)

    batch.discover_batch = discover_batch
    for name in ("spectral_rewards", "spectral_reward"):
        fn = getattr(reward, name)

        def rew(*a, _fn=fn, **k):
            with timed("reward"):
                return _fn(*a, **k)

        setattr(reward, name, rew)


def sim_config(args, batch: int):
    from topocut.sim.config import SimConfig

    return SimConfig(n_grid=args.n_grid, batch_size=batch, arch=args.device)


def bench_demo(args) -> dict:
    """The demonstration cut with each discovery mode of --discovery (both: per scene first, the reference); with
    --push and --push-last both, the rollouts' push after their last cut on (the reference) and off."""
    modes = {"both": (False, True), "batched": (True,), "per-scene": (False,)}[args.discovery]
    if args.push and args.push_last == "both":
        m = modes[-1]
        out = {last: demo_cuts(args, m, push_last=last, executed=EXECUTED[args.executed][0]) for last in (True, False)}
        a, b = out[True], out[False]
        print(f"rollouts without the push after their last cut against with it, same process: wall {a['wall']:.3f} "
              f"-> {b['wall']:.3f} s a cut ({a['wall'] / b['wall']:.2f}x), simulation {a['sim']:.3f} -> "
              f"{b['sim']:.3f} s ({a['sim'] / max(b['sim'], 1e-9):.2f}x)")
        return out
    if args.reward_kernels == "both":
        from reward_kernels import reference_kernels

        return before_and_now(args, modes[-1], reference_kernels(), "the reward's Warp kernels (FPS, neighbour queries)",
                              "reward")
    if args.host == "both":
        return before_and_now(args, modes[-1], host_functions("before"), "this session's host shortcuts", "rest")
    executed = EXECUTED[args.executed]
    if len(executed) > 1:
        m = modes[-1]
        out = {how: demo_cuts(args, m, push_last=args.push_last == "true", size_solver=args.size_solver,
                              executed=how) for how in executed}
        a = out[executed[0]]
        for how in executed[1:]:
            b = out[how]
            print(f"the executed cut {HOW[how]} against {HOW[executed[0]]}, same process: wall {a['wall']:.3f} -> "
                  f"{b['wall']:.3f} s a cut ({a['wall'] / b['wall']:.2f}x), simulation {a['sim']:.3f} -> "
                  f"{b['sim']:.3f} s ({a['sim'] / max(b['sim'], 1e-9):.2f}x)")
        return out
    if args.size_solver == "both":
        m = modes[-1]
        out = {solver: demo_cuts(args, m, push_last=args.push_last == "true", size_solver=solver,
                                 executed=EXECUTED[args.executed][0]) for solver in ("host", "device")}
        a, b = out["host"], out["device"]
        print(f"fragment sizes on the device against the host, same process: wall {a['wall']:.3f} -> {b['wall']:.3f} "
              f"s a cut ({a['wall'] / b['wall']:.2f}x), reward {a['reward']:.3f} -> {b['reward']:.3f} s "
              f"({a['reward'] / max(b['reward'], 1e-9):.2f}x)")
        return out
    out = {("batched" if m else "per-scene"): demo_cuts(args, m, push_last=args.push_last == "true",
                                                        size_solver=args.size_solver, executed=executed[0])
           for m in modes}
    if len(out) == 2:
        a, b = out["per-scene"], out["batched"]
        print(f"batched discovery against per scene, same process: wall {a['wall']:.3f} -> {b['wall']:.3f} s a cut "
              f"({a['wall'] / b['wall']:.2f}x), discovery {a['discovery']:.3f} -> {b['discovery']:.3f} s "
              f"({a['discovery'] / max(b['discovery'], 1e-9):.2f}x)")
    return out


def before_and_now(args, batched: bool, reference, what: str, part: str) -> dict:
    """The demonstration cut twice in one process: under ``reference`` (a context manager putting back the code as it
    was: the reference, first), then as it is; prints the ratios of the wall and of ``part`` (a column of the table)."""
    out = {}
    for how, context in (("before", reference), ("current", contextlib.nullcontext())):
        with context:
            out[how] = demo_cuts(args, batched, push_last=args.push_last == "true", size_solver=args.size_solver,
                                 executed=EXECUTED[args.executed][-1])
    a, b = out["before"], out["current"]
    print(f"{what} against the code they replace, same process: wall {a['wall']:.3f} -> {b['wall']:.3f} s a cut "
          f"({a['wall'] / b['wall']:.2f}x), {part} {a[part]:.3f} -> {b[part]:.3f} s ({a[part] / max(b[part], 1e-9):.2f}x)")
    return out


@contextlib.contextmanager
def gpu_profile(args):
    """--gpu-profile: every CUDA kernel and copy of the measured episode (torch.profiler's CUPTI trace: Taichi's and
    Warp's kernels too), the GPU time by kernel name, the largest first, into the file named and its head printed."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        yield
    table = prof.key_averages().table(sort_by="self_cuda_time_total", row_limit=60, max_name_column_width=70)
    with open(args.gpu_profile, "w") as f:
        f.write(table)
    print(f"GPU time of the measured episode by kernel ({args.gpu_profile}):")
    print("\n".join(table.splitlines()[:45]))


@contextlib.contextmanager
def host_functions(how: str):
    """--host before: the host functions of every demonstration cut as they were before 2026-12-01 (the reference):
    piece_agreement by np.unique over stacked (label, piece) rows, the blade's centring band over every particle,
    fragments' ids by a second sort.  current: as they are."""
    if how == "current":
        yield
        return
    import topocut.episode.engine as engine
    import topocut.episode.scoring as scoring
    import topocut.sim.pieces as pieces

    def agreement(labels, piece, min_points: int = 4):
        labels, piece = np.asarray(labels, np.int64), np.asarray(piece, np.int64)
        n_sim = int((np.bincount(piece) >= min_points).sum()) if len(piece) else 0
        ok = labels >= 0
        if not ok.any():
            return n_sim, float("nan")
        pairs, inter = np.unique(np.stack([labels[ok], piece[ok]]), axis=1, return_counts=True)
        size_l, size_p, worst = np.bincount(labels[ok]), np.bincount(piece), 1.0
        for lab in np.unique(pairs[0]):
            if size_l[lab] >= min_points:
                m = pairs[0] == lab
                j = np.argmax(inter[m])
                worst = min(worst, float(inter[m][j] / (size_l[lab] + size_p[pairs[1][m][j]] - inter[m][j])))
        return n_sim, worst

    def band(x, p0, nrm, width):  # the full (N,3) difference, rows by fancy indexing
        x = np.asarray(x, np.float64)
        return x[np.flatnonzero(np.abs((x - p0) @ nrm) <= width)]

    def fragments(x, labels, min_points):
        x, labels = np.asarray(x), np.asarray(labels).reshape(-1)
        key = labels.astype(np.int16) if len(labels) and -2 ** 15 <= labels.min() and labels.max() < 2 ** 15 else labels
        order = np.argsort(key, kind="stable")
        ids, start = np.unique(labels[order], return_index=True)
        return [f for c, f in zip(ids, np.split(x[order], start[1:])) if c >= 0 and len(f) >= min_points]

    saved = engine.piece_agreement, pieces._in_band, scoring.fragments
    engine.piece_agreement, pieces._in_band, scoring.fragments = agreement, band, fragments
    try:
        yield
    finally:
        engine.piece_agreement, pieces._in_band, scoring.fragments = saved


# --executed: how the demonstration's executed cut is made, and the runs each choice makes (the first the reference)
HOW = {"rollout": "restored from its best rollout", "scene0": "cut again in scene 0",
       "every": "cut again in every scene"}
EXECUTED = {"rollout": ("rollout",), "scene0": ("scene0",), "every": ("every",), "both": ("every", "scene0"),
            "all": ("every", "scene0", "rollout"), "again": ("scene0", "rollout")}


def every_scene(env) -> None:
    """The engine's executed cut, push and turn as before 2026-11-30 (the reference of ``--executed both``): one
    episode alone (MPPI's) moved in every scene of the batch, not in scene 0 with the others idle."""
    cut, push, turn = env.cut, env.push, env.turn

    def every(acts):
        return [acts[0]] * len(acts) if isinstance(acts, list) and all(a is None for a in acts[1:]) else acts

    env.cut = lambda acts, **k: cut(every(acts), **k)
    env.push = lambda scenes=None: push(None if scenes is not None and not np.asarray(scenes)[1:].any() else scenes)
    env.turn = lambda t, **k: turn(t[0] if isinstance(t, list) and all(u is None for u in t[1:]) else t, **k)


def demo_cuts(args, batch_scenes: bool, push_last: bool = False, size_solver: str = "auto",
              executed: str = "rollout") -> dict:
    from topocut.planning import MPPIConfig, MPPIPolicy, run_episode, sim_rollout_factory
    from topocut.reward.config import RewardConfig
    from topocut.sim.env import CuttingEnv
    from topocut.sim.objects import ObjectPose
    from topocut.tasks import get_task, task_config
    from topocut.topology.config import TopologyConfig

    env = CuttingEnv(sim_config(args, args.K), batch_size=args.K)
    instrument(env)
    if executed == "every":
        every_scene(env)
    # no push unless --push: as docs/benchmarks.md timed; --push: the task's own (stick and dice push)
    task = task_config(args.task, max_cuts=args.cuts, **({} if args.push else {"push": False})).validate()
    rcfg = RewardConfig(backend=args.reward_backend, device=args.device if args.reward_backend == "torch" else "cpu",
                        size_solver=size_solver)
    topo = TopologyConfig(resolution=args.topo_resolution, batch_scenes=batch_scenes)
    pose = ObjectPose()
    goal = get_task(task.name).make_goal(task, args.object, pose, env.cfg.spacing, board_z=env.cfg.board_z)
    planner = MPPIConfig(num_samples=args.K, iterations=args.iters, horizon=1, reuse_rollout_cut=executed == "rollout")
    factory = sim_rollout_factory(env, rcfg, topo, board_z=env.cfg.board_z, push=task.push, push_last=push_last)
    rows = []
    for rep in range(2):  # the first episode compiles kernels and fills caches: the second is measured
        env.reset(args.object, pose, seed=0)
        TIMES.clear()
        cuts = []

        def progress(n, info="", cuts=cuts):
            cuts.append((time.perf_counter(), dict(TIMES)))

        prof = cProfile.Profile() if args.profile and rep == 1 else None
        kernels = gpu_profile(args) if args.gpu_profile and rep == 1 else contextlib.nullcontext()
        t0 = time.perf_counter()
        kernels.__enter__()
        if prof is not None:
            prof.enable()
        _, summary = run_episode(env, goal, MPPIPolicy(planner, factory, seed=0), rcfg, topo, task.max_cuts,
                                 task.push, progress=progress, seed=0, success_fn=lambda r: False)
        if summary.get("error"):  # a failed episode times nothing: say why
            print(f"the episode ended {summary['status']}: {summary['error']}")
        kernels.__exit__(None, None, None)
        if prof is not None:
            prof.disable()
            prof.dump_stats(args.profile)
            print(f"profile of the measured episode ({args.profile}), by cumulative time:")
            pstats.Stats(prof).sort_stats("cumulative").print_stats(r"topocut|numpy|scipy|torch|taichi|warp", 60)
        if rep == 0:
            continue
        prev_t, prev = t0, {}
        for t, snap in cuts:
            d = {k: snap.get(k, 0.0) - prev.get(k, 0.0) for k in ("sim", "sim_split", "discovery", "reward")}
            rows.append({"wall": t - prev_t, **d})
            prev_t, prev = t, snap
    print(f"demonstration cut ({args.device}, {args.n_grid}^3, {args.object}/{args.task}, K={args.K}, "
          f"{args.iters} iterations, reward {args.reward_backend} (sizes: {size_solver}), discovery "
          f"{args.topo_resolution}^3, "
          f"{'batched over scenes' if batch_scenes else 'scene by scene'}, "
          f"{'push' + (', rollouts push after their last cut' if push_last else '') if task.push else 'no push'}, "
          f"the executed cut: {HOW[executed]}):")
    print(f"{'cut':>4} {'wall s':>8} {'sim s':>8} {'(split)':>8} {'disc s':>8} {'reward s':>8} {'rest s':>8} "
          f"{'wall/sim':>9}")
    for i, r in enumerate(rows):
        rest = r["wall"] - r["sim"] - r["discovery"] - r["reward"]
        print(f"{i + 1:>4} {r['wall']:8.3f} {r['sim']:8.3f} {r['sim_split']:8.3f} {r['discovery']:8.3f} "
              f"{r['reward']:8.3f} {rest:8.3f} {r['wall'] / max(r['sim'], 1e-9):9.2f}")
    wall = float(np.mean([r["wall"] for r in rows]))
    sim = float(np.mean([r["sim"] for r in rows]))
    disc = float(np.mean([r["discovery"] for r in rows]))
    print(f"mean: {wall:.3f} s per cut, of which simulation {sim:.3f} s: wall/sim = {wall / sim:.2f}; "
          f"1,000 episodes x 5 cuts projected: {1000 * 5 * wall / 60:.1f} min")
    reward = float(np.mean([r["reward"] for r in rows]))
    return {"wall": wall, "sim": sim, "discovery": disc, "reward": reward, "rest": wall - sim - disc - reward}


def bench_eval(args) -> dict:
    from topocut.episode import make_scoring, run_episodes
    from topocut.eval.config import EvalConfig
    from topocut.eval.protocol import _episode, episode_specs
    from topocut.planning import GoalPlanesPolicy
    from topocut.planning.heuristic import HeuristicPolicy
    from topocut.reward.config import RewardConfig
    from topocut.sim.env import CuttingEnv
    from topocut.tasks import task_config
    from topocut.topology.config import TopologyConfig

    ecfg = EvalConfig()
    specs = episode_specs(ecfg)
    stride = max(1, len(specs) // args.eval_episodes)
    chosen = specs[::stride][: args.eval_episodes]
    # no push, as docs/benchmarks.md timed (the protocol's stick and dice push: topocut.eval.runner.task_configs)
    task_cfgs = {t: task_config(t, max_cuts=ecfg.max_cuts, push=False).validate() for t in ecfg.tasks}
    rcfg = RewardConfig(backend=args.reward_backend, device=args.device if args.reward_backend == "torch" else "cpu")
    topo = TopologyConfig(resolution=args.topo_resolution)
    out = {}
    for B, eps in ((args.batch, chosen), (1, chosen[: args.ref_episodes])):
        env = CuttingEnv(sim_config(args, B), batch_size=B)
        sc = make_scoring(rcfg, topo, min_fragment_points=ecfg.min_fragment_points, env=env)
        policies = {"oracle": GoalPlanesPolicy(),
                    "heuristic": HeuristicPolicy(task_cfgs, spacing=env.cfg.spacing, board_z=env.cfg.board_z)}
        for name, pol in policies.items():
            run_episodes(env, [_episode(s, task_cfgs[s.task]) for s in eps[:min(B, 2)]], pol, sc,
                         max_cuts=ecfg.max_cuts)  # warm-up: kernels, caches
            t0 = time.perf_counter()
            logs = run_episodes(env, [_episode(s, task_cfgs[s.task]) for s in eps], pol, sc, max_cuts=ecfg.max_cuts)
            dt = (time.perf_counter() - t0) / len(eps)
            out[name, B] = dt
            cuts = sum(len(lg.actions) for lg in logs)
            print(f"eval {name:>9} B={B:<3} {len(eps):>3} episodes, {cuts:>4} cuts: {dt:7.3f} s/episode "
                  f"(405 episodes: {405 * dt / 60:6.1f} min); statuses "
                  f"{dict(zip(*np.unique([lg.status for lg in logs], return_counts=True)))}")
    for name in ("oracle", "heuristic"):
        print(f"eval {name}: batched B={args.batch} vs one at a time: {out[name, 1] / out[name, args.batch]:.2f}x "
              f"faster per episode")
    return out


def bench_policy(args) -> None:
    import torch

    from topocut.policies.base import make_obs
    from topocut.policies.config import PolicyTrainConfig
    from topocut.policies.module import PDDPModule, PDDPPolicy

    tc = PolicyTrainConfig()
    module = PDDPModule(train=tc)  # untrained: the time of an action does not depend on the weights
    rng = np.random.default_rng(0)
    obs = []
    for _ in range(args.batch):
        pts = rng.uniform(0.4, 0.6, (2048, 3)).astype(np.float32)
        goal = rng.uniform(0.4, 0.6, (tc.num_goal_points, 3)).astype(np.float32)
        obs.append(make_obs(pts, np.zeros(2048, np.int32), goal, (goal[:, 0] > 0.5).astype(np.int32)))
    pols = []
    for b in range(args.batch):
        p = PDDPPolicy(module, device=args.device, seed=0)
        p.reset(type("Goal", (), {"points": obs[b]["goal"], "labels": obs[b]["goal_labels"]})(), seed=b)
        pols.append(p)
    sync = torch.cuda.synchronize if args.device == "cuda" else (lambda: None)
    pols[0].act(obs[0])
    sync()
    t0 = time.perf_counter()
    for p, o in zip(pols, obs):
        p.act(o)
    sync()
    one = (time.perf_counter() - t0) / len(obs)
    line = f"PDDP act ({args.device}, T={pols[0].scfg.steps}): {one * 1e3:.1f} ms per episode one at a time"
    if hasattr(PDDPPolicy, "act_batch"):
        PDDPPolicy.act_batch(pols, obs)
        sync()
        t0 = time.perf_counter()
        PDDPPolicy.act_batch(pols, obs)
        sync()
        bat = (time.perf_counter() - t0) / len(obs)
        line += f"; act_batch of {len(obs)}: {bat * 1e3:.1f} ms per episode ({one / bat:.2f}x)"
        one = bat
    print(line + f"; 405 episodes x 5 cuts: {405 * 5 * one / 60:.1f} min of acting")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    p.add_argument("--n-grid", type=int, default=64)
    p.add_argument("--K", type=int, default=16, help="MPPI samples = the demonstration's scenes")
    p.add_argument("--iters", type=int, default=2)
    p.add_argument("--cuts", type=int, default=3, help="cuts of the measured demonstration episode")
    p.add_argument("--object", default="cake")
    p.add_argument("--task", default="slice")
    p.add_argument("--reward-backend", choices=("scipy", "torch"), default="torch")
    p.add_argument("--topo-resolution", type=int, default=64)
    p.add_argument("--discovery", choices=("both", "batched", "per-scene"), default="both",
                   help="the rollouts' discovery: one call for all scenes of a cut, one per scene, or both")
    p.add_argument("--push", action="store_true", help="demo: the task's own push (stick, dice) instead of none")
    p.add_argument("--push-last", choices=("false", "true", "both"), default="false",
                   help="demo with --push: planner.push_last; both: with it (the reference), then without")
    p.add_argument("--size-solver", choices=("auto", "host", "device", "both"), default="auto",
                   help="demo: reward.size_solver; both: the host (the reference), then the device")
    p.add_argument("--executed", choices=tuple(EXECUTED), default="rollout",
                   help="demo: the executed cut restored from its best rollout (rollout: the engine's way), cut again "
                   "in scene 0 with the other scenes idle (scene0: the way before), or in every scene (every: the way "
                   "before that); both: every, then scene0; again: scene0, then rollout; all: the three (the first "
                   "the reference)")
    p.add_argument("--gpu-profile", default="", help="demo: the measured episode's GPU time by kernel (torch.profiler) "
                   "into this file")
    p.add_argument("--reward-kernels", choices=("current", "both"), default="current",
                   help="demo: both: the reward's FPS and neighbour queries as before 2026-12-01 (a captured CUDA graph, "
                   "tensor blocks: the reference), then as they are (Warp kernels)")
    p.add_argument("--host", choices=("current", "both"), default="current",
                   help="demo: both: the host functions of a cut as before 2026-12-01 (the reference), then as they are")
    p.add_argument("--batch", type=int, default=16, help="evaluation scenes (episodes at once)")
    p.add_argument("--eval-episodes", type=int, default=32)
    p.add_argument("--ref-episodes", type=int, default=4, help="episodes of the one-at-a-time reference")
    p.add_argument("--only", choices=("demo", "eval", "policy"), nargs="*", default=None)
    p.add_argument("--profile", default="", help="demo: cProfile the measured episode into this file and print the "
                   "60 entries of most cumulative time (on CUDA a host sync books the queued work's wait)")
    args = p.parse_args()
    from topocut.sim.runtime import init_taichi

    init_taichi(args.device)
    parts = args.only or ("demo", "eval", "policy")
    if "demo" in parts:
        bench_demo(args)
    if "eval" in parts:
        bench_eval(args)
    if "policy" in parts:
        bench_policy(args)


if __name__ == "__main__":
    main()

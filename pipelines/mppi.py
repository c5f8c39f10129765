"""stage=mppi: MPPI demonstrations guided by the spectral reward -> a versioned zarr dataset.

One run writes ``data.episodes`` episodes of one task and object, episode indices e = ``data.first_episode`` ..
``data.first_episode + data.episodes - 1`` with seeds ``demo_episode_seed(seed, e)`` (topocut.episode.seeds): runs over consecutive ranges
(stage=all's parts of a cell, ``data.episodes_per_job``) together write exactly the episodes of one run over their
union.  In a Hydra multirun (or with ``data.shard=true``, as stage=all's cells) each job writes its own shard
``dataset/<data.dataset>-<task>-<object>-s<seed>-<config key>`` marked ``shard_of: <data.dataset>`` in its
manifest (the key keeps jobs of a sweep over any other setting apart); ``stage=merge`` joins them.
Episodes are committed one by one: a killed run resumes where it stopped, and each episode draws its MPPI
samples from its own seed, so a resumed run writes what an uninterrupted one would.  The simulator is kept per
process (``topocut.sim.env.cached_env``): a stage=all worker running part after part builds it once.
"""
from __future__ import annotations

import dataclasses
import functools
import json
import logging
import time

import numpy as np

from pipelines._common import as_dict, begin_sim, object_pose
from topocut.data.collection import read_records
from topocut.data.store import config_key
from topocut.episode import demo_episode_seed
from topocut.utils.context import RunContext
from topocut.utils.errors import NothingUsable
from topocut.utils.progress import progress_bar

log = logging.getLogger("topocut")


def _is_multirun() -> bool:
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN
    except Exception:  # noqa: BLE001 - outside Hydra
        return False


SAMPLED_TILT_MAX = 1.2  # rad: |tilt| bound when a task samples tilt (as experiments/pyramid_mppi.py's pyramid MPPI)


def planner_for_task(planner, task):
    """The MPPI config a task runs with: a task whose goal plane is tilted (task.sample_tilt, the pyramid's
    35 deg) samples tilt, and |tilt| may reach SAMPLED_TILT_MAX; clipping at the default planner.tilt_max
    (0.6 rad) would move even the initial guess off the goal plane."""
    if not task.sample_tilt:
        return planner
    dims = list(planner.sampled_dims) + ([] if "tilt" in planner.sampled_dims else ["tilt"])
    return dataclasses.replace(planner, sampled_dims=dims, tilt_max=max(planner.tilt_max, SAMPLED_TILT_MAX))


def episode_scene(object, task, sim, seed: int, planner=None):
    """(pose, goal) of one episode: the task's goal on the simulator's board (sim.board_z), as env.reset places
    the object; with ``planner``, a goal plane tilted beyond planner.tilt_max raises instead of being clipped."""
    from topocut.tasks import get_task

    pose = object_pose(object, seed)
    goal = get_task(task.name).make_goal(task, object.name, pose, spacing=sim.spacing, board_z=sim.board_z, seed=seed)
    need = max((abs(p.tilt) for p in goal.planes), default=0.0)
    if planner is not None and need > planner.tilt_max:
        raise ValueError(f"task={task.name}: the goal's planes tilt up to {need:.4f} rad, beyond "
                         f"planner.tilt_max={planner.tilt_max}; raise planner.tilt_max")
    return pose, goal


def run(ctx: RunContext, sim, object, task, topology, reward, planner, data, compare_heuristic: int | bool = 1) -> dict:
    """The task says what runs (``tool``); a task without an mppi stage (scooping) is refused, naming it.

    ``compare_heuristic`` (conf/stage/mppi.yaml: data.heuristic_every): the heuristic also runs the episodes whose
    index is a multiple of it, for docs/data.md's comparison (true / 1: every episode; false / 0: none)."""
    from topocut.config import ConfigError, task_for_stage

    tool = task_for_stage(task, "mppi").tool
    if data.first_episode < 0:
        raise ConfigError(f"data.first_episode: {data.first_episode} is not valid; must be >= 0")
    if int(compare_heuristic) < 0:
        raise ConfigError(f"data.heuristic_every: {compare_heuristic} is not valid; must be >= 0 (0: never)")
    if tool == "pen":  # MPPI over the strokes of the pen's tasks
        return run_writing(ctx, sim, task, topology, reward, planner, bool(compare_heuristic))
    return run_knife(ctx, sim, object, task, topology, reward, planner, data, int(compare_heuristic))


def run_knife(ctx: RunContext, sim, object, task, topology, reward, planner, data, compare_heuristic: int) -> dict:
    """MPPI demonstrations of a knife task: the planner plans the cuts, the goal's turns run between them."""
    planner = planner_for_task(planner, task)  # pyramid: the goal plane is tilted
    from topocut.data.episodes import EpisodeWriter
    from topocut.planning import MPPIPolicy, sim_rollout_factory
    from topocut.sim import init_taichi
    from topocut.sim.env import cached_env
    from topocut.tasks import get_task

    success = functools.partial(get_task(task.name).success, cfg=task)  # RewardResult -> the task's success

    config = as_dict(("sim", sim), ("object", object), ("task", task), ("topology", topology),
                     ("reward", reward), ("planner", planner), ("episodes", data.episodes),
                     ("points_per_step", data.points_per_step), ("seed", ctx.seed))
    first = data.first_episode
    if first:  # keyed only when nonzero: the artifacts of runs from episode 0 keep the keys they had
        config["first_episode"] = first
    name, extra = data.dataset, {"seed": ctx.seed, "device": ctx.device}
    if data.shard or _is_multirun():
        name = f"{data.dataset}-{task.name}-{object.name}-s{ctx.seed}-{config_key(config)[:8]}"
        extra["shard_of"] = data.dataset
    writer, existing = ctx.store.begin("dataset", name, config, extra=extra)
    if existing is not None:
        return {"dataset": str(existing), "reused": True}
    sim = dataclasses.replace(sim, arch=ctx.device)  # one backend for Taichi, Warp and torch
    reward = reward.on(ctx.device)  # reward=torch: its eigensolver and FPS on the run's device
    init_taichi(arch=ctx.device, seed=ctx.seed)
    zpath = writer.path / "data.zarr"
    ew = EpisodeWriter(zpath, points_per_step=data.points_per_step, board_z=sim.board_z)
    done = ew.committed_keys()
    env = cached_env(sim, max(1, sim.batch_size))  # a worker's later parts reuse its simulator
    factory = sim_rollout_factory(env, reward, topology, board_z=sim.board_z, push=task.push,
                                  push_last=planner.push_last, success=success)
    log_path = writer.path / "episodes.jsonl"
    read_records(log_path, repair=True)  # a run killed while logging left a torn last line: drop it
    one = functools.partial(_demo_episode, env=env, expert=MPPIPolicy(planner, factory, seed=ctx.seed), ew=ew,
                            log_path=log_path, sim=sim, object=object, task=task, topology=topology, reward=reward,
                            planner=planner, success=success, compare_heuristic=compare_heuristic)
    label = f"mppi {task.name}/{object.name}" + (f" e{first}-{first + data.episodes - 1}" if first else "")
    with progress_bar(label, data.episodes * task.max_cuts, ctx.progress) as advance:
        for e in range(first, first + data.episodes):
            seed = demo_episode_seed(ctx.seed, e)
            if ew.episode_key({"task": task.name, "object": object.name, "seed": seed}) in done:
                advance(task.max_cuts, info=f"episode {e} already committed")
                continue
            one(e, seed, advance)
    return _commit_dataset(ctx, writer, zpath, log_path, name, data)


def _demo_episode(e: int, seed: int, advance, *, env, expert, ew, log_path, sim, object, task, topology, reward,
                  planner, success, compare_heuristic: int) -> None:
    """Demonstration episode e (seed ``seed``): its line in the episode log, then its commit to the dataset."""
    from topocut.episode import run_episode
    from topocut.planning.oracle import OraclePolicy

    pose, goal = episode_scene(object, task, sim, seed, planner)
    record = {"episode": e, "seed": seed, "started": time.time()}  # wall clock: start-up = first - launch
    # the same episode under the heuristic, for docs/data.md's comparison: every n-th episode by its index,
    # so that the parts of a cell compare the episodes one run over the cell would
    if compare_heuristic and e % compare_heuristic == 0:
        env.reset(object.name, pose, seed=seed)
        _, hs = run_episode(env, goal, OraclePolicy(goal, sim.board_z), reward, topology, task.max_cuts, task.push,
                            success_threshold=task.success_threshold, success_fn=success)
        record["heuristic_final_reward"] = hs["final_reward"]
        record["heuristic_time_s"] = hs["time_s"]
    env.reset(object.name, pose, seed=seed)
    steps, summary = run_episode(env, goal, expert, reward, topology, task.max_cuts, task.push,
                                 progress=advance, success_threshold=task.success_threshold, seed=seed,
                                 success_fn=success)
    meta = {"task": task.name, "object": object.name, "seed": seed, "pose": pose,
            "task_params": task, "material": {k: getattr(sim, k) for k in ("mu", "lam", "rho_core", "rho_skin",
                                                                            "eps_c", "eps_s", "m") if hasattr(sim, k)},
            "goal": goal.points, "goal_labels": goal.labels, "status": summary["status"],
            "final_reward": summary["final_reward"], "success": summary["success"]}
    record.update({k: summary[k] for k in ("status", "num_cuts", "final_reward", "success", "rewards",
                                           "turns", "time_s")})
    record["mppi_iterations"] = list(getattr(expert, "iterations_done", []))  # per cut (planner.stop_at_success)
    if summary["status"] != "ok":  # why it failed, in the episode log and the dataset's episode entry
        meta["error"] = record["error"] = summary.get("error", "unknown")
        log.warning("mppi episode %d (seed %d) failed after %d cuts: %s", e, seed, summary["num_cuts"],
                    record["error"])
    with open(log_path, "a") as f:  # before the episode's commit: a crash between the two re-runs it,
        f.write(json.dumps(record, default=float) + "\n")  # and its second record replaces the first
    ew.add_episode(steps, meta)
    advance(task.max_cuts - summary["num_cuts"],
            info=f"episode {e}: " + (f"reward {summary['final_reward']:.3f}" if summary["status"] == "ok"
                                     else f"failed ({record['error']})"))


def _commit_dataset(ctx: RunContext, writer, zpath, log_path, name: str, data) -> dict:
    """The run's dataset committed with its summary, unless nothing in it is usable (NothingUsable)."""
    from topocut.data.episodes import EpisodeDataset

    first = data.first_episode
    ds = EpisodeDataset(zpath)
    if ds.num_episodes != data.episodes:  # this run's episodes only, whatever its first_episode
        raise RuntimeError(f"{zpath} holds {ds.num_episodes} episodes, expected data.episodes={data.episodes}")
    records = read_records(log_path)
    failures = [{"episode": r["episode"], "seed": r.get("seed"), "error": r.get("error", "unknown")}
                for r in records if r.get("status") != "ok"]
    if len(failures) == len(records) or len(ds) == 0:
        # nothing to learn from: committing would make an empty or all-failed dataset `latest` for pretrain/bc.
        # The partial directory stays, so the same command re-reports without re-simulating.
        what = f"all {len(records)} episodes failed" if failures else "its episodes recorded no steps"
        reasons = "".join(f"; episode {f['episode']}: {f['error']}" for f in failures)
        raise NothingUsable(f"stage=mppi: {what}, nothing committed to dataset/{name} (log: {log_path}){reasons}",
                            failures)
    finals = [r["final_reward"] for r in records if r.get("status") == "ok"]
    heur = [r["heuristic_final_reward"] for r in records if "heuristic_final_reward" in r]
    summary = {"episodes": ds.num_episodes, "cuts": len(ds),
               "success_rate": float(np.mean([r["success"] for r in records])) if records else 0.0,
               "mean_final_reward": float(np.mean(finals)) if finals else float("nan"),
               "failed_episodes": len(failures)}
    if first:
        summary["first_episode"] = first
    if failures:
        summary["failures"] = failures
    if heur:
        summary["heuristic_mean_final_reward"] = float(np.mean(heur))
    _plot_rewards(records, writer.path / "rewards.png")
    path = writer.commit(summary)
    ctx.logger.log({f"mppi/{k}": v for k, v in summary.items() if isinstance(v, (int, float))})
    ctx.logger.log_image("mppi/rewards", path / "rewards.png")
    return {"dataset": str(path), **summary}


def run_writing(ctx: RunContext, sim, task, topology, reward, planner, compare_scripted: bool = True) -> dict:
    """task=cream_writing: MPPI over each letter's stroke (K = planner.num_samples scenes), scored by its
    spectral reward; writes ``sim/cream_writing-<word>-mppi`` (states, per-letter rewards, frames)."""
    from topocut.planning.stroke_mppi import StrokeMPPI, StrokeMPPIConfig
    from topocut.sim.pen import CreamPen
    from topocut.sim.render import write_gif
    from topocut.tasks.writing_scene import cluster_check, write_scripted, writing_scene

    mcfg = StrokeMPPIConfig(num_samples=planner.num_samples, iterations=planner.iterations,
                            temperature=planner.temperature)
    config = as_dict(("sim", sim), ("task", task), ("topology", topology), ("reward", reward), ("planner", mcfg),
                     ("compare_scripted", compare_scripted), ("seed", ctx.seed))
    writer, reused, sim = begin_sim(ctx, f"{task.name}-{task.word}-mppi", config, sim)
    if reused is not None:
        return reused
    goals, strokes, start, draw = writing_scene(sim, task)
    out = {"word": task.word}
    if compare_scripted:
        out["scripted"] = write_scripted(CreamPen(sim, task.pen, 1, start=start), strokes, goals, reward)
    pen = CreamPen(sim, task.pen, mcfg.num_samples, start=start)
    frames = []

    def on_letter(i, state):
        frames.append(draw(state["x"], state["stroke"], writer.path / "frames" / f"letter{i + 1}.png",
                           f"MPPI stroke {i + 1}: {task.word[i]}"))
        advance(1, info=f"letter {task.word[i]}")

    with progress_bar(f"mppi {task.name}/{task.word}", len(strokes), ctx.progress) as advance:
        res = StrokeMPPI(pen, goals, mcfg, reward, seed=ctx.seed).write(strokes, on_letter=on_letter)
    x, stroke = pen.particles()
    check = cluster_check(x[0], stroke, topology, device=ctx.device)
    frames.append(draw(x[0], stroke, writer.path / "frames" / "final.png",
                       f"MPPI {task.word}: {check['clusters']} clusters, reward {res['total']:.3f}"))
    np.savez_compressed(writer.path / "states.npz", x=x[0], stroke=stroke, labels=check.pop("labels"),
                        **{f"polyline_{i}": p for i, p in enumerate(res.pop("polylines"))})
    out["mppi"] = {**res, **check}
    (writer.path / "writing.json").write_text(json.dumps(out, indent=2, default=float))
    write_gif(frames, writer.path / "writing.gif", fps=1)
    summary = {"letters": len(strokes), "rollouts": res["rollouts"], "reward": res["total"],
               "clusters": check["clusters"], "clusters_match_strokes": check["agree"],
               **{f"reward_{c}{i}": r for i, (c, r) in enumerate(zip(task.word, res["per_letter"]))},
               "mppi_s": round(res["seconds"], 2)}
    if compare_scripted:
        summary["scripted_reward"] = out["scripted"]["total"]
    path = writer.commit(summary)
    ctx.logger.log({f"mppi/{k}": v for k, v in summary.items() if isinstance(v, (int, float))})
    ctx.logger.log_image("mppi/writing", path / "frames" / "final.png")
    return {"artifact": str(path), **summary}


def _plot_rewards(records: list[dict], path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.2))
    for r in records:
        ax.plot(range(1, len(r.get("rewards", [])) + 1), r.get("rewards", []), marker="o", label=f"ep {r['episode']}")
        if "heuristic_final_reward" in r:
            ax.axhline(r["heuristic_final_reward"], ls=":", lw=1, color="gray")
    ax.set_xlabel("cut")
    ax.set_ylabel("spectral reward")
    ax.set_title("MPPI episodes (dotted: heuristic final reward)")
    if records:
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)

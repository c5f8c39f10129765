"""stage=teleop: drive the knife from a Taichi window, or replay a saved log into a dataset.

Live: ``python -m topocut.run stage=teleop object=cake`` opens a window (mouse moves the knife plane,
wheel turns it, shift+wheel tilts; c cut, p push, u undo, s save, esc quit); the session's action log is
saved next to the run. Replay (headless): ``stage.run.replay=<log.json>`` re-executes the log in the
simulator and writes the same dataset records as MPPI (labels and rewards recomputed).
"""
from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

from pipelines._common import as_dict, object_pose
from topocut.utils.context import RunContext


def check_task(log: dict, task: str, log_path) -> None:
    """A log replays only under the task it was recorded for (its goal and push settings come from it)."""
    if log.get("task", task) != task:
        raise ValueError(f"{log_path}: the log was recorded for task {log['task']!r}, this run has task={task!r}; "
                         f"replay it with task={log['task']}")


def record_session(session, path, backend: str = "auto") -> Path:
    """Run the live window; the action log is saved to ``path`` (atomically: temp file + rename) however the
    session ends, so that an error or Ctrl-C in the window loses none of the recorded actions."""
    from topocut.planning.teleop import run_window

    try:
        run_window(session, backend=backend)
    finally:
        saved = session.save(path)
    return saved


def run(ctx: RunContext, sim, object, task, topology, reward, data, replay: str | None = None,
        backend: str = "auto") -> dict:
    from topocut.config import task_for_stage
    from topocut.data.episodes import EpisodeDataset, EpisodeWriter
    from topocut.planning.teleop import TeleopSession, load_log
    from topocut.planning.teleop import replay as replay_log
    from topocut.sim import CuttingEnv, init_taichi
    from topocut.sim.objects import ObjectPose

    make_goal = task_for_stage(task, "teleop").make_goal  # the task's goal (a stage it lacks is refused)
    log_path = None
    if replay is not None:  # checked before the simulator starts
        log_path = Path(replay)
        if not log_path.exists():
            raise FileNotFoundError(f"stage.run.replay: teleop log {log_path} does not exist")
        check_task(load_log(log_path), task.name, log_path)
    sim = dataclasses.replace(sim, arch=ctx.device)  # one backend for Taichi, Warp and torch
    init_taichi(arch=ctx.device, seed=ctx.seed)
    env = CuttingEnv(sim, batch_size=1)
    if replay is None:
        pose = object_pose(object, ctx.seed)
        goal = make_goal(task, object.name, pose, spacing=sim.spacing, board_z=sim.board_z, seed=ctx.seed)
        session = TeleopSession(env, goal, object.name, pose, ctx.seed, task.name, reward, topology,
                                task.success_threshold)
        log_path = record_session(session, ctx.run_dir / "teleop_log.json", backend)
    log = load_log(log_path)
    if not any(entry.get("type") == "cut" for entry in log["actions"]):  # nothing to learn from or compare against
        from topocut.config import ConfigError

        raise ConfigError(f"teleop log {log_path} holds no cut: nothing to replay, nothing committed; record cuts "
                          f"in a window (stage=teleop) or replay one that has them "
                          f"(stage.run.replay=examples/teleop_slice_cake.json)")
    pose = ObjectPose(**log["pose"]) if isinstance(log.get("pose"), dict) else ObjectPose()
    goal = make_goal(task, log["object"], pose, spacing=sim.spacing, board_z=sim.board_z, seed=int(log["seed"]))
    config = as_dict(("sim", sim), ("task", task), ("topology", topology), ("reward", reward), ("log", log),
                     ("points_per_step", data.points_per_step))
    writer, existing = ctx.store.begin("dataset", f"teleop-{task.name}-{log['object']}", config)
    if existing is not None:
        return {"dataset": str(existing), "reused": True}
    steps, summary = replay_log(log, env, goal, reward, topology, task.success_threshold)
    ew = EpisodeWriter(writer.path / "data.zarr", points_per_step=data.points_per_step, board_z=sim.board_z)
    if ew.num_episodes == 0:
        ew.add_episode(steps, {"task": task.name, "object": log["object"], "seed": log["seed"], "pose": pose,
                               "source": "teleop", "goal": goal.points, "goal_labels": goal.labels,
                               "status": summary.get("status", "ok")})
    shutil.copyfile(log_path, writer.path / "teleop_log.json")
    ds = EpisodeDataset(writer.path / "data.zarr")
    path = writer.commit({"episodes": ds.num_episodes, "cuts": len(ds)})
    return {"dataset": str(path), "cuts": len(ds), "final_reward": summary.get("final_reward")}

"""stage=simulate: a scripted cut sequence (the goal's ideal planes) on one object.

Stores per-cut particle states (positions, damage, cluster labels, knife sweeps)
as a versioned ``sim`` artifact and renders PNG frames coloured by cluster id and a GIF.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipelines._common import as_dict, begin_sim, object_pose
from topocut.utils.context import RunContext
from topocut.utils.progress import progress_bar


def run(ctx: RunContext, sim, object, task, topology, frames_per_cut: int = 6) -> dict:
    if task.name == "cream_writing":
        return run_writing(ctx, sim, task, topology)
    if task.name == "scooping":
        return run_scooping(ctx, sim, task, topology)
    from topocut.goals import make_goal
    from topocut.sim import CuttingEnv
    from topocut.sim.render import render_particles, write_gif
    from topocut.topology import discover

    config = as_dict(("sim", sim), ("object", object), ("task", task), ("topology", topology), ("seed", ctx.seed))
    writer, reused, sim = begin_sim(ctx, f"{object.name}-{task.name}", config, sim)
    if reused is not None:
        return reused
    pose = object_pose(object, ctx.seed)
    goal = make_goal(task, object.name, pose, spacing=sim.spacing, board_z=sim.board_z, seed=ctx.seed)
    env = CuttingEnv(sim, batch_size=1)
    st = env.reset(object.name, pose, seed=ctx.seed)
    x0 = st.x[0]
    limits = (x0.min(0) - 0.03, x0.max(0) + 0.03)
    topo = discover(x0, st.damage[0], None, cfg=topology, device=ctx.device)
    labels = topo.labels
    frames_dir = writer.path / "frames"
    frames = [render_particles(x0, labels, frames_dir / "cut0.png", title=f"{object.name}: start", limits=limits, size=6)]
    arrays = {"x_0": x0, "damage_0": st.damage[0], "labels_0": labels, "material": st.material}
    records = []
    planes = goal.planes[: task.max_cuts]
    with progress_bar(f"simulate {object.name}/{task.name}", len(planes), ctx.progress) as advance:
        for i, action in enumerate(planes, start=1):
            info = env.cut(action)
            if task.push:
                env.push()
            st = env.state()
            topo = discover(st.x[0], st.damage[0], st.sweeps[0], previous_labels=labels, cfg=topology,
                            device=ctx.device)
            labels = topo.labels
            arrays.update({f"x_{i}": st.x[0], f"damage_{i}": st.damage[0], f"labels_{i}": labels})
            dmg = np.where(st.damage[0], 1, 0)
            frames.append(render_particles(st.x[0], np.where(dmg > 0, 7, 0), frames_dir / f"cut{i}_damage.png",
                                           title=f"cut {i}: damaged particles", limits=limits, size=6))
            frames.append(render_particles(st.x[0], labels, frames_dir / f"cut{i}.png",
                                           title=f"cut {i}: {topo.num_clusters} pieces", limits=limits, size=6))
            records.append({"cut": i, "action": action.asdict(), "sweep": info.sweeps[0].asdict(),
                            "pieces": int(topo.num_clusters), "damaged": int(st.damage[0].sum()),
                            "force": float(np.linalg.norm(info.force[0])), "work": float(info.work[0]),
                            "substeps": int(info.substeps), "wall_s": round(info.wall_time, 3),
                            "topology_s": round(topo.timings.get("total", sum(topo.timings.values())), 3)})
            advance(1, info=f"{topo.num_clusters} pieces")
    np.savez_compressed(writer.path / "states.npz", **arrays)
    (writer.path / "cuts.json").write_text(json.dumps({"object": object.name, "pose": pose.__dict__,
                                                       "task": task.name, "cuts": records}, indent=2, default=float))
    write_gif(frames, writer.path / "cut.gif", fps=2)
    summary = {"cuts": len(records), "pieces": records[-1]["pieces"] if records else 1,
               "particles": int(len(x0)), "sim_s_per_cut": float(np.mean([r["wall_s"] for r in records] or [0])),
               "topology_s_per_cut": float(np.mean([r["topology_s"] for r in records] or [0]))}
    path = writer.commit(summary)
    ctx.logger.log({f"simulate/{k}": v for k, v in summary.items()})
    ctx.logger.log_image("simulate/last_frame", path / "frames" / f"cut{len(records)}.png")
    return {"artifact": str(path), **summary}


def _commit(ctx, writer, summary: dict, stage: str, image) -> dict:
    path = writer.commit(summary)
    ctx.logger.log({f"{stage}/{k}": v for k, v in summary.items() if isinstance(v, (int, float))})
    ctx.logger.log_image(f"{stage}/last_frame", path / image)
    return {"artifact": str(path), **summary}


def run_writing(ctx: RunContext, sim, task, topology) -> dict:
    """task=cream_writing: the scripted writer writes task.word; frames coloured by stroke (= cluster)."""
    from topocut.planning.writer import cluster_check, write_scripted, writing_scene
    from topocut.sim.pen import CreamPen
    from topocut.sim.render import write_gif

    config = as_dict(("sim", sim), ("task", task), ("topology", topology), ("seed", ctx.seed))
    writer, reused, sim = begin_sim(ctx, f"cream_writing-{task.word}", config, sim)
    if reused is not None:
        return reused
    goals, strokes, start, draw = writing_scene(sim, task)
    pen = CreamPen(sim, task.pen, 1, start=start)
    frames, arrays = [], {}

    def on_letter(i):
        x, stroke = pen.particles()
        arrays.update({f"x_{i + 1}": x[0], f"stroke_{i + 1}": stroke})
        frames.append(draw(x[0], stroke, writer.path / "frames" / f"letter{i + 1}.png", f"stroke {i + 1}: {task.word[i]}"))

    with progress_bar(f"simulate cream_writing/{task.word}", 1, ctx.progress) as advance:
        res = write_scripted(pen, strokes, goals, on_letter=on_letter)
        advance(1, info=f"reward {res['total']:.3f}")
    x, stroke = pen.particles()
    check = cluster_check(x[0], stroke, topology, device=ctx.device)
    frames.append(draw(x[0], stroke, writer.path / "frames" / "final.png",
                       f"{task.word}: {check['clusters']} clusters, reward {res['total']:.3f}"))
    np.savez_compressed(writer.path / "states.npz", x=x[0], stroke=stroke, labels=check.pop("labels"),
                        goal=np.concatenate(goals), goal_labels=np.repeat(np.arange(len(goals)), [len(g) for g in goals]),
                        **arrays)
    (writer.path / "writing.json").write_text(json.dumps({"word": task.word, **res, **check}, indent=2, default=float))
    write_gif(frames, writer.path / "writing.gif", fps=1)
    summary = {"letters": len(strokes), "particles": res["particles"], "reward": res["total"],
               "clusters": check["clusters"], "clusters_match_strokes": check["agree"],
               **{f"reward_{c}{i}": r for i, (c, r) in enumerate(zip(task.word, res["per_letter"]))},
               "sim_s": round(res["seconds"], 2)}
    return _commit(ctx, writer, summary, "simulate", Path(frames[-1]).relative_to(writer.path))


def run_scooping(ctx: RunContext, sim, task, topology) -> dict:
    """task=scooping: the spoon primitive at each placement of task.spoon.scoops; chunks in the cup are clusters."""
    from topocut.planning.scoop import scoop_episode
    from topocut.sim.render import write_gif

    config = as_dict(("sim", sim), ("task", task), ("topology", topology), ("seed", ctx.seed))
    writer, reused, sim = begin_sim(ctx, "scooping", config, sim)
    if reused is not None:
        return reused
    with progress_bar("simulate scooping", len(task.spoon.scoops), ctx.progress) as advance:
        res = scoop_episode(sim, task, topology, writer.path / "frames", seed=ctx.seed,
                            on_scoop=lambda i, r: advance(1, info=f"scoop {i + 1}: {r['chunks_in_cup']} chunks in cup"))
    np.savez_compressed(writer.path / "states.npz", **res.pop("arrays"))
    frames = res.pop("frames")
    (writer.path / "scoops.json").write_text(json.dumps(res, indent=2, default=float))
    write_gif(frames, writer.path / "scoop.gif", fps=2)
    summary = {"scoops": len(task.spoon.scoops), "chunks_in_cup": res["chunks_in_cup"], "reward": res["reward"],
               "particles": res["particles"], "sim_s": round(res["seconds"], 2)}
    return _commit(ctx, writer, summary, "simulate", Path(frames[-1]).relative_to(writer.path))

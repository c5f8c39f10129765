"""stage=simulate: the task's oracle sequence on one scene, stored as a versioned ``sim`` artifact.

The task (``topocut.tasks.get_task(task.name)``) says which scene runs (``tool``): the knife tasks execute
their goal's ideal steps (``Goal.steps``: cuts, and the turns between them, topocut.sim.CuttingEnv.turn) and
store per-step particle states (positions, damage, cluster labels, knife sweeps); cream writing runs the scripted
writer and scooping the spoon primitive.  PNG frames coloured by cluster id with the knife and the board, and a
GIF that shows each cut in motion (topocut.sim.render; docs/sim.md#rendering).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipelines._common import as_dict, begin_sim, object_pose
from topocut.utils.context import RunContext
from topocut.utils.progress import progress_bar


def run(ctx: RunContext, sim, object, task, topology, frames_per_cut: int = 10) -> dict:
    from topocut.config import task_for_stage

    tool = task_for_stage(task, "simulate").tool
    if tool == "knife":
        return run_knife(ctx, sim, object, task, topology, frames_per_cut)
    return {"pen": run_writing, "spoon": run_scooping}[tool](ctx, sim, object, task, topology)


def _discover_cut(env, labels, x_start, push: bool, topology, device) -> tuple:
    """(state, TopologyResult) after a cut: discovery where the blade left the pieces, each kerf particle on the
    side it started on (``x_start``), then, if the task pushes, the push and discovery again without the sweep,
    the cut's labels the previous ones (docs/topology.md#discovery-and-the-push)."""
    from topocut.topology import discover

    st = env.state()
    topo = discover(st.x[0], st.damage[0], st.sweeps[0], previous_labels=labels, cfg=topology, device=device,
                    start_positions=x_start)
    if push:
        env.push()
        st = env.state()
        topo = discover(st.x[0], st.damage[0], [], previous_labels=topo.labels, next_id=topo.next_id, cfg=topology,
                        device=device)
    return st, topo


def run_knife(ctx: RunContext, sim, object, task, topology, frames_per_cut: int = 10) -> dict:
    """The goal's ideal steps (at most task.max_cuts cuts, the turns between them), push after cuts iff task.push;
    frames/cut0.png, per cut cutK_damage.png and cutK.png, turnK.png, and cut.gif (``_render``)."""
    from topocut.config import ConfigError
    from topocut.sim import CuttingEnv
    from topocut.tasks import get_task, truncate_steps
    from topocut.topology import discover

    if frames_per_cut < 0:  # the user's to fix: one message, exit 2
        raise ConfigError(f"stage.run.frames_per_cut={frames_per_cut}: must be >= 0 (0: no motion frames in cut.gif)")
    config = as_dict(("sim", sim), ("object", object), ("task", task), ("topology", topology), ("seed", ctx.seed),
                     ("frames_per_cut", frames_per_cut))
    writer, reused, sim = begin_sim(ctx, f"{object.name}-{task.name}", config, sim)
    if reused is not None:
        return reused
    pose = object_pose(object, ctx.seed)
    t = get_task(task.name)
    goal = t.make_goal(task, object.name, pose, spacing=sim.spacing, board_z=sim.board_z, seed=ctx.seed)
    env = CuttingEnv(sim, batch_size=1)
    st = env.reset(object.name, pose, seed=ctx.seed)
    x0 = st.x[0]
    labels = discover(x0, st.damage[0], None, cfg=topology, device=ctx.device).labels
    # every frame is drawn at the end with one view box over all of them (pieces pushed aside stay in view);
    # "png": its file under frames/ (None: a GIF-only motion frame), "hold": seconds it shows in cut.gif (0: not shown)
    frames = [dict(x=x0, labels=labels, title=f"{object.name}: start", png="cut0", hold=1.0)]
    arrays = {"x_0": x0, "damage_0": st.damage[0], "labels_0": labels, "material": st.material}
    records, turns = [], []
    steps = truncate_steps(t.oracle(goal), task.max_cuts)
    i = 0  # cuts made
    with progress_bar(f"simulate {object.name}/{task.name}", len(steps), ctx.progress) as advance:
        for step in steps:
            if step.kind == "turn":  # lay the piece down; discovery keeps the ids (no new sweep: empty sweeps)
                mask = env.turn(step)
                st = env.state()
                topo = discover(st.x[0], st.damage[0], st.sweeps[0], previous_labels=labels, cfg=topology,
                                device=ctx.device)
                labels = topo.labels
                arrays.update({f"x_turn{i}": st.x[0], f"labels_turn{i}": labels})
                frames.append(dict(x=st.x[0], labels=labels, title=f"turn after cut {i}: {topo.num_clusters} pieces",
                                   png=f"turn{i}", hold=1.0))
                turns.append({"after_cut": i, "turned": int(mask[0].sum()), "pieces": int(topo.num_clusters),
                              "turn": {k: getattr(step, k) for k in ("pieces", "axis", "angle", "center", "target")}})
                advance(1, info=f"turn after cut {i}")
                continue
            i += 1
            # snapshots every `every` substeps: about frames_per_cut over the knife's travel from above the object
            travel = sim.cut_substeps or (float(st.x[0][:, 2].max()) - sim.board_z + sim.knife_clearance) / (
                sim.knife_speed * env.dt)
            every = max(1, int(travel) // frames_per_cut) if frames_per_cut else 0
            damaged_before = st.damage[0]
            x_start = np.array(st.x[0])  # where the blade starts: a kerf particle keeps its side there
            info = env.cut(step.action, record_every=every)
            for snap in info.snapshots or []:  # the previous pieces' colours, the particles this cut damaged dark
                frames.append(dict(x=snap.x[0], labels=labels, damaged=snap.damage[0] & ~damaged_before, knife=step.action,
                                   knife_edge=snap.knife_edge[0], png=None, hold=0.12,
                                   title=f"cut {i}: {1e3 * snap.substep * env.dt:.0f} ms"))
            st, topo = _discover_cut(env, labels, x_start, task.push, topology, ctx.device)
            labels = topo.labels
            arrays.update({f"x_{i}": st.x[0], f"damage_{i}": st.damage[0], f"labels_{i}": labels})
            frames += _cut_frames(st, labels, step.action, f"cut {i}", f"cut {i}{' + push' if task.push else ''}",
                                  topo.num_clusters)
            records.append({"cut": i, "action": step.action.asdict(), "sweep": info.sweeps[0].asdict(),
                            "pieces": int(topo.num_clusters), "damaged": int(st.damage[0].sum()),
                            "force": float(np.linalg.norm(info.force[0])), "work": float(info.work[0]),
                            "substeps": int(info.substeps), "wall_s": round(info.wall_time, 3),
                            "topology_s": round(topo.timings.get("total", sum(topo.timings.values())), 3)})
            advance(1, info=f"{topo.num_clusters} pieces")
    np.savez_compressed(writer.path / "states.npz", **arrays)
    (writer.path / "cuts.json").write_text(json.dumps({"object": object.name, "pose": pose.__dict__, "task": task.name,
                                                       "cuts": records, "turns": turns}, indent=2, default=float))
    last_png = _render(writer.path, frames, sim.board_z)
    summary = {"cuts": len(records), "turns": len(turns), "pieces": records[-1]["pieces"] if records else 1,
               "particles": int(len(x0)), "sim_s_per_cut": float(np.mean([r["wall_s"] for r in records] or [0])),
               "topology_s_per_cut": float(np.mean([r["topology_s"] for r in records] or [0]))}
    return _commit(ctx, writer, summary, "simulate", Path(last_png).relative_to(writer.path))


def _cut_frames(st, labels, action, name: str, title: str, pieces: int) -> list[dict]:
    """The two frames after a cut: its damaged particles (cutK_damage.png) and the pieces by cluster id (cutK.png)."""
    from topocut.sim.render import DAMAGED, UNASSIGNED

    dmg = np.where(st.damage[0][:, None], DAMAGED, UNASSIGNED)  # N,3
    png = name.replace(" ", "")
    return [dict(x=st.x[0], colors=dmg, legend_extra=(("intact", UNASSIGNED), ("damaged", DAMAGED)), knife=action,
                 title=f"{name}: damaged particles", png=f"{png}_damage", hold=0),
            dict(x=st.x[0], labels=labels, knife=action, png=png, hold=1.2, title=f"{title}: {pieces} pieces")]


def _render(path: Path, frames: list[dict], board_z: float):
    """Every frame drawn with one view box (topocut.sim.render: pieces pushed aside stay in view); frames/<png>.png
    for those named (the knife at the cut's plane, the board, pieces by cluster id); cut.gif plays each cut in motion
    (``frames_per_cut`` snapshots during the cut, CuttingEnv.cut's record_every, the particles this cut has damaged
    so far dark) and holds the states between the cuts.  Returns the last png."""
    from topocut.sim.render import render_frames, save_png, write_gif

    images = render_frames([{k: v for k, v in f.items() if k not in ("png", "hold")} for f in frames], board_z=board_z)
    pngs = [save_png(img, path / "frames" / f"{f['png']}.png") for f, img in zip(frames, images) if f["png"]]
    shown = [(img, f["hold"]) for f, img in zip(frames, images) if f["hold"] > 0]
    write_gif([img for img, _ in shown], path / "cut.gif", durations=[h for _, h in shown])
    return pngs[-1]


def _commit(ctx, writer, summary: dict, stage: str, image) -> dict:
    path = writer.commit(summary)
    ctx.logger.log({f"{stage}/{k}": v for k, v in summary.items() if isinstance(v, (int, float))})
    ctx.logger.log_image(f"{stage}/last_frame", path / image)
    return {"artifact": str(path), **summary}


def run_writing(ctx: RunContext, sim, object, task, topology) -> dict:
    """The pen's tasks: the scripted writer writes task.word; frames coloured by stroke (= cluster)."""
    from topocut.sim.pen import CreamPen
    from topocut.sim.render import write_gif
    from topocut.tasks.writing_scene import cluster_check, write_scripted, writing_scene

    config = as_dict(("sim", sim), ("task", task), ("topology", topology), ("seed", ctx.seed))
    writer, reused, sim = begin_sim(ctx, f"{task.name}-{task.word}", config, sim)
    if reused is not None:
        return reused
    goals, strokes, start, draw = writing_scene(sim, task)
    pen = CreamPen(sim, task.pen, 1, start=start)
    frames, arrays = [], {}

    def on_letter(i):
        x, stroke = pen.particles()
        arrays.update({f"x_{i + 1}": x[0], f"stroke_{i + 1}": stroke})
        frames.append(draw(x[0], stroke, writer.path / "frames" / f"letter{i + 1}.png", f"stroke {i + 1}: {task.word[i]}"))

    with progress_bar(f"simulate {task.name}/{task.word}", 1, ctx.progress) as advance:
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


def run_scooping(ctx: RunContext, sim, object, task, topology) -> dict:
    """The spoon's tasks: the spoon primitive at each placement of task.spoon.scoops; chunks in the cup are clusters."""
    from topocut.sim.render import write_gif
    from topocut.tasks.scooping_scene import scoop_episode

    config = as_dict(("sim", sim), ("task", task), ("topology", topology), ("seed", ctx.seed))
    writer, reused, sim = begin_sim(ctx, task.name, config, sim)
    if reused is not None:
        return reused
    with progress_bar(f"simulate {task.name}", len(task.spoon.scoops), ctx.progress) as advance:
        res = scoop_episode(sim, task, topology, writer.path / "frames", seed=ctx.seed,
                            on_scoop=lambda i, r: advance(1, info=f"scoop {i + 1}: {r['chunks_in_cup']} chunks in cup"))
    np.savez_compressed(writer.path / "states.npz", **res.pop("arrays"))
    frames = res.pop("frames")
    (writer.path / "scoops.json").write_text(json.dumps(res, indent=2, default=float))
    write_gif(frames, writer.path / "scoop.gif", fps=2)
    summary = {"scoops": len(task.spoon.scoops), "chunks_in_cup": res["chunks_in_cup"], "reward": res["reward"],
               "spilled": res["spilled"], "particles": res["particles"], "sim_s": round(res["seconds"], 2)}
    return _commit(ctx, writer, summary, "simulate", Path(frames[-1]).relative_to(writer.path))

"""stage=eval: the benchmark protocol (paper §4, Table 1) over every policy -> eval/<name>.

Policies: ``oracle`` (the goal's ideal planes for the true pose: the R̂ reference), ``heuristic``
(the same planes for the nominal pose, open loop), ``mppi`` (the expert), ``pddp``, ``pddp_noperc``,
``pddp_graphconv``, ``dp3``, ``3dda`` (checkpoints from the bc stage: the versions in
``eval.checkpoints``, latest for the others; with ``eval.train_seeds=k > 1`` the k checkpoints of that training
run trained with seeds ``seed .. seed+k-1``, each evaluated as ``<policy>@s<seed>`` and pooled by the report),
and ``module.path:ClassName`` entries: your own Policy class, imported (topocut.policies.registry.load_external).
Episodes are committed one by one; an interrupted evaluation resumes.  ``eval.jobs=J`` runs them in J worker
processes (topocut.eval.runner.eval_tasks: batches, MPPI's specs one by one), then the report as usual.  Renders:
``eval.gifs`` (GIFs of one policy run's first episodes per task and the cutting-sequence figure:
topocut.eval.sequences) and ``eval.videos`` (an MP4 of every policy run's first episodes, each cut in motion:
topocut.eval.videos), both filmed as the episodes are evaluated.
"""
from __future__ import annotations

import dataclasses
import logging

from pipelines._common import as_dict
from topocut.eval.runner import evaluate_in_processes, setup, task_configs
from topocut.eval.sequences import Sequences
from topocut.eval.videos import Filming, Films, film_episodes
from topocut.utils.context import RunContext


def artifact_config(eval, sim, topology, reward, planner, observation, sampler, task_cfgs, seed: int) -> dict:
    """What keys the eval artifact: everything an episode's numbers depend on (a changed sampler or task yaml
    is a new evaluation, not a reused one)."""
    # eval.checkpoints only says which versions to load; their fingerprints key the artifact as inputs, so a
    # pinned run (stage=all) and a plain one that loads the same versions share one evaluation
    eval = dataclasses.replace(eval, checkpoints={})
    out = as_dict(("eval", eval), ("sim", sim), ("topology", topology), ("reward", reward), ("planner", planner),
                  ("observation", observation), ("sampler", sampler),
                  ("tasks", {n: dataclasses.asdict(t) for n, t in task_cfgs.items()}), ("seed", seed))
    if not eval.policy_kwargs:  # evaluations from before the key keep their artifact key
        out["eval"].pop("policy_kwargs", None)
    out["eval"].pop("jobs", None)  # how many processes, not what is evaluated
    # which episodes are filmed changes none of them; evaluations from before the videos keep their key (and pieces
    # filmed differently still combine: experiments/table1.py compares the keyed config)
    for key in ("videos", "video_frames_per_cut"):
        out["eval"].pop(key, None)
    return out


def run(ctx: RunContext, eval, sim, topology, reward, planner, observation, data, sampler=None) -> dict:
    from topocut.data.store import write_json_atomic
    from topocut.eval.protocol import episode_specs, run_evaluation
    from topocut.eval.report import RUNS_FILE, write_report

    specs = episode_specs(eval)
    task_cfgs = task_configs(eval.tasks, eval.max_cuts, eval.task_overrides)
    teleop = []
    if eval.reference == "teleop":  # checked before the simulator starts: a missing log is an error, not NaN R̂
        from topocut.eval.teleop import teleop_references

        teleop = teleop_references(ctx.store, eval.tasks, eval.unseen, eval.max_cuts)
    sim = dataclasses.replace(sim, arch=ctx.device)  # one backend for Taichi, Warp and torch
    reward = reward.on(ctx.device)  # reward=torch: its eigensolver and FPS on the run's device
    runs: dict = {}
    env, policies, inputs, observe_fn = setup(ctx, eval, sim, topology, reward, planner, observation, task_cfgs,
                                              sampler, runs=runs)
    inputs.update({f"teleop/{t.spec.key}": t.ref for t in teleop})
    config = artifact_config(eval, sim, topology, reward, planner, observation, sampler, task_cfgs, ctx.seed)
    writer, existing = ctx.store.begin("eval", eval.name, config, inputs, extra={"seed": ctx.seed,
                                                                                "device": ctx.device})
    if existing is not None:
        if eval.videos > 0 and not any((existing / "videos").glob("*/*.mp4")):
            logging.getLogger("topocut").warning(
                "eval: reusing %s, which holds no videos (eval.videos does not key the evaluation); a new eval.name "
                "evaluates and films anew", existing)
        return {"eval": str(existing), "reused": True}
    write_json_atomic(writer.path / RUNS_FILE, runs)  # run name -> policy and training seed, for the report
    # filmed as they are evaluated: every policy run's first eval.videos episodes (an MP4 each, each cut in motion)
    # and one run's first eval.gifs episodes per task (a GIF each, the cutting-sequence figure's rows)
    sequences = Sequences.of(specs, eval, list(policies), writer.path / "gifs")
    film = Films.of(Filming.of(specs, eval, writer.path / "videos"), sequences)
    if eval.jobs > 1:  # the episodes in worker processes; the run below then finds them all written (resume)
        evaluate_in_processes(specs, eval.jobs, env.batch_size, ctx, writer.path, eval, sim, topology, reward,
                              planner, observation, sampler, task_cfgs, film=film)
    run_evaluation(specs, policies, env, task_cfgs, writer.path, reward, topology, observe_fn, cfg=eval,
                   progress=ctx.progress, logger=ctx.logger, spacing=sim.spacing, film=film)
    for t in teleop:  # the human reference: each committed log replayed like a policy, one episode each
        from topocut.eval.teleop import TeleopReplay

        run_evaluation([t.spec], {"teleop": TeleopReplay(t.cuts)}, env, task_cfgs, writer.path, reward, topology,
                       observe_fn, cfg=eval, progress=False, logger=ctx.logger, spacing=sim.spacing)
    if film is not None:  # what an interrupted evaluation committed without its films: run again and filmed
        again = film_episodes(specs, policies, env, task_cfgs, writer.path / "videos", eval, reward, topology,
                              observe_fn, sim.spacing, film=film)
        if again:
            logging.getLogger("topocut").info("eval: %d episodes filmed by running them again (committed without "
                                              "their videos or GIFs by an interrupted evaluation)", again)
    if sequences is not None:
        from topocut.episode import env_board_z

        sequences.draw(env_board_z(env))
    report = write_report(writer.path, reference=eval.reference, normalize_by=eval.normalize_by,
                          compare_to=eval.comparison, confidence=eval.confidence,
                          n_resamples=eval.bootstrap_resamples, seed=eval.bootstrap_seed)
    rows = report["rows"]
    seeds = {}
    for r in runs.values():
        if r["train_seed"] is not None:
            seeds.setdefault(r["policy"], []).append(r["train_seed"])
    videos = sorted(str(p.relative_to(writer.path)) for p in writer.path.glob("videos/*/*.mp4"))
    path = writer.commit({"episodes": len(specs) * len(policies) + len(teleop), "policies": list(policies),
                          "train_seeds": seeds, "videos": videos})
    ctx.logger.log_image("eval/results", path / "results.png")
    print((path / "results.md").read_text())
    return {"eval": str(path), "episodes": len(specs) * len(policies) + len(teleop), "rows": len(rows),
            "table": str(path / "results.md")}

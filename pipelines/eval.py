"""stage=eval: the benchmark protocol (paper §4, Table 1) over every policy -> eval/<name>.

Policies: ``oracle`` (the goal's ideal planes for the true pose: the R̂ reference), ``heuristic``
(the same planes for the nominal pose, open loop), ``mppi`` (the expert), ``pddp``, ``pddp_noperc``,
``pddp_graphconv``, ``dp3``, ``3dda`` (checkpoints from the bc stage: the versions in
``eval.checkpoints``, latest for the others).
Episodes are committed one by one; an interrupted evaluation resumes.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

from omegaconf import OmegaConf

from pipelines._common import as_dict
from topocut.eval.config import LEARNED
from topocut.utils.context import RunContext

CONF_TASKS = Path(__file__).resolve().parent.parent / "conf" / "task"
SCRIPTED = ("oracle", "heuristic", "mppi")


def task_configs(names, max_cuts: int, overrides=None) -> dict:
    """TaskConfig per task from conf/task/<name>.yaml (one source of truth for task parameters), with
    ``overrides[name]`` (eval.task_overrides) on top."""
    from topocut.goals.config import TaskConfig

    out = {}
    for name in names:
        f = CONF_TASKS / f"{name}.yaml"
        if not f.exists():
            raise KeyError(f"eval.tasks: unknown task {name!r}; valid: {', '.join(sorted(p.stem for p in CONF_TASKS.glob('*.yaml')))}")
        over = (overrides or {}).get(name, {})
        cfg = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(TaskConfig), OmegaConf.load(f), over))
        cfg.max_cuts = max_cuts
        cfg.validate()
        out[name] = cfg
    return out


def artifact_config(eval, sim, topology, reward, planner, observation, sampler, task_cfgs, seed: int) -> dict:
    """What keys the eval artifact: everything an episode's numbers depend on (a changed sampler or task yaml
    is a new evaluation, not a reused one)."""
    # eval.checkpoints only says which versions to load; their fingerprints key the artifact as inputs, so a
    # pinned run (stage=all) and a plain one that loads the same versions share one evaluation
    eval = dataclasses.replace(eval, checkpoints={})
    return as_dict(("eval", eval), ("sim", sim), ("topology", topology), ("reward", reward), ("planner", planner),
                   ("observation", observation), ("sampler", sampler),
                   ("tasks", {n: dataclasses.asdict(t) for n, t in task_cfgs.items()}), ("seed", seed))


def build_policies(ctx: RunContext, names, env, sim, planner, reward, topology, task_cfgs, sampler=None,
                   versions=None):
    from topocut.planning import HeuristicPolicy, MPPIPolicy, sim_rollout_factory
    from topocut.planning.heuristic import FixedTrajectoryPolicy

    bad = [n for n in names if n not in SCRIPTED + LEARNED]
    if bad:
        raise ValueError(f"eval.policies: unknown policy {bad[0]!r}; valid: {', '.join(SCRIPTED + LEARNED)}")
    policies, inputs = {}, {}
    for name in names:
        if name == "oracle":
            policies[name] = HeuristicPolicy()
        elif name == "heuristic":
            policies[name] = FixedTrajectoryPolicy(task_cfgs, spacing=sim.spacing, board_z=sim.board_z)
        elif name == "mppi":
            push = {task: bool(t.push) for task, t in task_cfgs.items()}  # rollouts do what the episode does
            factory = sim_rollout_factory(env, reward, topology, board_z=sim.board_z, push=push)
            policies[name] = MPPIPolicy(planner, factory, seed=ctx.seed)
        else:
            path = ctx.store.resolve("checkpoint", name, (versions or {}).get(name, "latest"))
            inputs[name] = ctx.store.ref(path)
            if name.startswith("pddp"):
                from topocut.policies.config import SamplerConfig
                from topocut.policies.module import PDDPPolicy

                policies[name] = PDDPPolicy(str(path / "model.ckpt"), sampler=sampler or SamplerConfig(),
                                            device=ctx.device, seed=ctx.seed, board_z=sim.board_z)
            else:
                from topocut.policies.baselines.module import load_pose_policy

                policies[name] = load_pose_policy(path / "model.ckpt", seed=ctx.seed, device=ctx.device)
    return policies, inputs


def run(ctx: RunContext, eval, sim, topology, reward, planner, observation, data, sampler=None) -> dict:
    from topocut.eval.protocol import episode_specs, make_observe_fn, run_evaluation
    from topocut.eval.report import write_report
    from topocut.sim import CuttingEnv, init_taichi

    specs = episode_specs(eval)
    task_cfgs = task_configs(eval.tasks, eval.max_cuts, eval.task_overrides)
    teleop = []
    if eval.reference == "teleop":  # checked before the simulator starts: a missing log is an error, not NaN R̂
        from topocut.eval.teleop import teleop_references

        teleop = teleop_references(ctx.store, eval.tasks, eval.unseen, eval.max_cuts)
    sim = dataclasses.replace(sim, arch=ctx.device)  # one backend for Taichi, Warp and torch
    init_taichi(arch=ctx.device, seed=ctx.seed)
    env = CuttingEnv(sim, batch_size=max(1, sim.batch_size) if "mppi" in eval.policies else 1)
    policies, inputs = build_policies(ctx, eval.policies, env, sim, planner, reward, topology, task_cfgs, sampler,
                                      versions=eval.checkpoints)
    inputs.update({f"teleop/{t.spec.key}": t.ref for t in teleop})
    config = artifact_config(eval, sim, topology, reward, planner, observation, sampler, task_cfgs, ctx.seed)
    writer, existing = ctx.store.begin("eval", eval.name, config, inputs, extra={"seed": ctx.seed,
                                                                                "device": ctx.device})
    if existing is not None:
        return {"eval": str(existing), "reused": True}
    observe_fn = make_observe_fn(eval.observation, eval.num_points, observation, seed=eval.seed)
    run_evaluation(specs, policies, env, task_cfgs, writer.path, reward, topology, observe_fn, cfg=eval,
                   progress=ctx.progress, logger=ctx.logger, spacing=sim.spacing)
    for t in teleop:  # the human reference: each committed log replayed like a policy, one episode each
        from topocut.eval.teleop import TeleopReplay

        run_evaluation([t.spec], {"teleop": TeleopReplay(t.cuts)}, env, task_cfgs, writer.path, reward, topology,
                       observe_fn, cfg=eval, progress=False, logger=ctx.logger, spacing=sim.spacing)
    if eval.gifs > 0:
        render_episodes(specs, policies, env, task_cfgs, writer.path / "gifs", eval, reward, topology,
                        observe_fn, sim.spacing)
    report = write_report(writer.path, reference=eval.reference, normalize_by=eval.normalize_by)
    rows = report["rows"]
    path = writer.commit({"episodes": len(specs) * len(policies) + len(teleop), "policies": list(policies)})
    ctx.logger.log_image("eval/results", path / "results.png")
    print((path / "results.md").read_text())
    return {"eval": str(path), "episodes": len(specs) * len(policies) + len(teleop), "rows": len(rows),
            "table": str(path / "results.md")}


class _Recorder:
    """Wraps the env and keeps (x, damage, sweeps) of scene 0 after reset and after every cut/push."""

    def __init__(self, env):
        self._env, self.frames = env, []

    def __getattr__(self, name):
        return getattr(self._env, name)

    def _snap(self):
        st = self._env.state()
        self.frames.append((st.x[0].copy(), st.damage[0].copy(), st.sweeps[0] if st.sweeps else None))

    def reset(self, *args, **kwargs):
        self.frames = []
        out = self._env.reset(*args, **kwargs)
        self._snap()
        return out

    def cut(self, action):
        out = self._env.cut(action)
        self._snap()
        return out

    def push(self):  # the pushed state replaces the cut frame; the cut sweep stays with it
        self._env.push()
        sweeps = self.frames[-1][2]
        self._snap()
        self.frames[-2:] = [self.frames[-1][:2] + (sweeps,)]


def render_episodes(specs, policies, env, task_cfgs, out_dir, eval, reward, topology, observe_fn, spacing):
    """A GIF of the first ``eval.gifs`` episodes per task, for PDDP (or the first policy): particles
    coloured by cluster id after every cut."""
    from topocut.eval.protocol import evaluate_episode
    from topocut.sim.render import render_particles, write_gif
    from topocut.topology import discover

    name = "pddp" if "pddp" in policies else next(iter(policies))
    rec = _Recorder(env)
    for task in eval.tasks:
        for spec in [s for s in specs if s.task == task][: eval.gifs]:
            res = evaluate_episode(spec, policies[name], rec, task_cfgs[task], reward, topology, observe_fn,
                                   policy_name=name, max_cuts=eval.max_cuts, spacing=spacing,
                                   min_fragment_points=eval.min_fragment_points,
                                   stop_on_success=eval.stop_on_success)
            frames, labels = [], None
            x0 = rec.frames[0][0]
            limits = (x0.min(0) - 0.03, x0.max(0) + 0.03)
            for i, (x, damage, sweeps) in enumerate(rec.frames):
                labels = discover(x, damage, sweeps if i else None, previous_labels=labels, cfg=topology).labels
                r = res.rewards[i - 1] if 0 < i <= len(res.rewards) else None
                title = f"{name} {spec.key} cut {i}" + (f": R={r:.2f}" if r is not None else "")
                frames.append(render_particles(x, labels, out_dir / f"{spec.key}_{name}_{i}.png", title=title,
                                               limits=limits, size=6))
            write_gif(frames, out_dir / f"{spec.key}_{name}.gif", fps=1.5)
            for f in frames:
                f.unlink()

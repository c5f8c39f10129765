"""What stage=eval runs, as library functions: the task configs, the policies (scripted, MPPI, learned checkpoints
per training seed, your own classes), the episodes in several processes, and the GIF / cutting-sequence renders.
pipelines/eval.py reads the config, calls these and commits the artifact (docs/evaluation.md).
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

from omegaconf import OmegaConf

from topocut.policies import registry
from topocut.utils.context import RunContext

CONF_TASKS = Path(__file__).resolve().parent.parent.parent / "conf" / "task"
SCRIPTED, LEARNED = registry.scripted(), registry.learned()  # topocut.policies.registry: the one policy list
_log = logging.getLogger("topocut")


def task_configs(names, max_cuts: int, overrides=None) -> dict:
    """The task config per task: its dataclass (``task_config``: DiceConfig for dice, whose defaults are the task's;
    for a task of your own, ``module.path:ClassName``, its class's ``config`` and ``defaults``), then what
    conf/task/<name>.yaml sets beside its schema, then ``overrides[name]`` (eval.task_overrides); the cut budget is
    eval.max_cuts, raised to the task's own minimum (``min_cuts``: a die needs 3)."""
    from topocut.tasks import get_task, is_task_path, task_config

    out = {}
    for name in names:
        f = CONF_TASKS / f"{name}.yaml"
        if is_task_path(name):
            own = {}
        elif f.exists():
            own = OmegaConf.load(f)
            own.pop("defaults", None)  # Hydra's defaults list (base_<name>): the dataclass below is that schema
        else:
            raise KeyError(f"eval.tasks: unknown task {name!r}; valid: {', '.join(sorted(p.stem for p in CONF_TASKS.glob('*.yaml')))}")
        over = (overrides or {}).get(name, {})
        cfg = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(task_config(name)), own, over))

        cfg.max_cuts = max(max_cuts, get_task(name).min_cuts)  # dice need 3 cuts even where eval.max_cuts is 2
        cfg.validate()
        out[name] = cfg
    return out


def _train_seed(manifest: dict):
    """The seed a checkpoint was trained with (the bc stage records it in the manifest and its config)."""
    seed = manifest.get("seed", (manifest.get("config") or {}).get("seed"))
    return int(seed) if isinstance(seed, int) and not isinstance(seed, bool) else None


def _training_run(manifest: dict) -> str:
    """What makes checkpoints the same training run but for the seed: their config without it, and their inputs."""
    config = {k: v for k, v in (manifest.get("config") or {}).items() if k != "seed"}
    return json.dumps([config, manifest.get("inputs") or {}], sort_keys=True, default=str)


def seed_checkpoints(store, name: str, version: str = "latest", seeds=None) -> list[tuple[int | None, Path]]:
    """[(training seed, checkpoint path)] of ``checkpoint/<name>`` to evaluate.

    ``seeds`` None: the ``version`` (pinned or latest) alone.  Otherwise, per seed, the newest version trained with
    that seed whose training config (but the seed) and inputs equal ``version``'s: the siblings a Hydra multirun
    (`-m stage=bc seed=0,1,2`) commits.  A seed without one is a MissingArtifact naming the command that trains it.
    """
    from topocut.data.store import CorruptArtifact, MissingArtifact

    anchor = store.resolve("checkpoint", name, version)
    manifest = store.manifest(anchor)
    if seeds is None:
        return [(_train_seed(manifest), anchor)]
    run, found = _training_run(manifest), {}
    for v in reversed(store.versions("checkpoint", name)):
        try:
            m = store.manifest(store.root / "checkpoint" / name / v)
        except CorruptArtifact:  # an unreadable or other-schema version is no sibling of a readable one
            continue
        seed = _train_seed(m)
        if seed in seeds and seed not in found and _training_run(m) == run:
            found[seed] = v
    missing = [s for s in seeds if s not in found]
    if missing:
        raise MissingArtifact(
            f"checkpoint/{name}: eval.train_seeds={len(seeds)} pools the checkpoints trained with seeds "
            f"{', '.join(map(str, seeds))} like {anchor.name} (same training config and inputs); none was trained "
            f"with seed {', '.join(map(str, missing))}. Train them with `python -m topocut.run -m stage=bc "
            f"seed={','.join(map(str, seeds))}` (same overrides otherwise), or set eval.train_seeds=1")
    return [(s, store.resolve("checkpoint", name, found[s])) for s in seeds]


def build_policies(ctx: RunContext, names, env, sim, planner, reward, topology, task_cfgs, sampler=None,
                   versions=None, train_seeds: int = 1, runs: dict | None = None, policy_kwargs=None):
    """{run name: policy}, {run name: checkpoint ref}.  A learned policy is one run (its name) with
    ``train_seeds=1``, else one run ``<name>@s<seed>`` per training seed ctx.seed .. ctx.seed+k-1; ``runs``, when
    given, receives {run name: {"policy", "train_seed", "checkpoint"}} (the report's policies.json)."""
    from topocut.eval.report import run_name
    from topocut.policies.scripted import ScriptedSetup

    registry.check(names, "eval.policies", external=True, kwargs=policy_kwargs)
    seeds = None if train_seeds == 1 else [ctx.seed + i for i in range(train_seeds)]
    policies, inputs, runs = {}, {}, runs if runs is not None else {}
    setup = ScriptedSetup(env=env, sim=sim, planner=planner, reward=reward, topology=topology, task_cfgs=task_cfgs,
                          seed=ctx.seed)
    for name in names:
        if registry.is_import_path(name):  # your own policy class (docs/evaluation.md): episodes/<safe name>/
            ext = registry.load_external(name)
            runs[ext.run] = {"policy": name, "train_seed": None, "checkpoint": None, "display": ext.display}
            inputs[ext.run] = ext.fingerprint()  # its source keys the artifact
            policies[ext.run] = ext.build(policy_kwargs)
            continue
        if name in SCRIPTED:
            runs[name] = {"policy": name, "train_seed": None, "checkpoint": None}
            policies[name] = registry.build_scripted(name, setup)
        else:  # learned: a run per training seed, each loaded from its checkpoint
            for seed, path in seed_checkpoints(ctx.store, name, (versions or {}).get(name, "latest"), seeds):
                run = name if seeds is None else run_name(name, seed)
                inputs[run] = ctx.store.ref(path)
                runs[run] = {"policy": name, "train_seed": seed, "checkpoint": inputs[run]}
                policies[run] = _load_learned(ctx, name, path, sim, sampler)
    return policies, inputs


def _load_learned(ctx, name: str, path: Path, sim, sampler):
    # the sampler's seed is the evaluation's, whatever seed trained the checkpoint: training seeds differ in
    # their weights alone
    return registry.load_learned(name, path / "model.ckpt", device=ctx.device, seed=ctx.seed,
                                 board_z=getattr(sim, "board_z", 0.05), sampler=sampler)


def runs_one_at_a_time(name: str) -> bool:
    """Whether the episode engine runs the episodes of eval.policies entry ``name`` one at a time: a policy that
    plans with the simulator reads its state (the registry's ``sim_state`` input: MPPI) and takes every scene for
    its rollouts (topocut.episode.run_episodes).  Decided from the registry, without building anything."""
    if registry.is_import_path(name):  # your own class runs behind registry._ProtocolPolicy, which passes no
        return False  # sim_state: batched
    return "sim_state" in registry.get(name).inputs


def eval_tasks(specs: list, policy_names, batch: int, one_at_a_time=frozenset()) -> list[tuple[str, list]]:
    """[(policy, specs)]: the units evaluate_in_processes hands its workers.  A batched policy's unit is a batch
    of ``batch`` consecutive specs as run_evaluation groups them (an episode keeps its batch-mates, so its
    numbers are one process's); a policy in ``one_at_a_time`` gets one spec per unit (its episodes run alone
    anyway, and small units keep the workers evenly busy).  Batch by batch, every policy on it before the
    next, like run_evaluation: an interrupted evaluation holds comparable episodes for all policies."""
    tasks, batch = [], max(1, int(batch))
    for g0 in range(0, len(specs), batch):
        group = specs[g0:g0 + batch]
        for name in policy_names:
            tasks += [(name, [s]) for s in group] if name in one_at_a_time else [(name, group)]
    return tasks


def evaluate_in_processes(specs, jobs: int, batch: int, ctx: RunContext, out_dir: Path, eval, sim, topology, reward,
                          planner, observation, sampler, task_cfgs, film=None) -> None:
    """The episodes of ``specs`` in ``jobs`` joblib worker processes (each its own Taichi/CUDA context), their JSONs
    written under out_dir as run_evaluation writes them.  The work is cut into eval_tasks, handed out one at a
    time as workers free up (MPPI's episodes run one at a time at ~28 s each on a GPU: parts dealt up front left
    most workers idle while a few ran their last batches); each worker sets up its simulator and policies once and
    films what ``film`` (topocut.eval.videos.Filming) wants of its episodes as run_evaluation does."""
    import uuid

    from joblib import Parallel, delayed

    names = list(eval.policies)
    alone = {n for n in names if runs_one_at_a_time(n)}
    tasks = eval_tasks(specs, names, batch, alone)
    n_jobs = max(1, min(jobs, len(tasks)))
    _log.info("eval: %d episode specs x %d policies as %d tasks (batches of %d specs%s) in %d processes "
              "(eval.jobs=%d); their episodes resume like one process's", len(specs), len(names), len(tasks), batch,
              f"; {', '.join(sorted(alone))} one spec each" if alone else "", n_jobs, jobs)
    # loky keeps its workers between calls of one parent (a multirun, the tests): a key new to this call makes
    # each worker set up once for it, never reuse another call's simulator or policies
    key = uuid.uuid4().hex
    if ctx.device == "cuda":
        from topocut.utils.devices import share_gpus

        share_gpus()  # the workers spread over every GPU of the node (topocut.utils.devices)
    setup_args = (str(ctx.store.root), str(out_dir), ctx.device, ctx.seed, eval, sim, topology, reward, planner,
                  observation, sampler, task_cfgs)
    # batch_size=1: one task per dispatch, so a worker that finishes early takes the next task instead of
    # waiting behind a prefetched one
    wrote = Parallel(n_jobs=n_jobs, backend="loky", batch_size=1)(
        delayed(_evaluate_task)(name, part, key, *setup_args, film=film) for name, part in tasks)
    per_policy = {n: 0 for n in names}
    for (name, _), n in zip(tasks, wrote):
        per_policy[name] += n
    _log.info("eval: the workers wrote %d new episodes (%s)", sum(wrote),
              ", ".join(f"{n} {k}" for n, k in per_policy.items()))


_WORKER: dict = {}  # in a worker process: {"key": the call's key, "setup": (env, policies, runs, observe_fn)}


def _evaluate_task(name: str, specs, key: str, store_root: str, out_dir: str, device: str, seed: int, eval, sim,
                   topology, reward, planner, observation, sampler, task_cfgs, film=None) -> int:
    """One task of evaluate_in_processes in a worker: run_evaluation of eval.policies entry ``name`` (all its runs:
    one per training seed) on ``specs``; returns how many episodes it wrote (those already there are resumed)."""
    from topocut.eval.protocol import episode_path, run_evaluation
    from topocut.utils.devices import bind_worker
    from topocut.utils.runtime import seed_everything_all

    bind_worker()  # this worker's own GPU of the node, before Taichi touches CUDA

    if _WORKER.get("key") != key:  # this worker's first task of the call: Taichi and the policies, once
        from topocut.data.store import ArtifactStore

        _WORKER.clear()  # the previous call's simulator and policies go before new ones are built
        seed_everything_all(seed)
        ctx = RunContext(store=ArtifactStore(Path(store_root)), run_dir=Path(out_dir), device=device, seed=seed,
                         logger=None, progress=False)
        runs: dict = {}
        env, policies, _, observe_fn = setup(ctx, eval, sim, topology, reward, planner, observation, task_cfgs,
                                             sampler, runs=runs)
        _WORKER.update(key=key, setup=(env, policies, runs, observe_fn))
    env, policies, runs, observe_fn = _WORKER["setup"]
    seed_everything_all(seed)  # every task from the same global RNG state, whatever ran before it here
    mine = {r: p for r, p in policies.items() if runs[r]["policy"] == name}
    before = sum(episode_path(out_dir, r, s).exists() for s in specs for r in mine)
    run_evaluation(specs, mine, env, task_cfgs, out_dir, reward, topology, observe_fn, cfg=eval, progress=False,
                   spacing=sim.spacing, film=film)
    return sum(episode_path(out_dir, r, s).exists() for s in specs for r in mine) - before


def setup(ctx: RunContext, eval, sim, topology, reward, planner, observation, task_cfgs, sampler=None,
          runs: dict | None = None):
    """An evaluation's simulator, policies and observation: (env, {run: policy}, {run: checkpoint ref}, observe_fn).
    ``sim`` and ``reward`` already on ctx.device; ``runs`` as build_policies."""
    from topocut.eval.protocol import make_observe_fn
    from topocut.sim import CuttingEnv, init_taichi

    # eval.cpu_threads=1: atomic adds in a fixed order, reproducible CPU numbers (a no-op when an earlier stage of
    # the process started Taichi)
    init_taichi(arch=ctx.device, seed=ctx.seed,
                cpu_threads=(eval.cpu_threads or None) if ctx.device == "cpu" else None)
    # sim.batch_size scenes: B episodes of a policy at once (MPPI: one episode, its rollouts the scenes)
    env = CuttingEnv(sim, batch_size=max(1, sim.batch_size))
    policies, inputs = build_policies(ctx, eval.policies, env, sim, planner, reward, topology, task_cfgs, sampler,
                                      versions=eval.checkpoints, train_seeds=eval.train_seeds, runs=runs,
                                      policy_kwargs=eval.policy_kwargs)
    return env, policies, inputs, make_observe_fn(eval.observation, eval.num_points, observation, seed=eval.seed,
                                                  device=ctx.device)

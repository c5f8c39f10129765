"""stage=all: run the stages in order with the same overrides, each as its own run.

``make paper`` is this stage at scale=paper on one GPU: MPPI demonstrations over data.tasks x data.objects (shards
of at most data.episodes_per_job episodes each, merged), perception pretraining, every learned policy trained with
eval.train_seeds seeds, and the 405-episode evaluation of every policy (docs/results.md).  ``make run`` is the same
command at smoke scale.
"""
from __future__ import annotations

import time
from pathlib import Path

from topocut.utils.context import RunContext
from topocut.utils.progress import flatten, print_summary

CONF_DIR = Path(__file__).resolve().parent.parent / "conf"


def _compose(overrides: list[str]):
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():
        return compose(config_name="config", overrides=overrides)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


def produced_versions(stage: str, summary: dict, cfg, policies=None) -> dict[str, str]:
    """Overrides that make the next stages read exactly what ``stage`` wrote or reused, not whatever is
    ``latest`` under that name (another run may commit a newer version meanwhile); bc's checkpoints only for
    ``policies`` (the evaluation's: it refuses a pin of a policy it does not run), all when None."""
    for key, produced_by, name_key, version_key in (("dataset", "mppi", "dataset", "version"),
                                                    ("dataset", "merge", "dataset", "version"),
                                                    ("checkpoint", "pretrain", "encoder", "encoder_version")):
        if stage == produced_by and summary.get(key):
            path = Path(summary[key])
            if path.parent.name == cfg.data[name_key]:
                return {f"data.{version_key}": path.name}
    if stage == "bc":  # one checkpoint per policy: {name: {"checkpoint": .../<name>/vNNN, ...}}
        versions = {name: Path(out["checkpoint"]).name for name, out in summary.items()
                    if isinstance(out, dict) and out.get("checkpoint") and Path(out["checkpoint"]).parent.name == name
                    and (policies is None or name in policies)}
        if versions:  # one dict override: a key like `eval.checkpoints.3dda` is not valid override grammar
            return {"++eval.checkpoints": "{" + ",".join(f"{k}:{v}" for k, v in versions.items()) + "}"}
    return {}


def _under(key: str, pinned: tuple[str, ...]) -> bool:
    """A user's override of a pinned key or of anything inside it (eval.checkpoints.pddp under eval.checkpoints)."""
    return any(key == p or key.startswith(p + ".") for p in pinned)


def cells(config: dict) -> list[tuple[str, str]]:
    """The (task, object) demonstration cells: data.tasks x data.objects, each [] meaning the run's own."""
    data = config["data"]
    return [(t, o) for t in (data["tasks"] or [config["task"]["name"]])
            for o in (data["objects"] or [config["object"]["name"]])]


# Relative cost of an episode by task, for the order of the demonstration runs only: one process's seconds a cut on
# an H100 (15 processes under MPS, docs/benchmarks.md "The paper's demonstrations for real": slice 4.3, stick 6.2,
# dice 6.4) times the cuts an episode made there (slice ~3.2, ending on success; stick and dice all 5).  A task not
# listed counts as the costliest, so that it never lands in the tail.
EPISODE_COST = {"slice": 14.0, "stick": 31.0, "dice": 32.0}


def demo_runs(config: dict) -> list[tuple[str, dict, tuple[int, int]]]:
    """stage=all's stage=mppi runs as (label, own keys, (cell, part)), in the order they are handed out.

    data.episodes_per_job=null: one run per cell, as a cell always was.  Set: each cell's episodes first_episode ..
    first_episode + episodes - 1 cut into consecutive parts of at most that many (data.first_episode, data.episodes
    per part), whose union is what the one run writes (same seeds, stage=mppi's demo_episode_seed).  Order: part index
    first, so every cell advances and the short last parts end the queue; within one index the costliest parts
    first (EPISODE_COST x episodes: dice, stick, slice), so the cheap ones fill the gaps the long ones leave."""
    from topocut.config import ConfigError

    data = config["data"]
    per_job, first = data.get("episodes_per_job"), int(data.get("first_episode") or 0)
    if per_job is not None and per_job < 1:
        raise ConfigError(f"data.episodes_per_job: {per_job} is not valid; must be >= 1 (or null: one run per cell)")
    runs = []
    for i, (t, o) in enumerate(cells(config)):
        # the cell's own task parameters (data.task_overrides), spelled as its stage=mppi run takes them
        task_keys = flatten((data.get("task_overrides") or {}).get(t) or {}, sep=".", prefix="task.")
        if per_job is None:
            runs.append(((0, 0, i), f"mppi-{t}-{o}", {"task": t, "object": o, "data.shard": "true", **task_keys},
                         (i, 0)))
            continue
        end = first + data["episodes"]
        for j, start in enumerate(range(first, end, per_job)):
            n = min(per_job, end - start)
            cost = n * EPISODE_COST.get(t, max(EPISODE_COST.values()))
            runs.append(((j, -cost, i), f"mppi-{t}-{o}-e{start}-{start + n - 1}",
                         {"task": t, "object": o, "data.shard": "true", "data.first_episode": start,
                          "data.episodes": n, **task_keys}, (i, j)))
    return [run[1:] for run in sorted(runs, key=lambda run: run[0])]


def train_seeds(config: dict) -> list[int]:
    """The seeds stage=bc trains with: seed .. seed + eval.train_seeds - 1, the ones stage=eval pools."""
    return [config["seed"] + i for i in range(config["eval"]["train_seeds"])]


def _timed_stage(cfg, run_dir: Path, overrides: list[str]) -> tuple[dict, float]:
    """run_stage in a joblib worker: (its summary, its wall seconds)."""
    from topocut.run import run_stage
    from topocut.utils.devices import bind_worker

    bind_worker()  # this worker's own GPU of the node, before anything touches CUDA (topocut.utils.devices)
    started = time.time()
    return run_stage(cfg, run_dir, overrides), round(time.time() - started, 1)


def run(ctx: RunContext, sequence: list[str], trainer=None) -> dict:
    # past 80 lines on purpose: one(), at_once() and overrides_of() share this run's pins and summaries as closures
    """Each stage of ``sequence`` as its own run under ``<run dir>/<label>``, later ones pinned to what earlier ones
    wrote.  mppi runs once per cell, or per part of a cell (data.episodes_per_job; several runs: shards, data.jobs of
    them at once in worker processes, then one merge of exactly those); bc once per training seed (trainer.jobs of
    them at once).
    Every run reuses a committed artifact of the same config, so a killed pipeline resumes where it stopped;
    the summary ends with each run's wall time."""
    from topocut.run import run_stage

    if trainer is not None and str(trainer.strategy).startswith("ddp") and trainer.devices != 1:
        # Lightning's DDP launcher starts every further rank by re-running this command: those ranks would run
        # the data and eval stages again beside rank 0.  Training stages on their own handle ranks (rank 0 commits).
        raise ValueError(f"stage=all runs in one process; trainer.strategy={trainer.strategy} with "
                         f"trainer.devices={trainer.devices} starts several. Run the stages one by one, e.g. "
                         "`python -m topocut.run stage=pretrain trainer=ddp` and then `stage=bc trainer=ddp`")

    def key(o: str) -> str:
        return o.split("=")[0].lstrip("+~")

    demos = demo_runs(ctx.config) if "mppi" in sequence else []  # a bad data.episodes_per_job fails before any run
    base = [o for o in ctx.overrides if not _under(key(o), ("stage",))]  # stage.run.*: stage=all's own keys
    summaries, pins, wall = {}, {}, {}

    def overrides_of(name: str, own: dict) -> list[str]:
        """The user's overrides, less stage=all's own keys, the pinned ones and ``own`` (this run's keys: cell,
        seed), then the pins, ``own`` and the stage."""
        pinned = tuple(k.lstrip("+") for k in pins)
        overrides = [o for o in base if key(o) not in own and not _under(key(o), pinned)]
        return overrides + [f"{k}={v}" for k, v in {**pins, **own}.items()] + [f"stage={name}"]

    def one(name: str, label: str, own: dict | None = None) -> dict:
        """One run of stage ``name``; ``own``: this run's keys (cell, seed), replacing the user's same keys."""
        overrides = overrides_of(name, own or {})
        cfg = _compose(overrides)
        started = time.time()
        summaries[label] = run_stage(cfg, ctx.run_dir / label, overrides)
        wall[label] = round(time.time() - started, 1)
        pins.update(produced_versions(name, summaries[label], cfg, policies=ctx.config["eval"]["policies"]))
        return summaries[label]

    def at_once(name: str, todo: list[tuple[str, dict]], jobs: int) -> list[dict]:
        """Runs of stage ``name`` for ``todo`` [(label, own keys)], ``jobs`` at a time in joblib's worker processes
        (each its own Taichi/CUDA context; composed here, run there), handed out one by one in ``todo``'s order as
        workers free up (batch_size=1: joblib's "auto" may group runs it sees end quickly, e.g. reused ones);
        their summaries in ``todo``'s order."""
        from joblib import Parallel, delayed

        from topocut.utils.devices import share_gpus

        if jobs <= 1:
            return [one(name, label, own) for label, own in todo]
        if getattr(ctx, "device", "cpu") == "cuda":
            share_gpus()  # the workers spread over every GPU of the node
        runs = []
        for label, own in todo:
            overrides = overrides_of(name, own)
            runs.append((label, _compose(overrides), overrides))
        started = time.time()
        out = Parallel(n_jobs=min(jobs, len(runs)), backend="loky", batch_size=1)(
            delayed(_timed_stage)(cfg, ctx.run_dir / label, overrides) for label, cfg, overrides in runs)
        for (label, cfg, _), (summary, seconds) in zip(runs, out):
            summaries[label], wall[label] = summary, seconds
            pins.update(produced_versions(name, summary, cfg, policies=ctx.config["eval"]["policies"]))
        wall[f"{name}-at-once"] = round(time.time() - started, 1)
        return [summaries[label] for label, _, _ in runs]

    for name in sequence:
        if name == "mppi" and len(demos) > 1:
            out = at_once("mppi", [(label, own) for label, own, _ in demos], int(ctx.config["data"]["jobs"]))
            # the merge takes the shards cell by cell, each cell's parts in episode order: the episodes in the
            # order one run per cell would give them
            by_part = {at: Path(s["dataset"]).parent.name for (*_, at), s in zip(demos, out)}
            only = ",".join(f"'{by_part[at]}'" for at in sorted(by_part))
            one("merge", "merge", {"stage.run.only": f"[{only}]"})
        elif name == "mppi":
            (t, o), = cells(ctx.config)
            data = ctx.config["data"]
            one("mppi", "mppi", {"task": t, "object": o} if data["tasks"] or data["objects"] else None)
        elif name == "bc" and len(train_seeds(ctx.config)) > 1:
            at_once("bc", [(f"bc-s{s}", {"seed": s}) for s in train_seeds(ctx.config)],
                    int(ctx.config["trainer"]["jobs"]))
        else:
            one(name, name)
    summaries["wall_s"] = wall
    print_summary("pipeline: " + " -> ".join(sequence), summaries)
    table = summaries.get("eval", {}).get("table")
    if table:  # the run ends on the results table
        print(Path(table).read_text().split("### Paper")[0])
    return summaries

"""stage=all: run the stages in order with the same overrides, each as its own run.

``make paper`` is this stage at scale=paper on one GPU: MPPI demonstrations over data.tasks x data.objects (one
shard each, merged), perception pretraining, every learned policy trained with eval.train_seeds seeds, and the
405-episode evaluation of every policy (docs/results.md).  ``make run`` is the same command at smoke scale.
"""
from __future__ import annotations

import time
from pathlib import Path

from topocut.utils.context import RunContext
from topocut.utils.progress import print_summary

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


def train_seeds(config: dict) -> list[int]:
    """The seeds stage=bc trains with: seed .. seed + eval.train_seeds - 1, the ones stage=eval pools."""
    return [config["seed"] + i for i in range(config["eval"]["train_seeds"])]


def _timed_stage(cfg, run_dir: Path, overrides: list[str]) -> tuple[dict, float]:
    """run_stage in a joblib worker: (its summary, its wall seconds)."""
    from topocut.run import run_stage

    started = time.time()
    return run_stage(cfg, run_dir, overrides), round(time.time() - started, 1)


def run(ctx: RunContext, sequence: list[str], trainer=None) -> dict:
    """Each stage of ``sequence`` as its own run under ``<run dir>/<label>``, later ones pinned to what earlier ones
    wrote.  mppi runs once per cell (several cells: shards, data.jobs of them at once in worker processes, then one
    merge of exactly those); bc once per training seed (trainer.jobs of them at once).
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
        (each its own Taichi/CUDA context; composed here, run there); their summaries in order."""
        from joblib import Parallel, delayed

        if jobs <= 1:
            return [one(name, label, own) for label, own in todo]
        runs = []
        for label, own in todo:
            overrides = overrides_of(name, own)
            runs.append((label, _compose(overrides), overrides))
        started = time.time()
        out = Parallel(n_jobs=min(jobs, len(runs)), backend="loky")(
            delayed(_timed_stage)(cfg, ctx.run_dir / label, overrides) for label, cfg, overrides in runs)
        for (label, cfg, _), (summary, seconds) in zip(runs, out):
            summaries[label], wall[label] = summary, seconds
            pins.update(produced_versions(name, summary, cfg, policies=ctx.config["eval"]["policies"]))
        wall[f"{name}-at-once"] = round(time.time() - started, 1)
        return [summaries[label] for label, _, _ in runs]

    for name in sequence:
        if name == "mppi" and len(cells(ctx.config)) > 1:
            todo = [(f"mppi-{t}-{o}", {"task": t, "object": o, "data.shard": "true"}) for t, o in cells(ctx.config)]
            shards = [Path(s["dataset"]) for s in at_once("mppi", todo, int(ctx.config["data"]["jobs"]))]
            one("merge", "merge", {"stage.run.only": "[" + ",".join(f"'{p.parent.name}'" for p in shards) + "]"})
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

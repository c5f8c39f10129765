"""stage=all: run the stages in order with the same overrides, each as its own run."""
from __future__ import annotations

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


def produced_versions(stage: str, summary: dict, cfg) -> dict[str, str]:
    """Overrides that make the next stages read exactly what ``stage`` wrote or reused, not whatever is
    ``latest`` under that name (another run may commit a newer version meanwhile)."""
    for key, produced_by, name_key, version_key in (("dataset", "mppi", "dataset", "version"),
                                                    ("checkpoint", "pretrain", "encoder", "encoder_version")):
        if stage == produced_by and summary.get(key):
            path = Path(summary[key])
            if path.parent.name == cfg.data[name_key]:
                return {f"data.{version_key}": path.name}
    if stage == "bc":  # one checkpoint per policy: {name: {"checkpoint": .../<name>/vNNN, ...}}
        versions = {name: Path(out["checkpoint"]).name for name, out in summary.items()
                    if isinstance(out, dict) and out.get("checkpoint") and Path(out["checkpoint"]).parent.name == name}
        if versions:  # one dict override: a key like `eval.checkpoints.3dda` is not valid override grammar
            return {"++eval.checkpoints": "{" + ",".join(f"{k}:{v}" for k, v in versions.items()) + "}"}
    return {}


def _under(key: str, pinned: tuple[str, ...]) -> bool:
    """A user's override of a pinned key or of anything inside it (eval.checkpoints.pddp under eval.checkpoints)."""
    return any(key == p or key.startswith(p + ".") for p in pinned)


def run(ctx: RunContext, sequence: list[str], trainer=None) -> dict:
    from topocut.run import run_stage

    if trainer is not None and str(trainer.strategy).startswith("ddp") and trainer.devices != 1:
        # Lightning's DDP launcher starts every further rank by re-running this command: those ranks would run
        # the data and eval stages again beside rank 0.  Training stages on their own handle ranks (rank 0 commits).
        raise ValueError(f"stage=all runs in one process; trainer.strategy={trainer.strategy} with "
                         f"trainer.devices={trainer.devices} starts several. Run the stages one by one, e.g. "
                         "`python -m topocut.run stage=pretrain trainer=ddp` and then `stage=bc trainer=ddp`")

    base = [o for o in ctx.overrides if not o.split("=")[0].lstrip("+~") == "stage"]
    summaries, pins = {}, {}
    for name in sequence:
        pinned = tuple(k.lstrip("+") for k in pins)
        overrides = [o for o in base if not _under(o.split("=")[0].lstrip("+~"), pinned)]
        overrides += [f"{k}={v}" for k, v in pins.items()] + [f"stage={name}"]
        cfg = _compose(overrides)
        summaries[name] = run_stage(cfg, ctx.run_dir / name, overrides)
        pins.update(produced_versions(name, summaries[name], cfg))
    print_summary("pipeline: " + " -> ".join(sequence), summaries)
    table = summaries.get("eval", {}).get("table")
    if table:  # the run ends on the results table
        print(Path(table).read_text().split("### Paper")[0])
    return summaries

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


def run(ctx: RunContext, sequence: list[str]) -> dict:
    from topocut.run import run_stage

    base = [o for o in ctx.overrides if not o.split("=")[0].lstrip("+~") == "stage"]
    summaries = {}
    for name in sequence:
        cfg = _compose(base + [f"stage={name}"])
        summaries[name] = run_stage(cfg, ctx.run_dir / name, base + [f"stage={name}"])
    print_summary("pipeline: " + " -> ".join(sequence), summaries)
    table = summaries.get("eval", {}).get("table")
    if table:  # the run ends on the results table
        print(Path(table).read_text().split("### Paper")[0])
    return summaries

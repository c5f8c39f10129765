"""Paper Table 2 from the artifact store: one row per trained perception checkpoint.

Each ``stage=pretrain`` run commits a ``checkpoint/perception*`` version whose manifest holds its
model and trainer config and whose ``metrics.json`` holds the validation metrics.  A Hydra sweep over
those keys therefore leaves one version per row; this script reads them back and writes the table:

    python -m topocut.run -m stage=pretrain model.sort=false,true model.noise=false,true model.num_points=128,256
    python -m topocut.run -m stage=pretrain model=pointnet model.num_points=512,2048
    python experiments/table2.py --root outputs [--out docs/perception_table2.md]

Rows sharing a configuration (reruns, whatever their seed) are listed once, the newest version winning;
``other`` names the settings without a column of their own on which the rows differ.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from topocut.data.store import ArtifactStore

COLUMNS = ("model", "sort", "noise", "points", "seen", "unseen", "rule_seen", "rule_unseen", "on_rule_errors_seen",
           "on_rule_errors_unseen", "err_reduction_seen", "err_reduction_unseen", "chamfer", "parameters",
           "held_out", "epochs", "other", "dataset", "version")
# seen / unseen: F's cluster accuracy; rule_*: the no-learning floor "split each input cluster by the cut mask";
# on_rule_errors_*: F's accuracy on the points where that rule is wrong (the rule scores 0 there);
# err_reduction_*: 1 - (1 - acc) / (1 - rule), the fraction of the rule's errors F removes (docs/perception.md)
# trainer settings that change what a run learns (hardware, workers and logging do not); the seed does not either:
# reruns of one configuration with other seeds share a row, the newest version winning
RUN_KEYS = ("max_epochs", "max_steps", "batch_size", "val_fraction", "held_out_objects")
SHOWN = {"model.model", "model.sort", "model.num_points", "trainer.max_epochs", "trainer.held_out_objects"}


def _run_config(manifest: dict) -> dict:
    """``model.*`` (DynamicsConfig defaults filled in, so older manifests key alike) and ``trainer.<RUN_KEYS>``.

    ``model.noise`` is folded into ``model.noise_std``, the jitter the run trained with (0 without noise).
    """
    from dataclasses import asdict

    from topocut.models.config import DynamicsConfig

    cfg = manifest.get("config", {})
    model = {**asdict(DynamicsConfig()), **(cfg.get("model") or {})}
    trainer = cfg.get("trainer") or {}
    held = trainer.get("held_out_objects")
    model["noise_std"] = float(model["noise_std"]) if model.pop("noise") else 0.0
    out = {f"model.{k}": v for k, v in model.items()}
    out.update({f"trainer.{k}": trainer.get(k) for k in RUN_KEYS})
    out["trainer.held_out_objects"] = sorted(held) if held is not None else None
    return out


def _reduction(metrics: dict, split: str):
    """val/cluster_err_reduction<split>, or for checkpoints from before it was logged, the same from the
    accuracies their metrics hold."""
    value = metrics.get(f"val/cluster_err_reduction{split}")
    if value is None:
        acc, rule = metrics.get(f"val/cluster_acc{split}"), metrics.get(f"val/mask_rule_acc{split}")
        if acc is not None and rule is not None:
            from topocut.models.losses import error_reduction

            value = error_reduction(acc, rule)
    return value


def collect(root: str | Path) -> list[dict]:
    """One dict per perception checkpoint version under ``root`` (newest per configuration).

    Rows are keyed by the whole model config, the trainer's RUN_KEYS and the dataset; ``other`` lists the
    settings, not in a column of their own, on which the listed rows differ.
    """
    store = ArtifactStore(root)
    rows: dict[str, dict] = {}
    for name in sorted(n for n in store.names("checkpoint") if n.startswith("perception")):
        for version in store.versions("checkpoint", name):  # oldest first: later ones overwrite
            path = store.root / "checkpoint" / name / version
            manifest = store.manifest(path)
            run = _run_config(manifest)
            metrics = json.loads((path / "metrics.json").read_text())["metrics"]
            held = run["trainer.held_out_objects"]
            row = {"model": run["model.model"], "sort": bool(run["model.sort"]),
                   "noise": run["model.noise_std"] > 0,
                   "points": int(run["model.num_points"]),
                   "seen": metrics.get("val/cluster_acc_seen"), "unseen": metrics.get("val/cluster_acc_unseen"),
                   "rule_seen": metrics.get("val/mask_rule_acc_seen"),
                   "rule_unseen": metrics.get("val/mask_rule_acc_unseen"),  # no-learning floor (module.py)
                   "on_rule_errors_seen": metrics.get("val/cluster_acc_rule_wrong_seen"),
                   "on_rule_errors_unseen": metrics.get("val/cluster_acc_rule_wrong_unseen"),
                   "err_reduction_seen": _reduction(metrics, "_seen"),
                   "err_reduction_unseen": _reduction(metrics, "_unseen"),
                   "chamfer": metrics.get("val/chamfer"),
                   "parameters": (manifest.get("summary") or {}).get("parameters"),
                   "held_out": "?" if held is None else ",".join(held) or "none",
                   "epochs": run["trainer.max_epochs"],
                   "dataset": ",".join(manifest.get("inputs", {}).values()) if isinstance(manifest.get("inputs"), dict)
                   else str(manifest.get("inputs", "")),
                   "version": f"{name}/{version}", "_run": run}
            rows[json.dumps([run, row["dataset"]], sort_keys=True, default=str)] = row
    runs = [r.pop("_run") for r in rows.values()]
    varying = sorted(k for k in {k for r in runs for k in r} - SHOWN
                     if len({json.dumps(r.get(k), sort_keys=True, default=str) for r in runs}) > 1)
    if len({r["model.noise_std"] for r in runs} - {0.0}) <= 1:  # the noise column tells them apart
        varying = [k for k in varying if k != "model.noise_std"]
    for row, run in zip(rows.values(), runs):
        row["other"] = ", ".join(f"{k}={run.get(k)}" for k in varying) or None
    order = {"graph_transformer": 0, "pointnet": 1}
    return sorted(rows.values(), key=lambda r: (order.get(r["model"], 2), r["points"], r["sort"], r["noise"],
                                                r["held_out"], str(r["epochs"]), r["other"] or "", r["dataset"]))


def _fmt(v) -> str:
    if v is None:
        return "—"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.3f}" if abs(v) >= 0.01 else f"{v:.2e}"
    return str(v)


def markdown(rows: list[dict]) -> str:
    head = "| " + " | ".join(COLUMNS) + " |\n|" + "---|" * len(COLUMNS) + "\n"
    return head + "".join("| " + " | ".join(_fmt(r[c]) for c in COLUMNS) + " |\n" for r in rows)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default="outputs", help="artifact store root (outputs_root)")
    ap.add_argument("--out", default=None, help="write the markdown table here (default: print only)")
    args = ap.parse_args(argv)
    rows = collect(args.root)
    if not rows:
        raise SystemExit(f"no checkpoint/perception* versions under {args.root!r}; run stage=pretrain first")
    text = markdown(rows)
    print(text)
    if args.out:
        Path(args.out).write_text(text)


if __name__ == "__main__":
    main()

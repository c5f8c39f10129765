"""Paper Table 2 from the artifact store: one row per trained perception checkpoint.

Each ``stage=pretrain`` run commits a ``checkpoint/perception*`` version whose manifest holds its
model config (model, sort, noise, num_points) and whose ``metrics.json`` holds the validation
metrics.  A Hydra sweep over those keys therefore leaves one version per row; this module reads them
back and writes the table:

    python -m topocut.run -m stage=pretrain model.sort=false,true model.noise=false,true model.num_points=128,256
    python -m topocut.run -m stage=pretrain model=pointnet model.num_points=512,2048
    python -m topocut.models.table2 --root outputs --out docs/perception_table2.md

Rows sharing a configuration (reruns) are listed once, the newest version winning.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from topocut.data.store import ArtifactStore

COLUMNS = ("model", "sort", "noise", "points", "seen", "unseen", "rule_seen", "rule_unseen", "chamfer", "parameters",
           "dataset", "version")


def collect(root: str | Path) -> list[dict]:
    """One dict per perception checkpoint version under ``root`` (newest per configuration)."""
    store = ArtifactStore(root)
    rows: dict[tuple, dict] = {}
    for name in sorted(n for n in store.names("checkpoint") if n.startswith("perception")):
        for version in store.versions("checkpoint", name):  # oldest first: later ones overwrite
            path = store.root / "checkpoint" / name / version
            manifest = store.manifest(path)
            model = manifest.get("config", {}).get("model", {})
            metrics = json.loads((path / "metrics.json").read_text())["metrics"]
            row = {"model": model.get("model", "?"), "sort": bool(model.get("sort")),
                   "noise": bool(model.get("noise")), "points": int(model.get("num_points", 0)),
                   "seen": metrics.get("val/cluster_acc_seen"), "unseen": metrics.get("val/cluster_acc_unseen"),
                   "rule_seen": metrics.get("val/mask_rule_acc_seen"),
                   "rule_unseen": metrics.get("val/mask_rule_acc_unseen"),  # no-learning floor (module.py)
                   "chamfer": metrics.get("val/chamfer"),
                   "parameters": (manifest.get("summary") or {}).get("parameters"),
                   "dataset": ",".join(manifest.get("inputs", {}).values()) if isinstance(manifest.get("inputs"), dict)
                   else str(manifest.get("inputs", "")),
                   "version": f"{name}/{version}"}
            rows[(row["model"], row["sort"], row["noise"], row["points"], row["dataset"])] = row
    order = {"graph_transformer": 0, "pointnet": 1}
    return sorted(rows.values(), key=lambda r: (order.get(r["model"], 2), r["points"], r["sort"], r["noise"]))


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

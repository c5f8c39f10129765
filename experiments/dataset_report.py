"""The demonstrations of a run, cell by cell (docs/data.md): episodes, cuts, MPPI's final reward with its 95%
interval, success, and MPPI minus the heuristic on the episodes both ran (topocut.data.report).

    python experiments/dataset_report.py --root outputs [--dataset demos] [--out table.md]
"""
import argparse
from pathlib import Path

from topocut.data.report import cell_table, episodes_of
from topocut.data.store import ArtifactStore


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default="outputs", help="artifact store root (outputs_root)")
    ap.add_argument("--dataset", default="demos", help="the collection whose shards to read (data.dataset)")
    ap.add_argument("--tasks", nargs="*", default=["slice", "stick", "dice"])
    ap.add_argument("--objects", nargs="*", default=["cake", "cube", "ditto", "ham", "potato"])
    ap.add_argument("--out", default=None, help="write the markdown table here (default: print only)")
    args = ap.parse_args(argv)
    episodes = episodes_of(ArtifactStore(Path(args.root)), args.dataset)
    if not episodes:
        raise SystemExit(f"no committed shards of {args.dataset!r} under {args.root!r}; run stage=mppi first")
    table, totals = cell_table(episodes, args.tasks, args.objects)
    text = f"{totals['episodes']} episodes, {totals['cuts']} cuts\n\n{table}\n"
    print(text)
    if args.out:
        Path(args.out).write_text(text)


if __name__ == "__main__":
    main()

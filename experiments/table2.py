"""Paper Table 2 from the artifact store (topocut.models.table2): one row per trained perception checkpoint.

    python experiments/table2.py --root outputs [--out docs/perception_table2.md]
"""
import argparse
from pathlib import Path

from topocut.models.table2 import collect, markdown


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

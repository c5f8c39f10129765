"""One Table 1 from several evaluation artifacts of the same protocol (topocut.eval.combine).

    python experiments/table1.py --out outputs/table1_combined outputs/eval/table1/v001 outputs/eval/table1/v002

Writes results.md (pooled seeds, paired differences, aggregates, the paper's table), results_seeds.md (one row
per training seed), results.csv, results_objects.csv, results.png and sources.json into --out.
"""
import argparse
import sys

from topocut.eval.combine import combine


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sources", nargs="+", help="evaluation artifact directories (eval/<name>/vNNN)")
    ap.add_argument("--out", required=True, help="directory to write the combined table into (replaced)")
    ap.add_argument("--reference", help="policy normalising R̂ (default: the reference of a piece that ran it)")
    ap.add_argument("--normalize-by", choices=("task", "task_split"), help="one reference mean per task or per split")
    ap.add_argument("--compare-to", help="policy of the paired-difference columns (default: the reference)")
    args = ap.parse_args(argv)
    try:
        out = combine(args.sources, args.out, console=True, reference=args.reference,
                      normalize_by=args.normalize_by, compare_to=args.compare_to)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"{len(out['runs'])} runs -> {out['md']}, {out['seeds_md']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

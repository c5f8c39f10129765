"""The additional tasks' figures (docs/tasks.md): pyramid cutting by MPPI and cream writing.  The experiments are
experiments/pyramid_mppi.py and experiments/cream_writing.py; this is their command line.

    python experiments/task_figures.py pyramid --out docs/img/pyramid.png          # ~10 min, figure + .json
    python experiments/task_figures.py writing --out docs/img/cream_writing.png
"""
import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a file: `experiments` from the repository root
from experiments.cream_writing import writing_experiment  # noqa: E402
from experiments.pyramid_mppi import pyramid_experiment  # noqa: E402


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("pyramid", help="MPPI on the pyramid task; figure + JSON of the numbers")
    p.add_argument("--out", default="docs/img/pyramid.png")
    p.add_argument("--n-grid", type=int, default=48)
    p.add_argument("--samples", type=int, default=8)
    p.add_argument("--iterations", type=int, default=6)
    p.add_argument("--size", type=float, default=0.1)
    p.add_argument("--init", type=float, nargs=3, default=(-0.02, 0.35, -0.3), metavar=("OFFSET", "DYAW", "DTILT"))
    p.add_argument("--delta", type=float, default=1.1)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    w = sub.add_parser("writing", help="cream writing: scripted writer vs MPPI over strokes; figure + JSON")
    w.add_argument("--out", default="docs/img/cream_writing.png")
    w.add_argument("--word", default="CORL")
    w.add_argument("--n-grid", type=int, default=48)
    w.add_argument("--samples", type=int, default=4)
    w.add_argument("--iterations", type=int, default=2)
    w.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if args.cmd == "writing":
        res = writing_experiment(args.word, args.n_grid, args.samples, args.iterations, args.seed, args.out)
    else:
        res = pyramid_experiment(args.n_grid, args.samples, args.iterations, args.size, tuple(args.init),
                                 args.delta, args.seed, args.device, args.out)
    print(json.dumps(res, indent=2, default=float))


if __name__ == "__main__":
    main()

"""Run-to-run spread of the evaluation: the same small `stage=eval` N times, each in a fresh process, and the
spread of every episode's final reward R and of every Table-1 cell's mean across the runs.

On the CPU with eval.cpu_threads=1 the runs agree to ~1e-15 (docs/evaluation.md: only the reward's ARPACK start
vector differs between processes); on a GPU Taichi's atomic adds run in a scheduling-dependent order, and this
script measures what that does to the numbers a report prints, next to the report's own bootstrap intervals.

    python benchmarks/eval_spread.py --runs 5 device=cuda                 # scripted policies, smoke-sized eval
    python benchmarks/eval_spread.py --runs 5 --store outputs device=cuda eval.policies=[oracle,pddp]
    python benchmarks/eval_spread.py --runs 3 device=cpu eval.cpu_threads=1   # the CPU check (expect ~0)

Every further argument is a Hydra override of `python -m topocut.run stage=eval` (after the defaults below).
Each run writes its own eval artifact `eval/spread-<stamp>-r<i>` in ``--store`` (a temporary directory by
default; name a store that holds checkpoints to include learned policies).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

DEFAULTS = ["stage=eval", "scale=smoke", "logger=none", "progress=false", "eval.gifs=0",
            "eval.policies=[oracle,heuristic,mppi]", "eval.episodes_per_cell=3"]


def run_once(store: Path, name: str, overrides: list[str], timeout: float) -> tuple[Path, float]:
    env = dict(os.environ, WANDB_MODE="disabled", HYDRA_FULL_ERROR="0")
    cmd = [sys.executable, "-m", "topocut.run", *DEFAULTS, *overrides, f"eval.name={name}", f"outputs_root={store}"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        sys.exit(f"run failed ({proc.returncode}): {' '.join(cmd)}\n{(proc.stdout + proc.stderr)[-4000:]}")
    versions = sorted((store / "eval" / name).glob("v[0-9]*"))
    if not versions:
        sys.exit(f"no eval/{name} version under {store}")
    return versions[-1], time.perf_counter() - t0


def spread(values: np.ndarray) -> dict:
    """Across runs (axis 0): sd (ddof=1), range, and whether every run agrees to the bit."""
    return {"mean": float(values.mean()), "sd": float(values.std(ddof=1)) if len(values) > 1 else math.nan,
            "range": float(values.max() - values.min()), "identical": bool(np.all(values == values[0]))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--store", type=Path, default=None, help="outputs_root for every run (default: a temp dir)")
    ap.add_argument("--json", type=Path, default=None, help="write the numbers here too")
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds per run")
    args, overrides = ap.parse_known_args()
    if args.runs < 2:
        ap.error("--runs must be >= 2")
    from topocut.eval.report import ALL, load_episodes

    store = args.store or Path(tempfile.mkdtemp(prefix="eval_spread-"))
    stamp = time.strftime("%Y%m%d-%H%M%S")
    runs, seconds = [], []
    for i in range(args.runs):
        path, sec = run_once(store, f"spread-{stamp}-r{i}", overrides, args.timeout)
        runs.append(path)
        seconds.append(sec)
        print(f"run {i}: {path} ({sec:.0f} s)", flush=True)

    finals = []  # per run: {(run name, task, object, episode seed): final R}
    for path in runs:
        finals.append({(e["run"], e["spec"]["task"], e["spec"]["object"], e["spec"]["seed"]): e["final_reward"]
                       for e in load_episodes(path)})
    keys = sorted(set.intersection(*(set(f) for f in finals)), key=repr)
    R = np.array([[f[k] for k in keys] for f in finals])  # runs x episodes
    per_episode = {"|".join(map(str, k)): spread(R[:, j]) for j, k in enumerate(keys)}

    # cell means per run, and the first run's bootstrap interval of the same cell for scale
    import csv

    cells = {}
    for path in runs:
        with open(path / "results.csv") as f:
            for r in csv.DictReader(f):
                if r["object"] == ALL and r["split"] != ALL and r["task"] != ALL:
                    cells.setdefault((r["policy"], r["task"], r["split"]), []).append(
                        (float(r["R_mean"]), float(r["R_lo"]), float(r["R_hi"])))
    per_cell = {}
    print(f"\nfinal R across {args.runs} runs, {len(keys)} episodes ({', '.join(overrides) or 'defaults'})")
    print(f"{'cell':34s} {'mean R':>8s} {'run sd':>10s} {'run range':>10s} {'95% CI width':>13s}")
    for key, vals in sorted(cells.items()):
        means = np.array([v[0] for v in vals])
        ci = vals[0][2] - vals[0][1]
        s = spread(means)
        per_cell["|".join(key)] = {**s, "ci_width_run0": ci}
        print(f"{' '.join(key):34s} {s['mean']:8.4f} {s['sd']:10.2e} {s['range']:10.2e} {ci:13.4f}")
    ranges = np.array([v["range"] for v in per_episode.values()])
    identical = sum(v["identical"] for v in per_episode.values())
    print(f"\nper episode: {identical}/{len(keys)} bit-identical across runs; range of final R: "
          f"median {np.median(ranges):.2e}, max {ranges.max():.2e}")
    worst = sorted(per_episode.items(), key=lambda kv: -kv[1]["range"])[:5]
    for k, v in worst:
        if v["range"] > 0:
            print(f"  {k}: R {v['mean']:.4f}, sd {v['sd']:.2e}, range {v['range']:.2e}")
    print(f"seconds per run: {', '.join(f'{s:.0f}' for s in seconds)}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"runs": [str(p) for p in runs], "overrides": DEFAULTS + overrides,
                                         "seconds": seconds, "per_episode": per_episode, "per_cell": per_cell},
                                        indent=2))


if __name__ == "__main__":
    main()

"""MPPI demonstrations from several processes sharing one GPU (Hydra's joblib launcher) against one process.

    python benchmarks/demo_processes.py --device cuda --jobs 4 --episodes 4
    python benchmarks/demo_processes.py --device cpu --n-grid 32 --K 4 --jobs 2 --episodes 1   # smoke

One demonstration process leaves the GPU idle most of the time (its host work: the split of pieces, topology
discovery launches, the planner's Python), so the way to more demonstrations per hour on one GPU is more
processes, each with its own cells: exactly a Hydra multirun over objects on the joblib launcher, which
``stage=all`` and ``make data-sweep`` already express.  This script times

1. the reference: one ``stage=mppi`` process, one object, ``--episodes`` episodes;
2. ``--jobs`` processes at once: ``-m stage=mppi seed=1,..,jobs hydra/launcher=joblib`` (one shard per seed, the
   same object and episodes per process),

each as a fresh command (Taichi's and Warp's kernel caches are warmed by a first, untimed run), and prints the
cuts per second of each over the command's wall time (process start-up and compilation from the warm caches
included: a real run pays those once per job) and inside the episodes (the episode records' time_s: what 1,000
episodes cost once the processes run), their ratios, and the projection to 1,000 episodes.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def stage_args(args, root: Path) -> list[str]:
    return [f"task={args.task}", f"device={args.device}", f"sim.n_grid={args.n_grid}", f"sim.batch_size={args.K}",
            f"planner.num_samples={args.K}", f"planner.iterations={args.iters}", "planner.horizon=1",
            "reward=torch", f"data.episodes={args.episodes}", "task.max_cuts=5",
            f"stage.run.compare_heuristic={str(args.compare_heuristic).lower()}",
            "logger=none", "progress=false", f"outputs_root={root}", *args.set]


def run(cmd: list[str], root: Path) -> tuple[float, int, int, float, float, dict]:
    """Wall seconds of ``cmd``; the cuts and episodes its mppi runs wrote (their status.json files); their
    in-episode and steady rates; and where a process's wall time went, averaged over the processes (start-up: from
    the launch to its first episode; the first episode; the later episodes; their heuristic comparisons; the rest)."""
    launched, t0 = time.time(), time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "WANDB_MODE": "disabled"})
    wall = time.perf_counter() - t0
    if proc.returncode:
        sys.exit(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    cuts = episodes = 0
    inside = 0.0  # cuts per second inside the episodes (their time_s: planning and cutting, no start-up), summed
    steady = 0.0  # the same without each process's first episode (where Taichi and Warp compile at first use)
    # start-up: launch to the first episode; first episode: its heuristic comparison and itself (first-use
    # compilation lands there); then the later episodes and their comparisons; the rest: writes, the end
    split = {"start-up": [], "first episode": [], "episodes": [], "heuristic": [], "rest": []}
    for f in root.rglob("status.json"):
        s = json.loads(f.read_text())
        if s.get("stage") == "mppi" and s.get("status") == "ok":
            cuts += int(s["summary"]["cuts"])
            episodes += int(s["summary"]["episodes"])
            dataset = Path(s["summary"]["dataset"])
            recs = [json.loads(line) for line in (dataset / "episodes.jsonl").read_text().splitlines() if line]
            inside += sum(r["num_cuts"] for r in recs) / max(sum(r.get("time_s", 0.0) for r in recs), 1e-9)
            later = recs[1:] or recs
            steady += sum(r["num_cuts"] for r in later) / max(sum(r.get("time_s", 0.0) for r in later), 1e-9)
            if all("started" in r for r in recs):
                first = min(recs, key=lambda r: r["started"])
                others = [r for r in recs if r is not first]
                parts = (first["started"] - launched, first.get("time_s", 0.0) + first.get("heuristic_time_s", 0.0),
                         sum(r.get("time_s", 0.0) for r in others), sum(r.get("heuristic_time_s", 0.0) for r in others))
                for k, v in zip(split, (*parts, wall - sum(parts))):
                    split[k].append(v)
    return wall, cuts, episodes, inside, steady, {k: sum(v) / len(v) for k, v in split.items() if v}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cuda", choices=["cpu", "cuda"])
    ap.add_argument("--jobs", type=int, default=4)
    ap.add_argument("--episodes", type=int, default=4)
    ap.add_argument("--task", default="slice")
    ap.add_argument("--object", default="cake")
    ap.add_argument("--n-grid", type=int, default=64)
    ap.add_argument("--K", type=int, default=16)
    ap.add_argument("--iters", type=int, default=2)
    ap.add_argument("--compare-heuristic", action="store_true",
                    help="run the stage's heuristic comparison beside every episode, as make paper does")
    ap.add_argument("--set", nargs="*", default=[], help="more overrides for every run")
    args = ap.parse_args()
    py = [sys.executable, "-m", "topocut.run"]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        warm = tmp / "warm"  # compile once: every later process loads Taichi's and Warp's caches
        run([*py, "stage=mppi", "object=cube", *stage_args(args, warm), "data.episodes=1"], warm)
        one = tmp / "one"
        w1, c1, e1, i1, s1, p1 = run([*py, "stage=mppi", f"object={args.object}", *stage_args(args, one)], one)
        many = tmp / "many"
        seeds = ",".join(str(i) for i in range(1, args.jobs + 1))  # one shard per seed: every job cuts the same object
        wj, cj, ej, ij, sj, pj = run([*py, "-m", "stage=mppi", f"object={args.object}", f"seed={seeds}", "hydra/launcher=joblib",
                              f"hydra.launcher.n_jobs={args.jobs}", *stage_args(args, many)], many)
    r1, rj = c1 / w1, cj / wj
    print(f"{args.device}, {args.n_grid}^3, K={args.K}, {args.iters} iterations, task {args.task}, "
          f"{args.episodes} episodes per process; cuts/s over the command's wall time (start-up included) and "
          f"inside the episodes (summed over processes), and inside all but each process's first episode (steady)")
    print(f"  1 process:       {e1:3d} episodes, {c1:4d} cuts in {w1:7.1f} s: {r1:6.3f} cuts/s wall, "
          f"{i1:6.3f} in episodes, {s1:6.3f} steady ({1 / s1:.2f} s a cut)")
    print(f"  {args.jobs} processes (joblib): {ej:3d} episodes, {cj:4d} cuts in {wj:7.1f} s: {rj:6.3f} cuts/s wall "
          f"({rj / r1:.2f}x the one process), {ij:6.3f} in episodes ({ij / i1:.2f}x), {sj:6.3f} steady "
          f"({sj / s1:.2f}x; {args.jobs / sj:.2f} s a cut in each process)")
    for name, parts in (("1 process", p1), (f"{args.jobs} processes", pj)):
        if parts:
            print(f"  where a process's wall time went ({name}, mean): "
                  + ", ".join(f"{k} {v:.1f} s" for k, v in parts.items()))
    per_ep = cj / max(ej, 1)
    for name, r in (("1 process", s1), (f"{args.jobs} processes", sj)):
        print(f"  1,000 episodes ({per_ep:.2f} cuts each) at the steady rate of {name}: "
              f"{1000 * per_ep / r / 60:6.1f} min; of 5 cuts each: {5000 / r / 60:6.1f} min")


if __name__ == "__main__":
    main()

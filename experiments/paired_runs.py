"""Two evaluation runs of one policy on the same episodes, paired: did a setting change what the policy achieves?

    python experiments/paired_runs.py A B --policy mppi [--moved 0.05]

A and B are evaluation artifacts (`outputs/eval/<name>/vNNN`) or the tarballs of their `episodes/` folder that
`benchmarks/gpu.sh mppi-check` brings back (`<NAME>.tgz`).  Episodes are paired by spec (task, object, seed: the
same scene; read by the evaluation's own loader).  Per task and over all: the mean final raw R of each run, the paired
difference B - A with its 95% percentile-bootstrap interval (topocut.eval.stats, 10,000 resamples), the successes,
and the mean time the policy took to act in an episode; then every episode whose R moved by more than --moved.
docs/data.md "The rollout's last push" was made with it.
"""
from __future__ import annotations

import argparse
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np

from topocut.eval.stats import bootstrap_mean, paired_difference
from topocut.eval.summary import load_episodes


def episodes(source: str, policy: str, scratch: Path) -> dict[str, dict]:
    """{spec name (task_object_seed): episode} of run ``policy`` in an artifact folder or an episodes tarball, read
    by the evaluation's own loader (topocut.eval.summary.load_episodes)."""
    path = Path(source)
    if path.is_file():
        out = scratch / path.name.replace(".", "_")
        with tarfile.open(path) as tar:
            tar.extractall(out, filter="data")
        path = out
    mine = [e for e in load_episodes(path) if e["run"] == policy]
    if not mine:
        raise ValueError(f"{source}: no episodes/{policy}/*.json (an eval artifact or its episodes tarball)")
    return {f"{e['spec']['task']}_{e['spec']['object']}_{int(e['spec']['seed']):03d}": e for e in mine}


def table(a: dict, b: dict, names: tuple[str, str]) -> list[str]:
    keys = sorted(set(a) & set(b))
    tasks = sorted({a[k]["spec"]["task"] for k in keys})
    rows = [f"| task | n | R {names[0]} | R {names[1]} | ΔR (B − A) [95%] | successes A / B | act s A → B |",
            "|---|---|---|---|---|---|---|"]
    for task in [*tasks, None]:
        ks = [k for k in keys if task is None or a[k]["spec"]["task"] == task]
        ra = {k: float(a[k]["final_reward"]) for k in ks}
        rb = {k: float(b[k]["final_reward"]) for k in ks}
        d = paired_difference(rb, ra, label=f"paired {task}")
        act = [float(np.mean([sum(e[k]["act_time_s"]) for k in ks])) for e in (a, b)]
        rows.append(f"| {task or 'all'} | {len(ks)} | {bootstrap_mean(list(ra.values())).mean:.3f} | "
                    f"{bootstrap_mean(list(rb.values())).mean:.3f} | {d.mean:+.3f} [{d.lo:+.3f}, {d.hi:+.3f}] | "
                    f"{sum(bool(a[k]['success']) for k in ks)} / {sum(bool(b[k]['success']) for k in ks)} | "
                    f"{act[0]:.1f} → {act[1]:.1f} |")
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a", help="the reference run: an eval artifact folder or its episodes tarball")
    ap.add_argument("b", help="the run compared with it")
    ap.add_argument("--policy", default="mppi", help="the policy (run name) under episodes/")
    ap.add_argument("--moved", type=float, default=0.05, help="list the episodes whose R moved by more than this")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        try:
            a, b = (episodes(s, args.policy, Path(tmp)) for s in (args.a, args.b))
        except (ValueError, OSError, tarfile.TarError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
    if not set(a) & set(b):
        print(f"error: {args.a} and {args.b} share no episode of {args.policy}", file=sys.stderr)
        return 2
    print("\n".join(table(a, b, ("A", "B"))))
    moved = [(k, a[k]["final_reward"], b[k]["final_reward"]) for k in sorted(set(a) & set(b))
             if abs(b[k]["final_reward"] - a[k]["final_reward"]) > args.moved]
    print(f"\n{len(moved)} episodes moved by more than {args.moved}:" + "".join(
        f"\n  {k}: {ra:.3f} → {rb:.3f}" for k, ra, rb in moved))
    return 0


if __name__ == "__main__":
    sys.exit(main())

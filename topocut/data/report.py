"""What a demonstration collection holds, cell by cell: the table docs/data.md publishes for a paper-scale run.

Reads the shards of ``dataset`` (stage=mppi's per-run ``episodes.jsonl`` beside each committed version: one line per
episode with its final reward, its cuts and, where ``data.heuristic_every`` ran it, the heuristic's final reward on
the same scene) and reports per (task, object): episodes, cuts, MPPI's mean final reward with its 95% bootstrap
interval (``topocut.eval.stats``), the success rate, and MPPI minus the heuristic paired on the episodes both ran.
"""
from __future__ import annotations

from pathlib import Path

from topocut.data.collection import read_records, shards_of
from topocut.eval.report import format_difference, format_interval
from topocut.eval.stats import bootstrap_mean, paired_difference


def episodes_of(store, dataset: str) -> list[dict]:
    """Every committed episode of ``dataset``'s shards (their latest versions), with the shard's task and object,
    shard by shard in name order."""
    out = []
    for name, path in sorted(shards_of(store, dataset).items()):
        config = store.manifest(path)["config"]
        task, obj = config["task"]["name"], config["object"]["name"]
        # one record per episode, the last written: an episode re-run after a crash between its log line and its
        # commit (or a snapshot taken between the two) is logged twice
        out.extend({"task": task, "object": obj, "shard": name, **r}
                   for r in read_records(Path(path) / "episodes.jsonl"))
    return out


def cell_table(episodes: list[dict], tasks=None, objects=None) -> tuple[str, dict]:
    """(markdown table, totals) of ``episodes`` per (task, object); rows in ``tasks`` x ``objects`` order (default:
    as first seen), then one row per task over its objects and one over everything."""
    tasks = list(tasks or dict.fromkeys(e["task"] for e in episodes))
    objects = list(objects or dict.fromkeys(e["object"] for e in episodes))
    rows = ["| task | object | episodes | cuts | MPPI final reward [95% CI] | success | "
            "MPPI − heuristic (paired, n) |", "|---|---|---|---|---|---|---|"]

    def row(task: str, obj: str, eps: list[dict]) -> None:
        if not eps:
            return
        label = f"{task}/{obj}"
        reward = bootstrap_mean([e["final_reward"] for e in eps], label=label)
        paired = [e for e in eps if e.get("heuristic_final_reward") is not None]
        diff = paired_difference({i: e["final_reward"] for i, e in enumerate(paired)},
                                 {i: e["heuristic_final_reward"] for i, e in enumerate(paired)}, label=label + "/h")
        success = sum(bool(e.get("success")) for e in eps) / len(eps)
        rows.append(f"| {task} | {obj} | {len(eps)} | {sum(int(e['num_cuts']) for e in eps)} | "
                    f"{format_interval((reward.mean, reward.lo, reward.hi))} | {success:.2f} | "
                    f"{format_difference(diff.mean, diff.lo, diff.hi, diff.tie)} ({len(paired)}) |")

    for task in tasks:
        for obj in objects:
            row(task, obj, [e for e in episodes if e["task"] == task and e["object"] == obj])
    for task in tasks:
        row(task, "all", [e for e in episodes if e["task"] == task])
    row("all", "all", episodes)
    totals = {"episodes": len(episodes), "cuts": sum(int(e["num_cuts"]) for e in episodes)}
    return "\n".join(rows), totals

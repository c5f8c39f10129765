"""topocut.data.report: the per-cell table of a demonstration collection, from its shards' episode logs."""
from __future__ import annotations

import json

import numpy as np

from topocut.data.report import cell_table, episodes_of
from topocut.data.store import ArtifactStore


def _shard(store, task, obj, first, rewards, heuristic):
    config = {"task": {"name": task}, "object": {"name": obj}, **({"first_episode": first} if first else {})}
    w, _ = store.begin("dataset", f"demos-{task}-{obj}-e{first}", config, extra={"shard_of": "demos"})
    lines = [{"episode": first + i, "final_reward": r, "num_cuts": 2 + i % 3, "success": r >= 0.95,
              **({"heuristic_final_reward": heuristic[i]} if heuristic[i] is not None else {})}
             for i, r in enumerate(rewards)]
    # the last episode logged twice (re-run after a crash before its commit): counted once, the last record
    (w.path / "episodes.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines[:-1] + [
        {**lines[-1], "final_reward": 0.5}] + lines[-1:]))
    w.commit()


def test_cells_count_every_committed_episode_and_pair_only_the_compared_ones(tmp_path):
    store = ArtifactStore(tmp_path)
    _shard(store, "slice", "cake", 0, [0.96, 0.5, 0.7], [0.9, None, None])
    _shard(store, "slice", "cake", 3, [0.99, 0.3], [None, 0.4])
    _shard(store, "dice", "ham", 0, [0.1, 0.2], [0.3, 0.0])
    w, _ = store.begin("dataset", "demos-dice-ham-e9", {"x": 1}, extra={"shard_of": "demos"})  # never committed
    (w.path / "episodes.jsonl").write_text(json.dumps({"final_reward": 1.0, "num_cuts": 9}) + "\n")

    episodes = episodes_of(store, "demos")
    assert len(episodes) == 7 and {e["task"] for e in episodes} == {"slice", "dice"}
    table, totals = cell_table(episodes, ["slice", "dice"], ["cake", "ham"])
    assert totals == {"episodes": 7, "cuts": 2 + 3 + 4 + 2 + 3 + 2 + 3}
    rows = {tuple(c.strip() for c in line.split("|")[1:3]): [c.strip() for c in line.split("|")[3:-1]]
            for line in table.splitlines()[2:]}
    assert list(rows) == [("slice", "cake"), ("dice", "ham"), ("slice", "all"), ("dice", "all"), ("all", "all")]
    slice_cake = rows[("slice", "cake")]
    assert slice_cake[:2] == ["5", "14"]
    mean = np.mean([0.96, 0.5, 0.7, 0.99, 0.3])
    assert slice_cake[2].startswith(f"{mean:.2f} [")
    lo, hi = (float(v) for v in slice_cake[2].split("[")[1].rstrip("]").split(","))
    assert 0.3 <= lo < mean < hi <= 0.99
    assert slice_cake[3] == f"{2 / 5:.2f}"  # 0.96 and 0.99 reach 0.95
    # paired on the two episodes the heuristic ran beside: (0.96 - 0.9, 0.3 - 0.4); Table 1's difference format,
    # "≈" where the interval holds 0
    assert slice_cake[4].startswith(f"≈ {np.mean([0.06, -0.1]):+.2f} [") and slice_cake[4].endswith("(2)")
    assert rows[("dice", "ham")][4].startswith(f"≈ {np.mean([-0.2, 0.2]):+.2f}")
    assert rows[("all", "all")][:2] == ["7", str(totals["cuts"])]

"""stage=all with data.episodes_per_job, for real at a tiny CPU scale: a cell written as parts and merged holds
the episodes one stage=mppi run of the cell writes (same seeds, poses and episode indices), and the parts share
one simulator.  In-process (data.jobs=1), so the run's env cache and this test see the same process."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir

from topocut.data.episodes import EpisodeDataset

# as tests/test_stages.py's FAST (a coarse grid, 2 MPPI samples, short knife / push / settle phases), with the
# heuristic comparison on every 2nd episode (data.heuristic_every: stage=all passes no stage.run.* key on)
FAST = ["logger=none", "progress=false", "device=cpu", "sim.n_grid=20", "sim.cut_substeps=40",
        "sim.dwell_time=0.0005", "sim.push_time=0.002", "sim.settle_time=0.002", "sim.batch_size=2",
        "planner.num_samples=2", "planner.horizon=1", "planner.iterations=1", "task.max_cuts=2",
        "data.points_per_step=128", "topology.resolution=32",
        "task=slice", "object=cube", "seed=3", "data.episodes=3", "data.heuristic_every=2"]


def _run(root, *overrides):
    from pipelines.all import CONF_DIR
    from topocut.config import register_configs
    from topocut.run import run_stage

    register_configs()
    overrides = [*FAST, f"outputs_root={root}", *overrides]
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides)
        return run_stage(cfg, root / "runs" / cfg.stage.name, overrides)


def _episodes(path):
    ds = EpisodeDataset(path / "data.zarr")
    return [(m["task"], m["object"], m["seed"], json.dumps(m["pose"], sort_keys=True, default=str))
            for m in (ds.meta(e) for e in range(ds.num_episodes))]


def test_a_cell_in_parts_merges_into_the_episodes_of_one_run(tmp_path, monkeypatch):
    import topocut.sim
    from topocut.data.collection import read_records
    from topocut.episode import demo_episode_seed as episode_seed
    from topocut.sim import env as simenv

    built = []

    class Counted(topocut.sim.CuttingEnv):
        def __init__(self, *args, **kwargs):
            built.append(self)
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(topocut.sim, "CuttingEnv", Counted)
    simenv.release_env()  # whatever an earlier test of this process left
    try:
        parts = _run(tmp_path, "stage=all", "stage.run.sequence=[mppi]", "data.episodes_per_job=2",
                     "data.dataset=parts")
        whole = _run(tmp_path, "stage=mppi", "data.dataset=whole")
    finally:
        simenv.release_env()
    assert len(built) == 1  # the second part and the unsplit run reused the first part's simulator
    labels = list(parts["wall_s"])
    assert labels == ["mppi-slice-cube-e0-1", "mppi-slice-cube-e2-2", "merge"]
    shards = [parts[k]["dataset"] for k in labels[:2]]
    assert [parts[k]["episodes"] for k in labels[:2]] == [2, 1] and parts["mppi-slice-cube-e2-2"]["first_episode"] == 2
    merged = parts["merge"]
    assert merged["shards"] == 2 and merged["episodes"] == whole["episodes"] == 3
    expected = _episodes(Path(whole["dataset"]))
    assert [s for _, _, s, _ in expected] == [episode_seed(3, e) for e in range(3)]
    assert _episodes(Path(merged["dataset"])) == expected  # same episodes, same order
    a, b = (EpisodeDataset(Path(d) / "data.zarr") for d in (merged["dataset"], whole["dataset"]))
    assert len(a) == len(b)  # and, Taichi single-threaded on the CPU (conftest), the same cuts bit for bit
    assert all(np.array_equal(a[i]["action"], b[i]["action"]) and a[i]["reward"] == b[i]["reward"]
               for i in range(len(a)))
    # the parts' logs number the episodes as the whole run's does
    records = [r for s in shards for r in read_records(Path(s) / "episodes.jsonl")]
    whole_records = read_records(Path(whole["dataset"]) / "episodes.jsonl")
    assert [(r["episode"], r["seed"]) for r in records] == [(r["episode"], r["seed"]) for r in whole_records]
    # the heuristic ran beside episodes 0 and 2 (every 2nd by index), in the parts as in the whole run
    for recs in (records, whole_records):
        assert [r["episode"] for r in recs if "heuristic_final_reward" in r] == [0, 2]

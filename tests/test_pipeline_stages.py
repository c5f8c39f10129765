"""The Hydra stages as a user runs them: a multirun sweep merged into one dataset, a killed run that
resumes, reuse of a finished version, and refusal of a tampered input."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from topocut.data.episodes import EpisodeDataset
from topocut.data.store import ArtifactStore

ROOT = Path(__file__).resolve().parents[1]
TINY = ["logger=none", "progress=false", "sim.n_grid=32", "sim.batch_size=2", "planner.num_samples=2",
        "planner.horizon=1", "planner.iterations=1", "task.max_cuts=1", "data.points_per_step=256",
        "topology.resolution=48", "object.randomize_pose=false"]
MPPI = ["stage=mppi", "+stage.run.compare_heuristic=false"]


def topocut(out, *args, multirun=False, check=True, popen=False):
    cmd = [sys.executable, "-m", "topocut.run", *(["-m"] if multirun else []), f"outputs_root={out}", *TINY, *args]
    env = dict(os.environ, WANDB_MODE="disabled", HYDRA_FULL_ERROR="0")
    if popen:
        return subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                start_new_session=True)
    r = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    if check:
        assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    return r


def test_sweep_of_two_tasks_and_two_objects_merges_into_one_dataset(tmp_path):
    # a stick needs two cuts (slab, then width)
    topocut(tmp_path, *MPPI, "task=slice,stick", "object=cube,cake", "data.episodes=1", "task.max_cuts=2",
            multirun=True)
    store = ArtifactStore(tmp_path)
    shards = sorted(n for n in store.names("dataset") if n.startswith("demos-"))
    assert shards == ["demos-slice-cake-s0", "demos-slice-cube-s0", "demos-stick-cake-s0", "demos-stick-cube-s0"]
    topocut(tmp_path, "stage=merge")
    merged = store.resolve("dataset", "demos")
    manifest = json.loads((merged / "manifest.json").read_text())
    assert sorted(manifest["inputs"]) == shards
    assert all(v.endswith(":v001") for v in manifest["inputs"].values())
    ds = EpisodeDataset(merged / "data.zarr")
    per_shard = [EpisodeDataset(store.resolve("dataset", n) / "data.zarr").num_episodes for n in shards]
    assert ds.num_episodes == sum(per_shard) == 4
    pairs = sorted((ds.meta(e)["task"], ds.meta(e)["object"]) for e in range(ds.num_episodes))
    assert pairs == [("slice", "cake"), ("slice", "cube"), ("stick", "cake"), ("stick", "cube")]


@pytest.fixture(scope="module")
def killed_and_resumed(tmp_path_factory):
    """stage=mppi with 3 episodes, killed once the first episode is committed, then run again."""
    out = tmp_path_factory.mktemp("resume")
    proc = topocut(out, *MPPI, "task=slice", "object=cube", "data.episodes=3", popen=True)
    first, deadline = None, time.time() + 300
    try:
        while time.time() < deadline and proc.poll() is None:
            for z in out.glob("dataset/demos/.partial-*/data.zarr"):
                try:
                    ds = EpisodeDataset(z)
                    if ds.num_episodes >= 1:
                        first = (ds.num_episodes, ds[0]["x_t"].copy(), ds.meta(0)["seed"])
                except Exception:  # noqa: BLE001 - the buffer may be mid-write
                    pass
            if first is not None:
                break
            time.sleep(0.3)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert first is not None, "no episode was committed before the deadline"
    committed_before_kill = ArtifactStore(out).versions("dataset", "demos")
    topocut(out, *MPPI, "task=slice", "object=cube", "data.episodes=3")
    return out, first, committed_before_kill


def test_killed_run_resumes_without_losing_or_duplicating(killed_and_resumed):
    out, (n_seen, x0, seed0), committed_before_kill = killed_and_resumed
    assert committed_before_kill == []  # the kill came before the version was committed
    store = ArtifactStore(out)
    assert store.versions("dataset", "demos") == ["v001"]
    ds = EpisodeDataset(store.resolve("dataset", "demos") / "data.zarr")
    seeds = [ds.meta(e)["seed"] for e in range(ds.num_episodes)]
    assert ds.num_episodes == 3 and sorted(seeds) == [0, 1, 2]  # episode_seed(0, e) = e: none lost, none twice
    assert ds.meta(0)["seed"] == seed0 and (ds[0]["x_t"] == x0).all()  # committed data kept byte for byte


def test_finished_stage_is_reused_not_redone(killed_and_resumed):
    out = killed_and_resumed[0]
    r = topocut(out, *MPPI, "task=slice", "object=cube", "data.episodes=3")
    assert "reused" in r.stdout + r.stderr
    assert ArtifactStore(out).versions("dataset", "demos") == ["v001"]


def test_tampered_dataset_is_refused_downstream(killed_and_resumed, tmp_path):
    import shutil

    src = killed_and_resumed[0]
    out = tmp_path / "tampered"
    shutil.copytree(src, out)
    version = out / "dataset" / "demos" / "v001"
    victim = sorted(json.loads((version / "manifest.json").read_text())["files"])[0]
    with open(version / victim, "r+b") as f:
        byte = f.read(1)
        f.seek(0)
        f.write(bytes([byte[0] ^ 0xFF]) if byte else b"x")
    r = topocut(out, "stage=pretrain", "trainer.max_epochs=1", check=False)
    assert r.returncode != 0
    text = r.stdout + r.stderr
    assert "sha256" in text and Path(victim).name in text


def test_bad_choices_fail_before_simulating(tmp_path):
    r = topocut(tmp_path, *MPPI, "object=carrot", check=False)
    assert r.returncode != 0 and "cake" in r.stdout + r.stderr and not (tmp_path / "dataset").exists()
    r = topocut(tmp_path, *MPPI, "sim.dt=0.05", check=False)
    assert r.returncode != 0 and "sim.dt" in r.stdout + r.stderr and not (tmp_path / "dataset").exists()

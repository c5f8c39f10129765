"""Zarr episode buffer: round trip, cut masks, FPS downsampling, crash safety, resume and merge."""
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from topocut.data.episodes import EpisodeDataset, EpisodeWriter, merge
from topocut.sim.action import KnifeAction

KEYS = {"x_t", "f_t", "mask", "x_t1", "f_t1", "action", "pose", "history", "goal", "goal_labels", "reward",
        "success", "episode", "step", "task", "object"}


def make_episode(n_steps, n_points, seed, task="slice", obj="cube"):
    """Random clouds; labels = which side of x = 0.5; each step moves the +x half by +0.01."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.3, 0.7, (n_points, 3)).astype(np.float32)
    steps = []
    for t in range(n_steps):
        a = KnifeAction(0.4 + 0.05 * t, 0.5)  # yaw = tilt = 0: normal +x, mask = x > a.x
        x1 = x + (np.where(x[:, :1] > a.x, 0.01, 0.0) * [1, 0, 0]).astype(np.float32)
        steps.append({"x_t": x, "f_t": (x[:, 0] > 0.5).astype(np.int32), "x_t1": x1,
                      "f_t1": (x1[:, 0] > 0.5).astype(np.int32) + t, "action": a, "pose": a.to_matrix(),
                      "history": np.full((3, 7), t, np.float32), "reward": 0.1 * t, "success": t == n_steps - 1})
        x = x1
    goal = rng.uniform(0.3, 0.7, (40, 3)).astype(np.float32)
    meta = {"task": task, "object": obj, "seed": seed, "goal": goal, "goal_labels": np.arange(40) % 3,
            "pose": {"x": 0.5, "y": 0.5, "yaw": 0.0, "scale": 1.0}, "task_params": {"thickness": 0.03}}
    return steps, meta


def test_round_trip_keys_dtypes_values_and_mask(tmp_path):
    w = EpisodeWriter(tmp_path / "d.zarr", points_per_step=64)
    eps = [make_episode(3, 50, seed=1), make_episode(2, 30, seed=2, task="dice", obj="cake")]
    for steps, meta in eps:
        w.add_episode(steps, meta)
    assert w.num_episodes == 2 and w.committed_keys() == {("slice", "cube", 1), ("dice", "cake", 2)}
    for ds in (EpisodeDataset(tmp_path / "d.zarr"), EpisodeDataset(tmp_path / "d.zarr", in_memory=True)):
        assert len(ds) == 5 and ds.num_episodes == 2
        for i, (e, t) in enumerate([(0, 0), (0, 1), (0, 2), (1, 0), (1, 1)]):
            item, (steps, meta) = ds[i], eps[e]
            s = steps[t]
            assert set(item) == KEYS
            assert item["x_t"].dtype == np.float32 and item["f_t"].dtype == np.int32 and item["mask"].dtype == np.uint8
            assert item["action"].shape == (4,) and item["pose"].shape == (4, 4) and item["history"].shape == (3, 7)
            np.testing.assert_array_equal(item["x_t"], s["x_t"])  # fewer points than points_per_step: all kept
            np.testing.assert_array_equal(item["x_t1"], s["x_t1"])
            np.testing.assert_array_equal(item["f_t1"], s["f_t1"])
            np.testing.assert_array_equal(item["mask"], (s["x_t"][:, 0] > s["action"].x).astype(np.uint8))
            np.testing.assert_allclose(item["action"], [s["action"].x, 0.5, 0, 0])
            np.testing.assert_array_equal(item["goal"], meta["goal"])
            np.testing.assert_array_equal(item["goal_labels"], np.arange(40) % 3)
            assert np.isclose(item["reward"], 0.1 * t) and item["success"] == (t == len(steps) - 1)
            assert (item["episode"], item["step"], item["task"], item["object"]) == (e, t, meta["task"], meta["object"])
        assert ds.meta(1)["task_params"] == {"thickness": 0.03} and ds.meta(1)["status"] == "ok"
        assert len(ds.episode(1)) == 2 and ds[-1]["step"] == 1


def test_missing_keys_are_named(tmp_path):
    steps, meta = make_episode(1, 10, seed=0)
    del steps[0]["history"]
    with pytest.raises(KeyError, match="history"):
        EpisodeWriter(tmp_path / "d.zarr").add_episode(steps, meta)
    steps, meta = make_episode(1, 10, seed=0)
    del meta["goal"]
    with pytest.raises(KeyError, match="goal"):
        EpisodeWriter(tmp_path / "e.zarr").add_episode(steps, meta)


def test_fps_downsampling_keeps_same_points_for_t_and_t1(tmp_path):
    pytest.importorskip("topocut.metrics", reason="topocut.metrics.fps not written yet")
    steps, meta = make_episode(2, 3000, seed=3)
    w = EpisodeWriter(tmp_path / "d.zarr", points_per_step=256)
    w.add_episode(steps, meta)
    ds = EpisodeDataset(tmp_path / "d.zarr")
    for t in range(2):
        item, a = ds[t], steps[t]["action"]
        assert len(item["x_t"]) == 256 and len(item["goal"]) == 40
        # x_t1 is the same particles: displaced by exactly the step's rule
        np.testing.assert_allclose(item["x_t1"] - item["x_t"],
                                   np.where(item["x_t"][:, :1] > a.x, 0.01, 0.0) * [1, 0, 0], atol=1e-6)
        np.testing.assert_array_equal(item["f_t"], item["x_t"][:, 0] > 0.5)
        np.testing.assert_array_equal(item["mask"], item["x_t"][:, 0] > a.x)
        # FPS spreads points: min pairwise spacing far above that of a random subset of the same size
        d = np.linalg.norm(item["x_t"][:, None] - item["x_t"][None], axis=-1) + np.eye(256)
        assert d.min() > 0.01


KILL = textwrap.dedent("""
    import os, sys
    import numpy as np
    import zarr
    from test_episodes import make_episode
    from topocut.data.episodes import EpisodeWriter
    w = EpisodeWriter({path!r}, points_per_step=64)
    w.add_episode(*make_episode(2, 40, seed=0))
    where = {where!r}
    orig_append = zarr.Array.append
    def append(self, data, axis=0):
        if self.path.endswith("episode_ends"):
            if where == "after_resize":
                self.resize((self.shape[0] + 1,))  # episode_ends grown (reads -1), its value never written
            os._exit(3)  # before_commit: everything of episode 1 is written except its commit record
        return orig_append(self, data, axis=axis)
    zarr.Array.append = append
    w.add_episode(*make_episode(3, 40, seed=1))
""")


@pytest.mark.parametrize("where", ["before_commit", "after_resize"])
def test_killed_writer_loses_nothing_committed_and_duplicates_nothing(tmp_path, where):
    path = str(tmp_path / "d.zarr")
    import os

    script = KILL.format(path=path, where=where)  # run from tests/ so that make_episode is importable
    rc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=os.path.dirname(__file__))
    assert rc.returncode == 3, rc.stderr
    ds = EpisodeDataset(path)
    assert ds.num_episodes == 1 and len(ds) == 2  # the reader sees only the committed episode
    w = EpisodeWriter(path, points_per_step=64)  # truncates the uncommitted tail
    assert w.num_episodes == 1 and w.committed_keys() == {("slice", "cube", 0)}
    steps, meta = make_episode(3, 30, seed=5)  # different data than the lost episode: stale arrays would show
    w.add_episode(steps, meta)
    ds = EpisodeDataset(path)
    assert ds.num_episodes == 2 and len(ds) == 5
    for t in range(3):
        np.testing.assert_array_equal(ds[2 + t]["x_t"], steps[t]["x_t"])
        assert ds[2 + t]["episode"] == 1 and ds[2 + t]["step"] == t
    np.testing.assert_array_equal(ds[4]["goal"], meta["goal"])


def test_merge_renumbers_and_resumes(tmp_path):
    shards = []
    for i, (n_eps, seed0) in enumerate([(2, 10), (1, 20)]):
        w = EpisodeWriter(tmp_path / f"s{i}.zarr", points_per_step=64)
        for k in range(n_eps):
            w.add_episode(*make_episode(2 + k, 20 + 5 * k, seed=seed0 + k))
        shards.append(tmp_path / f"s{i}.zarr")
    out = tmp_path / "merged.zarr"
    listed = merge(shards, out, points_per_step=64)
    assert listed == [str(s) for s in shards]
    merge(shards, out, points_per_step=64)  # a second (resumed) merge copies nothing twice
    ds = EpisodeDataset(out)
    assert ds.num_episodes == 3 and len(ds) == 2 + 3 + 2
    src = [(EpisodeDataset(shards[0]), 0), (EpisodeDataset(shards[0]), 1), (EpisodeDataset(shards[1]), 0)]
    for e, (sd, se) in enumerate(src):
        a, b = ds.episode(e), sd.episode(se)
        assert len(a) == len(b) and ds.meta(e)["seed"] == sd.meta(se)["seed"]
        assert ds.meta(e)["source"] == {"shard": str(shards[0] if e < 2 else shards[1]), "episode": se}
        for sa, sb in zip(a, b):
            assert sa["episode"] == e
            for k in ("x_t", "f_t", "mask", "x_t1", "f_t1", "action", "goal", "goal_labels", "reward", "step"):
                np.testing.assert_array_equal(sa[k], sb[k])

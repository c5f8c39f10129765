"""Issue #32: the artifact store and the config refuse what they cannot trust.

One test (or a few) per item of the issue.  CLI items run ``python -m topocut.run`` as a subprocess on a tmp
``outputs_root``; datasets they read are written in-process (a few fake steps through EpisodeWriter), so only
the divergence test simulates anything.
"""
from __future__ import annotations

import errno
import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from tests.stage_runner import run as run_stage
from topocut.data import store as st  # st.InvalidName, st.UnsupportedSchema: looked up in the tests that use them
from topocut.data.episodes import EpisodeDataset, EpisodeWriter
from topocut.data.store import ArtifactStore, CorruptArtifact

REPO = Path(__file__).resolve().parents[1]


def _env(root: Path) -> dict:
    env = dict(os.environ, WANDB_MODE="disabled", TOPOCUT_OUTPUTS=str(root), HYDRA_FULL_ERROR="0")
    env.pop("CUDA_VISIBLE_DEVICES", None)
    return env


def topocut(root: Path, *overrides: str, timeout: float = 120) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "topocut.run", "logger=none", "progress=false", *overrides, f"outputs_root={root}"]
    return run_stage(cmd, cwd=REPO, env=_env(root), timeout=timeout)


def _out(proc) -> str:
    return proc.stdout + proc.stderr


def _user_error(proc, *needles: str) -> str:
    """Exit status 2, one message holding every needle, no traceback."""
    out = _out(proc)
    assert proc.returncode == 2, f"exit {proc.returncode}\n{out[-3000:]}"
    assert "Traceback" not in out, out[-3000:]
    for needle in needles:
        assert needle in out, f"{needle!r} not in:\n{out[-3000:]}"
    return out


def _steps(n_steps: int = 2, n: int = 40, seed: int = 0) -> list[dict]:
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.4, 0.6, (n, 3)).astype(np.float32)
    return [{"x_t": x, "f_t": np.zeros(n, np.int32), "x_t1": x, "f_t1": (x[:, 0] > 0.5).astype(np.int32),
             "action": np.array([0.5, 0.5, 0.0, 0.0], np.float32), "pose": np.eye(4, dtype=np.float32),
             "history": np.zeros((3, 7), np.float32), "reward": 0.5, "success": False} for _ in range(n_steps)]


def fake_dataset(store: ArtifactStore, name: str = "demos", seed: int = 0, episodes: int = 2) -> Path:
    """A committed dataset version of a few tiny episodes (no simulation)."""
    writer, existing = store.begin("dataset", name, {"fake": seed})
    assert existing is None
    ew = EpisodeWriter(writer.path / "data.zarr", points_per_step=32)
    for e in range(episodes):
        ew.add_episode(_steps(seed=seed + e), {"task": "slice", "object": "cake", "seed": seed * 100 + e,
                                               "goal": np.zeros((8, 3)), "goal_labels": np.zeros(8, int)})
    return writer.commit({"episodes": episodes})


# 1 -----------------------------------------------------------------------------------------------------------
def test_version_without_manifest_is_refused_by_name_and_numbered_past(tmp_path):
    store = ArtifactStore(tmp_path)
    v1, v2 = fake_dataset(store, seed=1), fake_dataset(store, seed=2)
    (v2 / "manifest.json").unlink()  # an interrupted copy of outputs/
    # pretrain does not fall back to v001 in silence
    proc = topocut(tmp_path, "stage=pretrain", "trainer.max_epochs=1")
    _user_error(proc, f"{v2} has no manifest.json")
    assert not (tmp_path / "checkpoint").exists() or not store.names("checkpoint")
    with pytest.raises(CorruptArtifact, match="v002 has no manifest.json"):
        store.resolve("dataset", "demos")
    assert store.resolve("dataset", "demos", "v001") == v1  # a pinned intact version still reads
    # the next commit numbers past the directory instead of failing 1000 renames onto it
    v3 = fake_dataset(store, seed=3)
    assert v3.name == "v003" and store.versions("dataset", "demos") == ["v001", "v003"]


# 2 -----------------------------------------------------------------------------------------------------------
def _compose(*overrides: str):
    from hydra import compose, initialize_config_dir

    from topocut.config import register_configs

    register_configs()
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def test_plus_prefixed_typo_keys_are_refused_listing_the_valid_ones(tmp_path):
    proc = topocut(tmp_path, "stage=mppi", "+planner.num_sample=64")
    _user_error(proc, "planner.num_sample: unknown key", "did you mean planner.num_samples", "horizon, iterations")
    proc = topocut(tmp_path, "stage=mppi", "sim.n_gird=32")  # Hydra's own refusal: its '+' advice is not repeated
    out = _user_error(proc, "sim.n_gird: unknown key", "did you mean sim.n_grid", "valid keys of sim:")
    assert "+sim.n_gird" not in out
    assert not (tmp_path / "dataset").exists()


def test_plus_keys_of_open_dicts_stay_valid():
    from topocut.config import ConfigError, check_known_keys

    for overrides in (["stage=eval", "+eval.checkpoints.pddp=v003"],
                      ["stage=eval", "+eval.checkpoints={3dda:v002,pddp:v003}"]):
        check_known_keys(_compose(*overrides))  # README's documented forms
    for typo, needle in (("+sim.n_gird=64", "sim.n_gird"), ("+eval.nme=x", "eval.nme"), ("+foo=1", "foo")):
        with pytest.raises(ConfigError, match=rf"{needle}: unknown key.*valid keys"):
            check_known_keys(_compose(typo))


# 3 -----------------------------------------------------------------------------------------------------------
MPPI = ["stage=mppi", "sim.n_grid=32", "task.max_cuts=1", "planner.num_samples=2", "sim.batch_size=2",
        "planner.iterations=1", "planner.horizon=1", "stage.run.compare_heuristic=false", "object.randomize_pose=false"]


def test_mppi_whose_episodes_all_diverge_commits_nothing_and_records_why(tmp_path):
    # J may leave (0.9999, 1.0001) on the first cut: every episode diverges, as with a huge gravity
    proc = topocut(tmp_path, *MPPI, "data.episodes=2", "sim.j_min=0.9999", "sim.j_max=1.0001", timeout=240)
    _user_error(proc, "all 2 episodes failed, nothing committed", "episode 0: cut 1: SimulationDiverged",
                "episode 1: cut 1: SimulationDiverged")
    store = ArtifactStore(tmp_path)
    assert store.versions("dataset", "demos") == []  # nothing usable as latest
    status = json.loads(next((tmp_path / "runs").rglob("status.json")).read_text())
    assert status["status"] == "failed" and [f["episode"] for f in status["failures"]] == [0, 1]
    assert all("SimulationDiverged" in f["error"] for f in status["failures"])
    log = next((tmp_path / "dataset" / "demos").glob(".partial-*/episodes.jsonl"))
    records = [json.loads(line) for line in log.read_text().splitlines()]
    assert [r["status"] for r in records] == ["failed", "failed"] and all("diverged" in r["error"] for r in records)


def test_unbounded_gravity_is_refused_at_config_time(tmp_path):
    _user_error(topocut(tmp_path, *MPPI, "sim.gravity=1e6"), "sim.gravity")
    assert not (tmp_path / "dataset").exists()


# 4 -----------------------------------------------------------------------------------------------------------
def test_file_the_manifest_does_not_list_is_refused_by_name(tmp_path):
    import zarr

    store = ArtifactStore(tmp_path)
    v1 = fake_dataset(store)
    before = set(p for p in v1.rglob("*") if p.is_file())
    g = zarr.open_group(str(v1 / "data.zarr"), mode="a")
    g["data/success"][:] = True  # all False before: zarr had stored no chunk, so this adds one
    added = sorted(p for p in v1.rglob("*") if p.is_file() and p not in before)
    assert added and EpisodeDataset(v1 / "data.zarr")[0]["success"]  # readers would see flipped labels
    with pytest.raises(CorruptArtifact, match=f"{added[0]} is not listed in {v1}/manifest.json"):
        store.resolve("dataset", "demos")
    added[0].unlink()
    assert store.resolve("dataset", "demos") == v1


def test_commit_lists_every_file_it_leaves(tmp_path):
    store = ArtifactStore(tmp_path)
    writer, _ = store.begin("eval", "table1", {"k": 1})
    (writer.path / "a.txt").write_text("a")
    (writer.path / ".a.txt.tmp-123").write_text("half")  # a killed atomic write's leftover
    (writer.path / "sub").mkdir()
    (writer.path / "sub" / "manifest.json").write_text("{}")  # only the top-level manifest is the store's
    path = writer.commit()
    assert sorted(store.verify(path)["files"]) == ["a.txt", "sub/manifest.json"]


# 5 -----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("overrides,key", [
    ((*MPPI, "data.episodes=1", "data.dataset=../../escaped"), "data.dataset"),
    ((*MPPI, "data.episodes=1", "data.dataset={tmp}/escaped"), "data.dataset"),  # an absolute path
    (("stage=bc", "data.encoder=../perception"), "data.encoder"),
    (("stage=eval", "eval.name=../../x"), "eval.name"),
])
def test_artifact_names_cannot_leave_their_kind(tmp_path, overrides, key):
    overrides = [o.replace("{tmp}", str(tmp_path)) for o in overrides]
    _user_error(topocut(tmp_path / "out", *overrides), f"{key}=", "[A-Za-z0-9][A-Za-z0-9._-]*")
    assert [p.name for p in tmp_path.iterdir()] == ["out"] and not (tmp_path / "out" / "dataset").exists()


def test_store_refuses_names_outside_the_pattern(tmp_path):
    store = ArtifactStore(tmp_path / "root")
    for bad in ("../escaped", "/abs", "a/b", ".hidden", "", "-x"):
        with pytest.raises(st.InvalidName, match="not a valid artifact name"):
            store.begin("dataset", bad, {"k": 1})
        with pytest.raises(st.InvalidName):
            store.resolve("checkpoint", bad)
    assert [p.name for p in tmp_path.iterdir()] == ["root"]
    assert store.begin("dataset", "demos-slice_cake.v2", {"k": 1})[0] is not None


# 6 -----------------------------------------------------------------------------------------------------------
def test_unknown_manifest_schema_version_is_refused(tmp_path):
    store = ArtifactStore(tmp_path)
    v1 = fake_dataset(store)
    m = json.loads((v1 / "manifest.json").read_text())
    (v1 / "manifest.json").write_text(json.dumps({**m, "schema_version": 99}))
    with pytest.raises(st.UnsupportedSchema, match="schema_version 99 is not supported.*reads schema_version 1"):
        store.begin("dataset", "demos", {"fake": 0})  # not reused
    _user_error(topocut(tmp_path, "stage=pretrain", "trainer.max_epochs=1"), "schema_version 99",
                "reads schema_version 1")


def test_episode_buffer_of_another_format_is_refused_naming_what_differs(tmp_path):
    store = ArtifactStore(tmp_path)
    v1 = fake_dataset(store)
    z = tmp_path / "copy.zarr"
    shutil.copytree(v1 / "data.zarr", z)
    shutil.rmtree(z / "data" / "mask")  # a layout without the cut masks
    with pytest.raises(st.UnsupportedSchema, match="without data/mask.*reads topocut-episodes-v1"):
        EpisodeDataset(z)
    with pytest.raises(st.UnsupportedSchema, match="without data/mask"):
        EpisodeWriter(z)  # nor resumed into
    import zarr

    zarr.open_group(str(z), mode="a").attrs["format"] = "topocut-episodes-v2"
    with pytest.raises(st.UnsupportedSchema, match="format 'topocut-episodes-v2'"):
        EpisodeDataset(z)


# 7 -----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("overrides,needle", [
    (("stage=simulat",), "stage=simulat: no such option; valid: all, bc, eval"),
    (("stage=simulate", "object.scale_min=0"), "object.scale_min: 0.0 is not valid"),
    (("stage=simulate", "object.yaw_deg=-5"), "object.yaw_deg"),
    (("stage=pretrain", "device=cpu", "trainer=gpu"), "trainer.accelerator: gpu needs a CUDA device"),
])
def test_user_errors_exit_2_with_one_message(tmp_path, overrides, needle):
    fake_dataset(ArtifactStore(tmp_path))  # so that pretrain gets as far as its trainer
    _user_error(topocut(tmp_path, *overrides), needle)


def test_unwritable_outputs_root_is_a_user_error(tmp_path):
    (tmp_path / "file").write_text("not a directory")
    _user_error(topocut(tmp_path / "file" / "out", "stage=merge"), "outputs_root=", "cannot write there")
    if os.geteuid() != 0:  # root writes through permission bits
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o500)
        _user_error(topocut(ro, "stage=merge"), "cannot write there")


def test_full_disk_is_a_user_error_and_status_json_does_not_hide_it(tmp_path):
    """ENOSPC from the stage, and again from the status.json write in the run wrapper's finally."""
    script = textwrap.dedent("""
        import errno, runpy, sys
        import topocut.data.store as store

        def full(*args, **kwargs):
            raise OSError(errno.ENOSPC, "No space left on device", "/fake/outputs")

        real = store.write_json_atomic
        store.ArtifactStore.__init__ = full
        store.write_json_atomic = lambda path, obj: full() if path.name == "status.json" else real(path, obj)
        sys.argv = ["topocut.run", *sys.argv[1:]]
        runpy.run_module("topocut.run", run_name="__main__")
    """)
    proc = subprocess.run([sys.executable, "-c", script, "stage=merge", "logger=none", f"outputs_root={tmp_path}"],
                          cwd=REPO, env=_env(tmp_path), capture_output=True, text=True, timeout=120)
    out = _user_error(proc, "OSError: [Errno 28] No space left on device: '/fake/outputs'", "status.json")
    assert out.count("No space left") == 2  # the stage's error, and the warning that status.json was not written
    assert errno.ENOSPC == 28


# 8 -----------------------------------------------------------------------------------------------------------
def _spy_torch_load(monkeypatch) -> list:
    import torch

    calls, real = [], torch.load

    def spy(*args, **kwargs):
        calls.append(kwargs.get("weights_only"))
        return real(*args, **kwargs)

    monkeypatch.setattr(torch, "load", spy)
    return calls


def _save(module, path: Path) -> Path:
    import lightning
    import torch

    torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams),
                "pytorch-lightning_version": lightning.__version__}, path)
    return path


def test_checkpoints_load_with_weights_only(tmp_path, monkeypatch):
    from topocut.policies.baselines.module import PoseDiffusionModule, load_pose_policy
    from topocut.policies.config import PDDPConfig
    from topocut.policies.module import PDDPModule, PDDPPolicy

    pose = _save(PoseDiffusionModule(kind="dp3", num_points=16, num_goal_points=8, down_dims=(8, 16, 32),
                                     enc_dim=8), tmp_path / "dp3.ckpt")
    pddp = _save(PDDPModule(PDDPConfig(n_blocks=1, hidden=16, obs_dim=16, n_heads=2, cond_dim=16,
                                       time_freq_dim=16, goal_hidden=8, dropout=0.0), "none"), tmp_path / "pddp.ckpt")
    calls = _spy_torch_load(monkeypatch)
    load_pose_policy(pose)
    PDDPPolicy(str(pddp))
    assert calls == [True, True]

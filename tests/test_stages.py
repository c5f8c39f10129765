"""The Hydra stages run end to end as real subprocesses (`python -m topocut.run ...`).

Every run writes under a pytest tmp dir (``outputs_root=`` and TOPOCUT_OUTPUTS), never the repo's
outputs/.  The simulation is shrunk to a few seconds per job: a coarse grid, 2 MPPI samples, 2 cuts,
short knife travel / push / settle phases.  Expected numbers come from the stores themselves
(each shard's zarr, the manifest's file list), not from the stages' printed summaries.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from tests.stage_runner import run as run_stage
from topocut.data.episodes import EpisodeDataset
from topocut.data.store import ArtifactStore

REPO = Path(__file__).resolve().parents[1]

# Tiny everything: ~2 s per episode on a 2-core CPU.  task.max_cuts=2 because `stick` needs a slab cut
# and a width cut before it has a goal piece.
FAST = ["logger=none", "progress=false", "sim.n_grid=20", "sim.cut_substeps=40", "sim.dwell_time=0.0005",
        "sim.push_time=0.002", "sim.settle_time=0.002", "sim.batch_size=2", "planner.num_samples=2",
        "planner.horizon=1", "planner.iterations=1", "task.max_cuts=2", "data.points_per_step=128",
        "topology.resolution=32", "stage.run.compare_heuristic=false", "object.randomize_pose=false",
        "eval.videos=0"]  # filming: tests/test_eval_videos.py
RESUME_SEED = 7
RESUME_EPISODES = 3


def _env(root: Path) -> dict:
    env = dict(os.environ, WANDB_MODE="disabled", TOPOCUT_OUTPUTS=str(root), HYDRA_FULL_ERROR="0")
    env.pop("CUDA_VISIBLE_DEVICES", None)
    return env


def _cmd(root: Path, *overrides: str) -> list[str]:
    return [sys.executable, "-m", "topocut.run", *overrides, f"outputs_root={root}"]


def topocut(root: Path, *overrides: str, timeout: float = 180) -> subprocess.CompletedProcess:
    return run_stage(_cmd(root, *overrides), cwd=REPO, env=_env(root), timeout=timeout)


def _output(proc) -> str:
    return proc.stdout + proc.stderr


def _summary(proc) -> dict:
    """The JSON summary topocut.run logs as its last line (`... - summary: {...}`)."""
    lines = [ln for ln in _output(proc).splitlines() if " - summary: " in ln]
    assert lines, f"no summary line in output:\n{_output(proc)[-3000:]}"
    return json.loads(lines[-1].split(" - summary: ", 1)[1])


def _ok(proc) -> subprocess.CompletedProcess:
    assert proc.returncode == 0, f"{' '.join(proc.args)}\nexit {proc.returncode}\n{_output(proc)[-4000:]}"
    return proc


MPPI_ONE = ["stage=mppi", "task=slice", "object=cube", f"seed={RESUME_SEED}", f"data.episodes={RESUME_EPISODES}",
            *FAST]


@pytest.fixture(scope="module")
def resumed(tmp_path_factory):
    """A single mppi run killed after its first committed episode, then re-run to completion."""
    root = tmp_path_factory.mktemp("resume")
    store = ArtifactStore(root)
    proc = subprocess.Popen(_cmd(root, *MPPI_ONE), cwd=REPO, env=_env(root), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    first_x = None
    deadline = time.time() + 150
    try:
        while time.time() < deadline and proc.poll() is None:
            for z in (root / "dataset" / "demos").glob(".partial-*/data.zarr"):
                try:
                    ds = EpisodeDataset(z)
                    if ds.num_episodes >= 1:
                        first_x = np.array(ds[0]["x_t"], copy=True)  # a copy, read before the kill
                except Exception:  # noqa: BLE001 - the buffer may not be laid out yet
                    continue
            if first_x is not None:
                break
            time.sleep(0.5)
    finally:
        proc.kill()
        out = proc.communicate(timeout=30)[0]
    killed_rc = proc.returncode  # -9: killed mid-run, not finished on its own
    assert first_x is not None, f"no episode committed to a partial dir before the kill/timeout:\n{out[-3000:]}"
    versions_after_kill = store.versions("dataset", "demos")
    partials_after_kill = sorted(p.name for p in (root / "dataset" / "demos").glob(".partial-*"))
    committed_at_kill = EpisodeDataset(next((root / "dataset" / "demos").glob(".partial-*/data.zarr"))).num_episodes
    t0 = time.time()
    second = _ok(topocut(root, *MPPI_ONE))
    return {"root": root, "store": store, "first_x": first_x, "killed_rc": killed_rc, "versions_after_kill": versions_after_kill,
            "partials_after_kill": partials_after_kill, "second": second, "second_seconds": time.time() - t0,
            "second_launched": t0, "committed_at_kill": committed_at_kill}


def test_multirun_shards_merge_into_one_dataset(tmp_path):
    sweep = _ok(topocut(tmp_path, "-m", "stage=mppi", "task=slice,stick", "object=cube,cake",
                        "hydra/launcher=basic", "data.episodes=2", *FAST, timeout=240))
    store = ArtifactStore(tmp_path)
    names = [n for n in store.names("dataset") if n.startswith("demos-")]
    # one shard per job: <dataset>-<task>-<object>-s<seed>-<8 hex of the job's config key>
    assert sorted(n.rsplit("-", 1)[0] for n in names) == sorted(
        f"demos-{t}-{o}-s0" for t in ("slice", "stick") for o in ("cube", "cake")), _output(sweep)[-2000:]
    assert all(len(n.rsplit("-", 1)[1]) == 8 for n in names)
    shard_eps, shard_steps, shard_latest = 0, 0, {}
    for name in names:
        path = store.resolve("dataset", name)
        assert store.manifest(path)["shard_of"] == "demos"
        shard_latest[name] = store.ref(path)
        ds = EpisodeDataset(path / "data.zarr")
        shard_eps += ds.num_episodes
        shard_steps += len(ds)
    assert shard_eps == 2 * 4
    # a dataset whose name merely starts with "demos-" is not a shard of demos
    writer, _ = store.begin("dataset", "demos-paper", {"other": 1})
    (writer.path / "x.txt").write_text("not a shard")
    writer.commit()

    _ok(topocut(tmp_path, "stage=merge", "logger=none", "progress=false"))
    merged = tmp_path / "dataset" / "demos" / "v001"
    assert merged.is_dir()
    manifest = json.loads((merged / "manifest.json").read_text())
    assert manifest["inputs"] == shard_latest
    ds = EpisodeDataset(merged / "data.zarr")
    assert ds.num_episodes == shard_eps
    assert len(ds) == shard_steps
    pairs = [(ds.meta(e)["task"], ds.meta(e)["object"]) for e in range(ds.num_episodes)]
    assert sorted(pairs) == sorted((t, o) for t in ("slice", "stick") for o in ("cube", "cake") for _ in range(2))
    store.verify(merged)  # the manifest's sha256 match the files as written


def test_killed_mppi_resumes_without_redoing_episodes(resumed):
    assert resumed["killed_rc"] == -9
    assert resumed["versions_after_kill"] == []  # nothing committed by the killed run...
    assert len(resumed["partials_after_kill"]) == 1  # ...but its partial work is there to resume from
    store = resumed["store"]
    assert store.versions("dataset", "demos") == ["v001"]
    path = store.resolve("dataset", "demos")
    assert not list((resumed["root"] / "dataset" / "demos").glob(".partial-*"))  # renamed on commit
    ds = EpisodeDataset(path / "data.zarr")
    assert ds.num_episodes == RESUME_EPISODES
    seeds = [ds.meta(e)["seed"] for e in range(ds.num_episodes)]
    assert sorted(seeds) == [RESUME_SEED * 1_000_003 + e for e in range(RESUME_EPISODES)]  # mix_seed(seed, e)
    # episode 0 was written by the killed run and kept, not recomputed (bytes identical)
    x0 = ds[0]["x_t"]
    assert x0.dtype == resumed["first_x"].dtype and x0.shape == resumed["first_x"].shape
    assert x0.tobytes() == resumed["first_x"].tobytes()
    assert len(ds) == sum(ds.meta(e)["num_steps"] for e in range(ds.num_episodes))
    # the episode log's wall-clock starts (benchmarks/demo_processes.py splits a process's time with them): the
    # episodes the killed run committed started before the re-run was launched, the others in the re-run, in order
    from topocut.data.collection import read_records

    records = read_records(path / "episodes.jsonl")
    starts = [r["started"] for r in sorted(records, key=lambda r: r["episode"])]
    assert starts == sorted(starts) and 1 <= resumed["committed_at_kill"] < RESUME_EPISODES
    assert sum(s < resumed["second_launched"] for s in starts) == resumed["committed_at_kill"]
    assert all(r["time_s"] > 0 for r in records)
    # the iterations planned for each executed cut (planner.stop_at_success): one number per cut, none past the
    # planner's iterations (smoke: 1)
    assert all(len(r["mppi_iterations"]) == r["num_cuts"] and set(r["mppi_iterations"]) <= {1} for r in records)


def test_rerun_with_same_config_reuses_the_version(resumed):
    root, store = resumed["root"], resumed["store"]
    manifest_before = (store.resolve("dataset", "demos") / "manifest.json").read_text()
    t0 = time.time()
    again = _ok(topocut(root, *MPPI_ONE))
    elapsed = time.time() - t0
    summary = _summary(again)
    assert summary.get("reused") is True
    assert Path(summary["dataset"]) == root / "dataset" / "demos" / "v001"
    assert "reused" in again.stdout
    assert store.versions("dataset", "demos") == ["v001"]
    assert (root / "dataset" / "demos" / "v001" / "manifest.json").read_text() == manifest_before
    assert not list((root / "dataset" / "demos").glob(".partial-*"))
    assert elapsed < resumed["second_seconds"] + 5  # no simulation: no slower than the resumed run


@pytest.mark.parametrize("override,needles", [
    ("object=carrot", ["carrot", "cake", "cube", "donut"]),
    ("sim.dt=0.05", ["sim.dt"]),
])
def test_bad_override_fails_before_simulating(tmp_path, override, needles):
    proc = topocut(tmp_path, "stage=mppi", *FAST, override, timeout=60)
    assert proc.returncode != 0
    out = _output(proc)
    for needle in needles:
        assert needle in out, f"{needle!r} not in output:\n{out[-3000:]}"
    assert not (tmp_path / "dataset").exists()  # nothing simulated, nothing written


def test_tampered_dataset_is_refused_downstream(resumed, tmp_path):
    root = tmp_path / "outputs"
    shutil.copytree(resumed["root"] / "dataset", root / "dataset")  # tamper a copy: other tests keep theirs
    version = root / "dataset" / "demos" / "v001"
    files = json.loads((version / "manifest.json").read_text())["files"]
    rel = sorted(f for f in files if f.startswith("data.zarr/data/x_t/") and not f.endswith("zarr.json"))[0]
    target = (version / rel).resolve()
    blob = bytearray(target.read_bytes())
    blob[len(blob) // 2] ^= 0xFF
    target.write_bytes(bytes(blob))
    proc = topocut(root, "stage=pretrain", "logger=none", "progress=false", "trainer.max_epochs=1", timeout=120)
    out = _output(proc)
    assert proc.returncode != 0, out[-3000:]
    assert str(target) in out and "sha256" in out, out[-3000:]
    assert not (root / "checkpoint").exists() or not ArtifactStore(root).versions("checkpoint", "perception")


def test_ddp_pretrain_commits_one_version_from_rank_zero(resumed, tmp_path):
    """trainer.strategy=ddp on 2 CPU processes (gloo): Lightning re-runs the command for rank 1; only rank 0
    may write the version (before: both ranks copied and deleted the work area, and one crashed)."""
    root = tmp_path / "outputs"
    shutil.copytree(resumed["root"] / "dataset", root / "dataset")
    proc = _ok(topocut(root, "stage=pretrain", "logger=none", "progress=false", "trainer.max_epochs=1",
                       "trainer.accelerator=cpu", "trainer.devices=2", "trainer.strategy=ddp", timeout=240))
    store = ArtifactStore(root)
    assert store.versions("checkpoint", "perception") == ["v001"], _output(proc)[-3000:]
    files = store.verify(store.resolve("checkpoint", "perception"))["files"]
    assert {"model.ckpt", "metrics.json", "history.json", "loss.png"} <= set(files)
    left = [p.name for p in (root / "checkpoint" / "perception").iterdir() if p.name.startswith(".")]
    assert left == []  # no partial directory, no Lightning work area
    assert '"rank": 1' in _output(proc)  # rank 1 ran and returned without committing


def _pixels_of(png: Path, rgb) -> int:
    """Pixels drawn in colour ``rgb`` at any opacity over white: 1 - pixel is parallel to 1 - rgb
    (matplotlib's depth shading only changes the opacity)."""
    import matplotlib.image as mpimg

    ink = 1.0 - mpimg.imread(png)[..., :3].reshape(-1, 3).astype(np.float64)  # P,3
    ref = (1.0 - np.asarray(rgb, np.float64)) / np.linalg.norm(1.0 - np.asarray(rgb, np.float64))
    norm = np.linalg.norm(ink, axis=1)
    strong = norm > 0.15
    cos = (ink[strong] @ ref) / norm[strong]
    return int((cos > 0.995).sum())


def test_simulate_slices_a_cube_into_three_labelled_pieces(tmp_path):
    """stage=simulate, two slice cuts through a cube: 2 pieces, then 3, each piece on one side of every
    blade plane (from the recorded sweeps), and the renders colour particles by cluster id."""
    from topocut.sim.render import _PALETTE

    proc = topocut(tmp_path, "stage=simulate", "task=slice", "object=cube", "task.max_cuts=2", "sim.n_grid=32",
                   "topology.resolution=48", "object.randomize_pose=false", "logger=none", "progress=false")
    assert proc.returncode == 0, _output(proc)[-3000:]
    art = Path(_summary(proc)["artifact"])
    cuts = json.loads((art / "cuts.json").read_text())["cuts"]
    assert [c["pieces"] for c in cuts] == [2, 3]
    st = np.load(art / "states.npz")
    lab = st["labels_2"]
    assert len(set(lab[lab >= 0].tolist())) == 3 and (lab >= 0).mean() > 0.99
    for c in cuts:  # right after cut k (and its push), every piece lies on one side of blade plane k
        k = c["cut"]
        x, lab_k = st[f"x_{k}"], st[f"labels_{k}"]
        o, n = np.asarray(c["sweep"]["origin"]), np.asarray(c["sweep"]["n"])
        side = (x - o) @ n > 0
        for i in set(lab_k[lab_k >= 0].tolist()):
            s = side[lab_k == i]
            assert max(s.mean(), 1 - s.mean()) > 0.97, (k, i, s.mean())
    np.testing.assert_array_equal(np.unique(st["labels_1"][st["labels_1"] >= 0]), [0, 1])
    # renders: ids 0, 1 after the first cut; a third colour (id 2) appears only after the second
    frames = art / "frames"
    assert _pixels_of(frames / "cut1.png", _PALETTE[1]) > 200
    assert _pixels_of(frames / "cut1.png", _PALETTE[2]) < 20
    assert _pixels_of(frames / "cut2.png", _PALETTE[2]) > 200
    from PIL import Image

    with Image.open(art / "cut.gif") as gif:  # each cut in motion (stage.run.frames_per_cut snapshots), not stills
        assert gif.n_frames >= 1 + 4 * len(cuts) and gif.size[0] >= 800


@pytest.mark.parametrize("overrides,needle", [
    (("seed=-3",), "ConfigError: seed: -3 is not valid"),
    (("stage=eval", "task=stick"), "set eval.tasks=[stick]"),
    (("stage=eval", "task=pyramid"), "task=pyramid has no evaluation protocol"),
    (("stage=pretrain", "data.version=v999"), "MissingArtifact: no committed dataset named 'demos'"),
    (("stage=simulate", "task.thickness=10"), "a piece must be thinner than the object"),
])
def test_user_errors_print_one_message_and_exit_2(tmp_path, overrides, needle):
    """A bad value or a missing input is the user's to fix: its message, no traceback, exit status 2, and the
    traceback kept in the run's status.json."""
    proc = topocut(tmp_path, *overrides, "logger=none", timeout=120)
    out = _output(proc)
    assert proc.returncode == 2 and needle in out and "Traceback" not in out, out[-3000:]
    status = json.loads(next((tmp_path / "runs").rglob("status.json")).read_text())
    assert status["status"] == "failed" and "Traceback" in status["traceback"]


def test_eval_in_two_processes_writes_the_episodes_of_one(tmp_path):
    """eval.jobs=2: two loky worker processes, each its own simulator, write the same episodes (rewards, cut
    counts, actions) as one process; the report counts them all."""
    ev = ["stage=eval", "scale=smoke", "eval.policies=[oracle,heuristic]", "eval.tasks=[slice]", "eval.max_cuts=1",
          "eval.bootstrap_resamples=100", *[o for o in FAST if not o.startswith(("stage.run", "task.max_cuts"))],
          "sim.batch_size=1"]  # batches of one spec: 2 specs x 2 policies are 4 tasks for 2 workers
    runs = {}
    for jobs in (1, 2):
        proc = _ok(topocut(tmp_path / f"j{jobs}", *ev, f"eval.jobs={jobs}", timeout=400))
        assert _summary(proc)["episodes"] == 4
        files = sorted((tmp_path / f"j{jobs}" / "eval" / "table1" / "v001" / "episodes").glob("*/*.json"))
        runs[jobs] = {f.parent.name + "/" + f.name: json.loads(f.read_text()) for f in files}
    assert len(runs[1]) == 4 and runs[1].keys() == runs[2].keys()
    assert "2 processes (eval.jobs=2)" in _output(proc)
    assert "4 tasks" in _output(proc)  # a batch of one spec per policy each
    assert "the workers wrote 4 new episodes (oracle 2, heuristic 2)" in _output(proc)  # the stage then only reads
    for key, one in runs[1].items():
        two = runs[2][key]
        assert (one["final_reward"], one["cut_counts"], one["actions"]) == \
            (two["final_reward"], two["cut_counts"], two["actions"]), key


def test_stage_all_runs_the_whole_pipeline_and_each_stage_reads_the_last_ones_artifact(tmp_path):
    """`make run`'s command (stage=all at smoke scale), shrunk: simulate → mppi → pretrain → bc → eval for real in
    one process tree. Every stage commits its artifact, each reads the one before it (the manifests' inputs
    name them), and the evaluation holds every Table 1 policy on every episode spec.  With the default logger
    (wandb, offline) and progress on, as a user's first `make run` has them (issue #48; the suite's own runs set
    WANDB_MODE=disabled): each stage leaves its offline run in its run directory, says where in one line and
    prints no wandb banner (~30 lines a stage), and a training in a log gets a line per epoch."""
    root = tmp_path / "o"
    # stage=all passes its stages no stage.run.* key; the logger and the progress lines as a user has them
    small = [o for o in FAST if not o.startswith("stage.run.") and o not in ("logger=none", "progress=false")]
    proc = _ok(run_stage(
        _cmd(root, "stage=all", "scale=smoke", *small, "logger=wandb", "data.episodes=2", "trainer.max_epochs=1",
             "policy.train.max_epochs=1", "eval.max_cuts=1", "eval.bootstrap_resamples=100", "trainer.profiler=simple"),
        cwd=REPO, env=dict(_env(root), WANDB_MODE="offline"), timeout=900))
    out = _output(proc)
    (run_dir,) = (root / "runs" / "all").iterdir()
    said = [ln for ln in out.splitlines() if "wandb: offline run written to" in ln]
    for stage_dir in [run_dir, *(run_dir / s for s in ("simulate", "mppi", "pretrain", "bc", "eval"))]:
        offline = list((stage_dir / "wandb").glob("offline-run-*"))
        assert len(offline) == 1 and list(offline[0].glob("*.wandb")), f"no offline run in {stage_dir}"
        assert sum(str(offline[0]) in ln for ln in said) == 1, f"{stage_dir.name}:\n{out[-3000:]}"
    assert "Tracking run with wandb" not in out and "Run summary" not in out, f"a wandb banner:\n{out[-3000:]}"
    epochs = [ln.split(" - epoch 1/1: ", 1)[1] for ln in out.splitlines() if " - epoch 1/1: " in ln]
    assert len(epochs) >= 2 and "…" not in out, out[-3000:]  # F's and the policies' (names whole, not a bar's)
    from tests.test_logger import _keys_documented

    pretrain = _summary(proc)["pretrain"]  # every key its summary and its epoch line print is explained
    _keys_documented(pretrain, REPO / "docs" / "perception.md")
    _keys_documented(dict(kv.rsplit(" ", 1) for kv in epochs[0].split(", ")), REPO / "docs" / "perception.md")
    store = ArtifactStore(root)
    demos = store.resolve("dataset", "demos")
    assert EpisodeDataset(demos / "data.zarr").num_episodes == 2  # data.episodes of the one smoke cell
    demos_ref = store.ref(demos)
    assert store.manifest(store.resolve("checkpoint", "perception"))["inputs"]["dataset"] == demos_ref
    learned = ["pddp", "pddp_noperc", "dp3", "3dda"]
    ckpts = {}
    for name in learned:
        ckpts[name] = store.resolve("checkpoint", name)
        assert (ckpts[name] / "model.ckpt").is_file(), name
        assert store.manifest(ckpts[name])["inputs"]["dataset"] == demos_ref, name
    assert store.manifest(ckpts["pddp"])["inputs"]["encoder"] == store.ref(store.resolve("checkpoint", "perception"))
    # trainer.profiler: a report per fit in its run's directory (bc: per policy), and no part of a checkpoint's key
    profiles = {p.parent.name for p in (root / "runs").rglob("fit-profile.txt")}
    assert profiles == {"pretrain", *learned}, profiles
    for ck in [store.resolve("checkpoint", "perception"), *ckpts.values()]:
        assert "profiler" not in store.manifest(ck)["config"]["trainer"]
    table = store.resolve("eval", "table1")
    inputs = store.manifest(table)["inputs"]
    assert {store.ref(c) for c in ckpts.values()} <= set(inputs.values())  # the checkpoints bc just committed
    specs = 2  # eval.seen=[cube] + eval.unseen=[donut], one slice episode each
    policies = ["oracle", "heuristic", "mppi", *learned]
    # episode files live under <policy> or <policy>@s<seed>; exactly the seven policies, each on every spec
    per_policy = Counter(f.parent.name.split("@")[0] for f in (table / "episodes").glob("*/*.json"))
    assert per_policy == {p: specs for p in policies}
    report = (table / "results.md").read_text()
    assert all(label in report for label in ("Oracle", "Heuristic", "MPPI", "DP3", "3D Diffuser Actor", "PDDP"))

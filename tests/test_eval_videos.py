"""Issue #51 (item 3): rollout videos.  `python -m topocut.run stage=eval eval.videos=k` writes an MP4 per policy run
for its first k episodes, each cut shown in motion by eval.video_frames_per_cut frames (topocut.eval.videos), and
eval.videos=0 writes none; a negative value is the user's error (exit 2)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import imageio.v3 as iio
import numpy as np
import pytest

from tests.stage_runner import run as run_stage
from topocut.eval import EvalConfig
from topocut.eval.videos import STATE_HOLD_FRAMES, VIDEO_HEIGHT, VIDEO_WIDTH
from topocut.sim.cut_frames import pick_cut_frames

REPO = Path(__file__).resolve().parents[1]
POLICIES = ("oracle", "heuristic")
FRAMES_PER_CUT = 3
# one cube, three slice episodes of two cuts each, in one batch (smoke scale: sim.batch_size=4); a coarse grid
TINY = ["stage=eval", "device=cpu", "logger=none", "progress=false", f"eval.policies=[{','.join(POLICIES)}]",
        "eval.seen=[cube]", "eval.unseen=[]", "eval.tasks=[slice]", "eval.episodes_per_cell=3", "eval.max_cuts=2",
        "eval.num_points=128", "eval.cpu_threads=1", "eval.bootstrap_resamples=100", "sim.n_grid=32",
        "sim.cut_substeps=40", "sim.dwell_time=0.0005", "sim.push_time=0.002", "sim.settle_time=0.002",
        "topology.resolution=32"]


def topocut(root: Path, *overrides: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, WANDB_MODE="disabled", TOPOCUT_OUTPUTS=str(root), HYDRA_FULL_ERROR="0")
    env.pop("CUDA_VISIBLE_DEVICES", None)
    return run_stage([sys.executable, "-m", "topocut.run", *overrides, f"outputs_root={root}"], cwd=REPO,
                     env=env, timeout=300)


def _evaluation(root: Path, *overrides: str) -> tuple[Path, str]:
    gifs = [] if any(o.startswith("eval.gifs=") for o in overrides) else ["eval.gifs=0"]
    proc = topocut(root, *TINY, *gifs, *overrides)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-4000:]
    (path,) = (root / "eval" / "table1").glob("v*")
    return path, out


@pytest.fixture(scope="module")
def filmed_run(tmp_path_factory) -> tuple[Path, str]:
    return _evaluation(tmp_path_factory.mktemp("videos"), "eval.videos=2",
                       f"eval.video_frames_per_cut={FRAMES_PER_CUT}", "eval.gifs=1")


@pytest.fixture(scope="module")
def filmed(filmed_run) -> Path:
    return filmed_run[0]


def test_the_evaluation_films_as_it_goes_and_runs_no_episode_again(filmed_run):
    path, out = filmed_run
    assert "filmed by running them again" not in out, out[-3000:]
    # each video was written before its episode's JSON was committed (Filming, in run_evaluation)
    videos = sorted(path.glob("videos/*/*.mp4"))
    assert len(videos) == 2 * len(POLICIES), videos
    for video in videos:
        episode = path / "episodes" / video.parent.name / f"{video.stem}.json"
        assert video.stat().st_mtime_ns <= episode.stat().st_mtime_ns, video
    # eval.gifs=1: the first run's (no PDDP here: the oracle's) first slice episode as a GIF, before its JSON, and
    # the cutting-sequence figure from it; its panels are gone once the figure is drawn
    gif = path / "gifs" / f"slice_cube_000_{POLICIES[0]}.gif"
    assert sorted((path / "gifs").iterdir()) == sorted([gif, path / "gifs" / "sequences.png"])
    assert gif.stat().st_mtime_ns <= (path / "episodes" / POLICIES[0] / "slice_cube_000.json").stat().st_mtime_ns
    episode = json.loads((path / "episodes" / POLICIES[0] / "slice_cube_000.json").read_text())
    assert len(iio.imread(gif, index=None)) == 1 + episode["num_cuts"]  # the reset, then each cut's state


def test_every_policy_has_a_video_of_its_first_episodes_only(filmed):
    videos = sorted(str(p.relative_to(filmed)) for p in filmed.glob("videos/**/*.mp4"))
    assert videos == [f"videos/{run}/slice_cube_{e:03d}.mp4" for run in sorted(POLICIES) for e in (0, 1)], videos
    manifest = json.loads((filmed / "manifest.json").read_text())
    assert manifest["summary"]["videos"] == videos and set(videos) <= set(manifest["files"])
    assert not list(filmed.rglob("*.tmp-*")), "a temporary file was left behind"
    assert "videos" not in manifest["config"]["eval"]  # filming changes no episode: not in the evaluation's key


def test_a_video_holds_each_state_and_the_frames_during_each_cut(filmed):
    for run in POLICIES:
        for e in (0, 1):
            episode = json.loads((filmed / "episodes" / run / f"slice_cube_{e:03d}.json").read_text())
            cuts, turns = episode["num_cuts"], len(episode["turns"])
            assert episode["status"] == "ok" and cuts == 2, episode
            frames = iio.imread(filmed / "videos" / run / f"slice_cube_{e:03d}.mp4")  # T,H,W,3
            states = 1 + cuts + turns  # reset, after each cut, after each turn
            assert frames.shape == (STATE_HOLD_FRAMES * states + FRAMES_PER_CUT * cuts, VIDEO_HEIGHT, VIDEO_WIDTH, 3)
            # mean change from each frame to the next: reset held, cut 1's frames, the state after it held, ...
            step = np.abs(np.diff(frames.astype(np.int16), axis=0)).mean((1, 2, 3)).tolist()  # T-1
            assert max(step[:STATE_HOLD_FRAMES - 1]) < 0.2  # a held state stays put
            for c in range(cuts):
                first = (c + 1) * STATE_HOLD_FRAMES + c * FRAMES_PER_CUT  # the first frame during cut c + 1
                during = step[first:first + FRAMES_PER_CUT - 1]
                assert min(during) > 0.3, (run, e, c, during)  # the knife moves between frames of a cut


def test_no_videos_with_videos_0(tmp_path):
    path, _ = _evaluation(tmp_path, "eval.videos=0", "eval.episodes_per_cell=1", "eval.max_cuts=1",
                       "eval.policies=[oracle]", "sim.n_grid=20")
    assert not (path / "videos").exists()
    assert json.loads((path / "manifest.json").read_text())["summary"]["videos"] == []


def test_a_negative_count_is_a_config_error(tmp_path):
    proc = topocut(tmp_path, *TINY, "eval.videos=-1")
    out = proc.stdout + proc.stderr
    assert proc.returncode == 2 and "Traceback" not in out, out[-3000:]
    assert "eval.videos=-1 is not valid; must be >= 0" in out, out[-3000:]
    with pytest.raises(ValueError, match=r"eval.video_frames_per_cut=0 is not valid; must be >= 1"):
        EvalConfig(video_frames_per_cut=0).validate()
    with pytest.raises(ValueError, match=r"eval.gifs=-2 is not valid; must be >= 0"):
        EvalConfig(gifs=-2).validate()


def test_frames_during_a_cut_are_picked_evenly_within_the_scene_budget():
    """Exactly F frames per cut, the last one the scene's latest snapshot within its own budget (a batch runs the
    longest scene's substeps); a snapshot repeats where the cut recorded fewer than F; earlier damage left out."""
    n, B = 5, 2
    snaps = [SimpleNamespace(substep=s, x=np.full((B, n + 1, 3), s, np.float32), damage=np.ones((B, n + 1), bool),
                             knife_edge=np.full((B, 3), s, np.float64)) for s in (16, 32, 48, 64, 80, 96)]
    before = np.array([True, False, False, False, False])
    picked = pick_cut_frames(snaps, 1, n, before, budget=64, frames_per_cut=2, dt=1e-3)
    assert [f.substep for f in picked] == [32, 64] and picked[1].time_s == pytest.approx(0.064)
    assert picked[0].x.shape == (n, 3) and picked[0].damaged.tolist() == [False, True, True, True, True]
    assert [f.substep for f in pick_cut_frames(snaps[:2], 0, n, before, 96, 4, 1e-3)] == [16, 16, 32, 32]
    assert pick_cut_frames([], 0, n, before, 96, 4, 1e-3) == []

"""experiments/paired_runs.py: two evaluation runs of one policy paired by episode (docs/data.md, "The rollout's
last push"), checked against differences worked out by hand on made-up episodes."""
import json
import sys
import tarfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from experiments import paired_runs  # noqa: E402


def _run(root: Path, rewards: dict, acts: dict) -> Path:
    folder = root / "episodes" / "mppi"
    folder.mkdir(parents=True)
    for key, r in rewards.items():
        task, obj, seed = key.split("_")
        episode = {"spec": {"task": task, "object": obj, "seed": int(seed)}, "final_reward": r,
                   "success": r >= 0.9, "act_time_s": acts[key]}
        (folder / f"{key}.json").write_text(json.dumps(episode))
    return root


def test_pairs_by_episode_and_differences_by_hand(tmp_path, capsys):
    a = _run(tmp_path / "a", {"slice_cube_000": 0.95, "slice_cube_001": 0.80, "dice_cake_000": 0.50,
                              "dice_cake_001": 0.91}, {k: [1.0, 2.0] for k in ("slice_cube_000", "slice_cube_001",
                                                                              "dice_cake_000", "dice_cake_001")})
    b = _run(tmp_path / "b", {"slice_cube_000": 0.97, "slice_cube_001": 0.92, "dice_cake_000": 0.40,
                              "dice_cake_002": 0.99}, {k: [0.5] for k in ("slice_cube_000", "slice_cube_001",
                                                                         "dice_cake_000", "dice_cake_002")})
    with tarfile.open(tmp_path / "b.tgz", "w:gz") as tar:  # the tarball gpu.sh brings back: episodes/ at its root
        tar.add(b / "episodes", arcname="episodes")
    assert paired_runs.main([str(a), str(tmp_path / "b.tgz"), "--moved", "0.05"]) == 0
    out = capsys.readouterr().out
    rows = {line.split("|")[1].strip(): line for line in out.splitlines() if line.startswith("| ")}
    # three specs in both runs (dice_cake_001 and dice_cake_002 are in one run each)
    assert "| 3 |" in rows["all"]
    assert f"{np.mean([0.97 - 0.95, 0.92 - 0.80, 0.40 - 0.50]):+.3f}" in rows["all"]
    assert f"{np.mean([0.02, 0.12]):+.3f}" in rows["slice"] and "| -0.100 [" in rows["dice"]
    assert "| 1 / 2 |" in rows["all"] and "3.0 → 0.5" in rows["all"]  # successes (R >= 0.9 here); act seconds
    assert "2 episodes moved by more than 0.05" in out and "slice_cube_001: 0.800 → 0.920" in out


def test_a_missing_run_is_one_message_and_exit_2(tmp_path, capsys):
    assert paired_runs.main([str(tmp_path / "none"), str(tmp_path / "none")]) == 2
    assert "no episodes/mppi/*.json" in capsys.readouterr().err

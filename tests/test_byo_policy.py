"""Issue #31 (item 3): bring-your-own-policy evaluation.  ``eval.policies=[oracle,module.path:ClassName]`` imports a
class against the Policy protocol (topocut.policies.registry.load_external); the toy examples/my_policy.py is
evaluated beside the oracle by `python -m topocut.run stage=eval`, and a bad entry is a user error (exit 2)."""
from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from tests.stage_runner import run as run_stage
from topocut.eval import EvalConfig
from topocut.policies import registry

REPO = Path(__file__).resolve().parents[1]
EXAMPLES = REPO / "examples"
TOY = "my_policy:GoalPlanePolicy"
TINY = ["stage=eval", "device=cpu", "logger=none", "progress=false", "eval.seen=[cube]", "eval.unseen=[]",
        "eval.tasks=[slice]", "eval.episodes_per_cell=1", "eval.max_cuts=1", "eval.gifs=0", "eval.videos=0", "eval.num_points=128",
        "eval.cpu_threads=1", "sim.n_grid=20", "sim.cut_substeps=40", "sim.dwell_time=0.0005", "sim.push_time=0.002",
        "sim.settle_time=0.002", "topology.resolution=32"]


def _env(root: Path) -> dict:
    env = dict(os.environ, WANDB_MODE="disabled", TOPOCUT_OUTPUTS=str(root), HYDRA_FULL_ERROR="0",
               PYTHONPATH=os.pathsep.join(p for p in (str(EXAMPLES), os.environ.get("PYTHONPATH")) if p))
    env.pop("CUDA_VISIBLE_DEVICES", None)
    return env


def topocut(root: Path, *overrides: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return run_stage([sys.executable, "-m", "topocut.run", *overrides, f"outputs_root={root}"], cwd=REPO,
                     env=_env(root), timeout=timeout)


@pytest.fixture
def toy_on_path(monkeypatch):
    monkeypatch.syspath_prepend(str(EXAMPLES))


@pytest.fixture
def fake_module(tmp_path, monkeypatch):
    (tmp_path / "byo_fakes.py").write_text(textwrap.dedent("""
        class NoAct:
            def reset(self, goal):
                pass

        class NeedsArgs:
            def __init__(self, ckpt):
                pass
            def reset(self, goal):
                pass
            def act(self, obs):
                return None

        class BadAct:
            def reset(self, goal):
                pass
            def act(self):
                return None

        class ReturnsList:
            def reset(self, goal):
                pass
            def act(self, obs):
                return [0.5, 0.5, 0.0, 0.0]
    """))
    monkeypatch.syspath_prepend(str(tmp_path))
    yield "byo_fakes"
    sys.modules.pop("byo_fakes", None)


def test_import_path_entry_loads_the_class_and_passes_config(toy_on_path):
    ext = registry.load_external(TOY)
    assert ext.cls.__name__ == "GoalPlanePolicy" and ext.display == "Goal plane (example)"
    assert EvalConfig(policies=["oracle", TOY], seen=["cube"], unseen=[]).validate()
    assert registry.display_name(TOY) == "Goal plane (example)"
    assert registry.display_name("nowhere.mod:MyPolicy") == "MyPolicy"  # not importable here: the class part
    from topocut.eval.report import DISPLAY

    assert DISPLAY.get(TOY, TOY) == "Goal plane (example)" and DISPLAY.get("pddp") == "PDDP (Ours)"


def test_run_dir_is_filesystem_safe_and_deterministic():
    assert registry.run_dir("mypkg.sub.module:MyPolicy") == "mypkg-sub-module+MyPolicy"
    assert registry.run_dir("a.b:C") != registry.run_dir("a:b.C")  # one-to-one
    assert registry.run_dir("oracle") == "oracle"


def test_the_policy_sees_the_documented_obs_and_must_return_a_knife_action(toy_on_path, fake_module):
    from topocut.policies.base import OBS_KEYS
    from topocut.sim.action import KnifeAction

    policy = registry.load_external(TOY).build()
    policy.reset(goal=None, seed=3)
    pts = np.random.default_rng(0).uniform(0.4, 0.6, (256, 3)).astype(np.float32)
    goal_labels = (pts[:, 0] > 0.55).astype(np.int32)  # one goal piece: the slab x > 0.55; 0 the rest
    obs = {"points": pts, "labels": np.zeros(256, np.int32), "history": np.zeros((3, 7), np.float32),
           "goal": pts, "goal_labels": goal_labels, "sim_state": object(), "cuts_done": 0}
    action = policy.act(obs)  # the plane between the slab and the rest: x = 0.55, normal along x
    assert isinstance(action, KnifeAction) and abs(action.x - 0.55) < 0.01 and abs(action.yaw) < 0.1, action
    assert policy.act(obs) is None  # one goal piece, one cut: then it ends the episode
    policy.reset(goal=None, seed=3)
    seen = {}
    policy.policy.act = lambda o: seen.update(o) or action
    policy.act(obs)
    assert set(seen) == set(OBS_KEYS)  # sim_state and the like stay with the scripted policies
    bad = registry.load_external(f"{fake_module}:ReturnsList").build()
    with pytest.raises(TypeError, match="KnifeAction"):
        bad.act(obs)


@pytest.mark.parametrize("entry,needle", [
    ("no_such_module_xyz:MyPolicy", "cannot import module 'no_such_module_xyz'"),
    ("byo_fakes:Missing", "has no class 'Missing'; its classes with reset and act: BadAct, NeedsArgs, ReturnsList"),
    ("byo_fakes:NoAct", "has no method act"),
    ("byo_fakes:BadAct", "act(self) cannot be called as act(obs)"),
    ("byo_fakes:NeedsArgs", "constructor NeedsArgs(ckpt) needs arguments"),
    ("byo_fakes:", "is not of the form 'module.path:ClassName'"),
])
def test_bad_entries_name_the_key_the_entry_and_what_is_valid(fake_module, entry, needle):
    with pytest.raises(ValueError) as e:
        EvalConfig(policies=["oracle", entry]).validate()
    msg = str(e.value)
    assert msg.startswith(f"eval.policies: {entry!r}") and needle in msg, msg
    assert "valid: a registered policy (oracle, heuristic" in msg or "raised" in msg, msg


def test_policy_kwargs_reach_the_constructor_and_are_checked(fake_module):
    entry = f"{fake_module}:NeedsArgs"
    cfg = EvalConfig(policies=["oracle", entry], policy_kwargs={"NeedsArgs": {"ckpt": "x.pt"}}).validate()
    assert registry.load_external(entry, kwargs=cfg.policy_kwargs).build(cfg.policy_kwargs).policy is not None
    with pytest.raises(ValueError, match=r"constructor NeedsArgs\(ckpt\) does not take eval.policy_kwargs.NeedsArgs"):
        EvalConfig(policies=["oracle", entry], policy_kwargs={"NeedsArgs": {"steps": 3}}).validate()
    with pytest.raises(ValueError, match=r"eval.policy_kwargs.Other: no eval.policies entry.*\(NeedsArgs\)"):
        EvalConfig(policies=["oracle", entry], policy_kwargs={"NeedsArgs": {"ckpt": 1}, "Other": {}}).validate()


def test_unknown_plain_name_mentions_import_paths():
    with pytest.raises(ValueError, match=r"eval.policies: unknown policy 'dp4'.*dp3.*module.path:ClassName"):
        EvalConfig(policies=["oracle", "dp4"]).validate()


def test_bad_entry_on_the_command_line_exits_2(tmp_path):
    proc = topocut(tmp_path, *TINY, "eval.policies=[oracle,no_such_module_xyz:MyPolicy]")
    out = proc.stdout + proc.stderr
    assert proc.returncode == 2, out[-3000:]
    assert "Traceback" not in out, out[-3000:]
    assert "eval.policies: 'no_such_module_xyz:MyPolicy': cannot import module" in out, out[-3000:]
    assert "module.path:ClassName" in out
    proc = topocut(tmp_path, *TINY, f"eval.policies=[oracle,{TOY}]", "+eval.policy_kwargs.GoalPlanePolicy={depth:1}")
    out = proc.stdout + proc.stderr
    assert proc.returncode == 2 and "Traceback" not in out, out[-3000:]
    assert "does not take eval.policy_kwargs.GoalPlanePolicy={'depth': 1}" in out, out[-3000:]


def test_smoke_evaluation_of_the_toy_policy_beside_the_oracle(tmp_path):
    proc = topocut(tmp_path, *TINY, f"eval.policies=[oracle,{TOY}]")
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-4000:]
    (path,) = (tmp_path / "eval" / "table1").glob("v*")
    run = registry.run_dir(TOY)
    (episode,) = (path / "episodes" / run).glob("*.json")
    assert json.loads(episode.read_text())["status"] == "ok"
    with open(path / "results.csv") as f:
        rows = [r for r in csv.DictReader(f) if r["policy"] == TOY]
    assert rows and all(r["compared_to"] == "oracle" and r["episodes"] == "1" for r in rows)
    # it cuts where the goal's first slab ends, so it earns some reward (the example once scored 0 everywhere)
    (overall,) = [r for r in rows if r["task"] == "all"]
    assert float(overall["R_mean"]) > 0, overall
    assert "Goal plane (example)" in (path / "results.md").read_text()
    runs = json.loads((path / "policies.json").read_text())
    assert runs[run]["policy"] == TOY and runs[run]["display"] == "Goal plane (example)"
    manifest = json.loads((path / "manifest.json").read_text())
    assert manifest["inputs"][run].startswith(f"policy/{TOY}@")  # its source keys the evaluation

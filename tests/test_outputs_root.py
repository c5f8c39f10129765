"""A relative outputs root is taken from the repository root, not the current directory (issue #48): a stage run
from another directory wrote a second outputs tree there, which the next stage, run from the repository, never
saw.  The resolved root is said once at startup (README.md, "Where outputs go")."""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

from tests.stage_runner import run as run_stage
from topocut.run import OUTPUTS_ENV, REPO_ROOT, absolute_outputs_root

REPO = Path(__file__).resolve().parents[1]


def test_repo_root_is_this_checkout():
    assert REPO_ROOT == REPO


def test_a_relative_override_or_variable_is_made_absolute_against_the_repo_root():
    env = {OUTPUTS_ENV: "elsewhere"}
    argv, note = absolute_outputs_root(["stage=mppi", "outputs_root=runs/a"], env)
    assert argv == ["stage=mppi", f"outputs_root={REPO / 'runs' / 'a'}"] and "outputs_root=runs/a is relative" in note
    assert env == {OUTPUTS_ENV: "elsewhere"}  # the override wins; the variable is not read
    argv, note = absolute_outputs_root(["++outputs_root=../x"], {})
    assert argv == [f"++outputs_root={REPO.parent / 'x'}"]  # normalised, prefix kept
    env = {OUTPUTS_ENV: "out2"}
    assert absolute_outputs_root(["stage=eval"], env) == (["stage=eval"], f"{OUTPUTS_ENV}=out2 is relative: taken "
                                                          f"from the repository root {REPO}")
    assert env[OUTPUTS_ENV] == str(REPO / "out2")
    env = {}  # the default `outputs`: the repository's, wherever the command runs; nothing to say
    assert absolute_outputs_root(["stage=eval"], env) == (["stage=eval"], "")
    assert env[OUTPUTS_ENV] == str(REPO / "outputs")


def test_absolute_and_interpolated_roots_are_left_alone(tmp_path):
    for argv in ([f"outputs_root={tmp_path}"], ["outputs_root=${oc.env:HOME}/o"]):
        env = {OUTPUTS_ENV: "rel"}
        assert absolute_outputs_root(argv, env) == (argv, "") and env == {OUTPUTS_ENV: "rel"}
    env = {OUTPUTS_ENV: str(tmp_path)}
    assert absolute_outputs_root([], env) == ([], "") and env[OUTPUTS_ENV] == str(tmp_path)


def test_a_run_from_another_directory_writes_under_the_repo_relative_root(tmp_path):
    """TOPOCUT_OUTPUTS relative to the repository root (it climbs out to a pytest directory, so nothing lands in
    the checkout), the command run from an unrelated directory: the run's status.json is written under the
    resolved root, nothing under the current directory, and the first line of the log says where."""
    root, cwd = tmp_path / "outputs", tmp_path / "cwd"
    cwd.mkdir()
    rel = os.path.relpath(root, REPO)
    env = dict(os.environ, WANDB_MODE="disabled", HYDRA_FULL_ERROR="0", **{OUTPUTS_ENV: rel},
               PYTHONPATH=os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH")) if p))
    # a missing input: the cheapest stage run there is (exit 2 before any work), and it still writes status.json
    proc = run_stage([sys.executable, "-m", "topocut.run", "stage=pretrain", "data.version=v999", "logger=none"],
                     cwd=cwd, env=env, timeout=120)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 2 and "MissingArtifact" in out, out[-3000:]
    (status,) = (root / "runs" / "pretrain").glob("*/status.json")
    assert json.loads(status.read_text())["status"] == "failed"
    assert list(cwd.iterdir()) == []
    said = [ln for ln in out.splitlines() if "outputs: " in ln]
    assert len(said) == 1 and f"outputs: {root} ({OUTPUTS_ENV}={rel} is relative: taken from the repository " \
        f"root {REPO})" in said[0], out[-3000:]

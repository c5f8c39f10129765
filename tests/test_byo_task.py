"""Issue #50: a task of your own is one file.  A toy knife task (halve the object across its longer axis) is
written to a temporary module, named on the command line as ``module.path:ClassName`` beside the toy policy of
examples/my_policy.py, and evaluated by `python -m topocut.run stage=eval` at smoke scale: its goal is what its
one plane makes, so the oracle (its own step) earns full marks and the table shows the new task's column."""
from __future__ import annotations

import csv
import json
import textwrap

import numpy as np
import pytest

from tests.test_byo_policy import TINY, TOY, topocut
from topocut.tasks import REGISTRY, TaskConfig, get_task, make_goal

TOY_TASK = textwrap.dedent('''
    """Halve: one cut across the object's longer axis, through its middle; the goal piece is the +a1 half."""
    import numpy as np

    from topocut.tasks.base import KnifeTask, plane


    class HalveTask(KnifeTask):
        name = "halve"
        defaults = {"success_threshold": 0.5}  # the task's parameters (TaskConfig fields) on the task

        def pieces(self, cfg, pts, axes, pad, spacing, board_z):
            s = pts @ axes[0]
            mid = 0.5 * (s.min() + s.max())
            point = pts.mean(0) + (mid - pts.mean(0) @ axes[0]) * axes[0]
            return [plane(axes[0], point, board_z)], (s > mid).astype(np.int32)
''')
ENTRY = "toy_tasks:HalveTask"


@pytest.fixture
def toy_task(tmp_path, monkeypatch):
    (tmp_path / "mods").mkdir()
    (tmp_path / "mods" / "toy_tasks.py").write_text(TOY_TASK)
    monkeypatch.syspath_prepend(str(tmp_path / "mods"))
    yield tmp_path / "mods"
    REGISTRY.pop(ENTRY, None)


def test_an_import_path_registers_the_task_under_its_entry(toy_task):
    task = get_task(ENTRY)
    assert task.name == ENTRY and REGISTRY[ENTRY] is task
    goal = make_goal(TaskConfig(name=ENTRY, max_cuts=1), "cube", spacing=0.01)
    assert goal.task == ENTRY and len(goal.planes) == 1
    s = goal.points @ goal.axes[0]  # the goal piece is the +a1 half: as many points above the middle as labelled
    mid = 0.5 * (s.min() + s.max())
    assert abs(float(np.mean(goal.labels > 0)) - float(np.mean(s > mid))) < 0.05


def test_unknown_entries_name_what_is_valid():
    with pytest.raises(ValueError, match="slice, stick, dice, pyramid, cream_writing, scooping, or a task class"):
        get_task("no_such_task")
    with pytest.raises(ValueError, match="cannot import Nope from 'no_such_module_xyz'"):
        get_task("no_such_module_xyz:Nope")


def test_smoke_evaluation_of_the_toy_task_with_the_toy_policy(tmp_path, toy_task, monkeypatch):
    monkeypatch.setenv("PYTHONPATH", str(toy_task))  # topocut() adds examples/ (the toy policy) in front
    args = [a for a in TINY if not a.startswith("eval.tasks=")]
    proc = topocut(tmp_path / "out", *args, f"eval.tasks=[{ENTRY}]", f"eval.policies=[oracle,{TOY}]")
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-4000:]
    (path,) = (tmp_path / "out" / "eval" / "table1").glob("v*")
    with open(path / "results.csv") as f:
        rows = [r for r in csv.DictReader(f) if r["task"] == ENTRY and r["object"] == "all" and r["split"] == "in"]
    by_policy = {r["policy"]: r for r in rows}
    assert set(by_policy) == {"oracle", TOY}, rows
    assert float(by_policy["oracle"]["R_mean"]) > 0.9, by_policy["oracle"]  # the reference earns full marks
    episodes = [json.loads(p.read_text()) for p in (path / "episodes").rglob("*.json")]
    assert episodes and all(e["spec"]["task"] == ENTRY for e in episodes)
    assert f"ID {ENTRY} R̂" in (path / "results.md").read_text()  # the table has the new task's column

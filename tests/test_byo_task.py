"""Issue #50: a task of your own is one file.  A toy knife task (halve the object across its longer axis) is
written to a temporary module with the dataclass of its parameters beside it (``config = HalveConfig``), named on
the command line as ``module.path:ClassName`` beside the toy policy of examples/my_policy.py, and evaluated by
`python -m topocut.run stage=eval` at smoke scale: its goal is what its one plane makes, so the oracle (its own
step) earns full marks and the table shows the new task's column.  A class that declares no dataclass runs on
KnifeTask's (KnifeTaskConfig) with its ``defaults`` over it."""
from __future__ import annotations

import csv
import json
import textwrap

import numpy as np
import pytest

from tests.test_byo_policy import TINY, TOY, topocut
from topocut.tasks import REGISTRY, get_task, make_goal, task_config

TOY_TASK = textwrap.dedent('''
    """Halve: one cut across the object's longer axis; the goal piece is its +a1 end, ``fraction`` of its length."""
    from dataclasses import dataclass

    import numpy as np

    from topocut.tasks.base import KnifeTask, plane
    from topocut.tasks.config import KnifeTaskConfig


    @dataclass
    class HalveConfig(KnifeTaskConfig):
        fraction: float = 0.5  # the goal piece's share of the object's length, from its +a1 end
        max_cuts: int = 1

        def validate(self):
            super().validate()
            if not 0 < self.fraction < 1:
                raise ValueError(f"task.fraction={self.fraction} must lie in (0, 1)")
            return self


    def cut_at(pts, axes, board_z, fraction):
        s = pts @ axes[0]
        at = s.max() - fraction * (s.max() - s.min())
        point = pts.mean(0) + (at - pts.mean(0) @ axes[0]) * axes[0]
        return [plane(axes[0], point, board_z)], (s > at).astype(np.int32)


    class HalveTask(KnifeTask):
        name = "halve"
        config = HalveConfig  # its parameters: KnifeTaskConfig's and a fraction

        def pieces(self, cfg, pts, axes, pad, spacing, board_z):
            return cut_at(pts, axes, board_z, cfg.fraction)


    class PlainHalveTask(KnifeTask):
        """No dataclass of its own: KnifeTask's KnifeTaskConfig, with its ``defaults`` over it."""

        name = "plain_halve"
        defaults = {"max_cuts": 1, "success_threshold": 0.4}

        def pieces(self, cfg, pts, axes, pad, spacing, board_z):
            return cut_at(pts, axes, board_z, 0.5)
''')
ENTRY = "toy_tasks:HalveTask"
PLAIN = "toy_tasks:PlainHalveTask"


@pytest.fixture
def toy_task(tmp_path, monkeypatch):
    (tmp_path / "mods").mkdir()
    (tmp_path / "mods" / "toy_tasks.py").write_text(TOY_TASK)
    monkeypatch.syspath_prepend(str(tmp_path / "mods"))
    yield tmp_path / "mods"
    REGISTRY.pop(ENTRY, None)
    REGISTRY.pop(PLAIN, None)


def test_an_import_path_registers_the_task_under_its_entry(toy_task):
    task = get_task(ENTRY)
    assert task.name == ENTRY and REGISTRY[ENTRY] is task
    goal = make_goal(task_config(ENTRY, max_cuts=1), "cube", spacing=0.01)
    assert goal.task == ENTRY and len(goal.planes) == 1
    s = goal.points @ goal.axes[0]  # the goal piece is the +a1 half: as many points above the middle as labelled
    mid = 0.5 * (s.min() + s.max())
    assert abs(float(np.mean(goal.labels > 0)) - float(np.mean(s > mid))) < 0.05


def test_a_task_of_your_own_declares_its_parameters_as_the_builtins_do(toy_task):
    """Its dataclass is what task_config builds (its own keys, and a key it lacks refused naming them); a class
    without one gets KnifeTaskConfig and its ``defaults``."""
    from topocut.config import ConfigError
    from topocut.eval.runner import task_configs
    from topocut.tasks import KnifeTaskConfig

    cfg = task_config(ENTRY, fraction=0.25)
    assert type(cfg).__name__ == "HalveConfig" and cfg.name == ENTRY and cfg.max_cuts == 1
    goal = make_goal(cfg, "cube", spacing=0.01)
    assert abs(float(np.mean(goal.labels > 0)) - 0.25) < 0.05  # the task reads its own key
    with pytest.raises(ValueError, match=r"task\.fraction=1\.5 must lie in \(0, 1\)"):
        task_config(ENTRY, fraction=1.5).validate()
    with pytest.raises(ConfigError, match=r"task\.thickness: unknown key \(a key of task=slice, stick\); valid keys "
                                          r"of task \(HalveConfig\): .*sample_tilt, fraction$"):
        task_config(ENTRY, thickness=0.05)
    plain = task_config(PLAIN)
    assert type(plain) is KnifeTaskConfig and (plain.name, plain.max_cuts, plain.success_threshold) == (PLAIN, 1, 0.4)
    evaluated = task_configs([ENTRY, PLAIN], max_cuts=2)  # what stage=eval runs: the budget is eval.max_cuts
    assert evaluated[ENTRY].fraction == 0.5 and evaluated[PLAIN].success_threshold == 0.4


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

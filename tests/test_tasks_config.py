"""The additional tasks (cream_writing, scooping) compose with every stage and are refused, naming the keys,
where they have no pipeline; their fields are validated."""
from pathlib import Path

import pytest

from tests.stage_runner import run as run_stage
from tests.test_config import CONF, _compose  # conf/'s composer (test_config registers the config schemas)
from topocut.config import STAGES, ConfigError, validate
from topocut.tasks import TASKS, PenConfig, TaskConfig, get_task, task_config

# the tasks that run with some stages only (their conf/task yaml fills task.stage from stage.name)
PARTIAL = sorted(n for n in TASKS if set(STAGES) - set(get_task(n).stages))


@pytest.mark.parametrize("task", PARTIAL)
@pytest.mark.parametrize("stage", STAGES)
def test_new_tasks_run_only_with_their_stages(stage, task):
    assert PARTIAL == ["cream_writing", "scooping"]
    cfg = _compose(f"stage={stage}", f"task={task}", "logger=none")
    assert cfg.task.stage == stage  # interpolated from stage.name
    if stage in get_task(task).stages:
        validate(cfg)
    else:
        with pytest.raises(ConfigError, match=rf"task={task} runs with stage in \(.*\) only, got stage={stage} "
                                              rf"\(stage\.name\).*slice, stick, dice, pyramid"):
            validate(cfg)


def test_pyramid_samples_tilt_and_writing_fields_are_checked():
    assert _compose("task=pyramid").task.sample_tilt is True
    with pytest.raises(ValueError, match=r"task\.word='CORX'.*\['X'\].*valid letters: .*C.*L.*O.*R"):
        task_config("cream_writing", word="CORX").validate()
    with pytest.raises(ValueError, match=r"task\.pen\.extrude_speed=0"):
        task_config("cream_writing", pen=PenConfig(extrude_speed=0)).validate()
    with pytest.raises(ConfigError, match=r"task\.spoon\.depth"):
        validate(_compose("task=scooping", "task.spoon.depth=0.5"))
    with pytest.raises(ConfigError, match=r"task\.spoon\.cup_center.*inside the block"):
        validate(_compose("task=scooping", "task.spoon.cup_center=[0.4,0.5]"))


# -- issue #50: each task its own dataclass, the task group backed by it -------------------------------------------
def test_each_task_config_is_its_dataclass_with_the_yaml_defaults():
    """task_config(name) is the task's own dataclass (DiceConfig for dice), holding what conf/task/<name>.yaml
    composes to where no scale changes it (scale=paper): the dataclass's defaults are the task's defaults."""
    from omegaconf import OmegaConf

    from topocut.tasks.dice import DiceConfig

    dice = task_config("dice")
    assert type(dice) is DiceConfig and (dice.size, dice.push, dice.max_cuts) == (0.03, True, 5)
    assert not hasattr(dice, "thickness") and not hasattr(dice, "width")  # dice reads its size alone
    for name in TASKS:
        composed = OmegaConf.to_object(_compose(f"task={name}", "scale=paper").task)
        assert type(composed) is get_task(name).config
        composed.stage = ""  # conf/task fills the stage from stage.name (cream writing, scooping)
        assert composed == task_config(name), name


def test_a_key_of_another_task_is_refused_naming_the_tasks_own_keys():
    """A key the task does not read is no key of its: refused while composing (and as `+task.key`, which Hydra
    would add silently), by task_config and by eval.task_overrides, each time listing the task's own keys."""
    from hydra.errors import ConfigCompositionException

    from topocut.config import check_known_keys, composition_error
    from topocut.eval.config import EvalConfig

    own = "name, success_threshold, stage, max_cuts, push, num_goal_points, sample_tilt, size"
    with pytest.raises(ConfigCompositionException) as e:
        _compose("task=pyramid", "task.width=0.05")
    assert str(composition_error(e.value)) == (f"task.width: unknown key (a key of task=stick); valid keys of "
                                               f"task=pyramid (PyramidConfig): {own}")
    with pytest.raises(ConfigError, match=rf"task\.width: unknown key .*valid keys of task=pyramid.*: {own}$"):
        check_known_keys(_compose("task=pyramid", "+task.width=0.05"))
    with pytest.raises(ConfigError, match=r"task\.thickness: unknown key \(a key of task=slice, stick\); valid keys "
                                          r"of task=dice \(DiceConfig\): .*sample_tilt, size$"):
        task_config("dice", thickness=0.05)
    with pytest.raises(ConfigError, match=r"task\.max_cuts: unknown key .*task=cream_writing.*word, letter_height"):
        task_config("cream_writing", max_cuts=2)  # no knife, no cut budget
    with pytest.raises(ValueError, match=r"eval\.task_overrides\.dice\.thickness: not a parameter of task=dice; "
                                         r"valid keys of DiceConfig: .*size"):
        EvalConfig(task_overrides={"dice": {"thickness": 0.05}}).validate()
    EvalConfig(task_overrides={"dice": {"size": 0.05}, "stick": {"width": 0.05}}).validate()
    with pytest.raises(ValueError, match=r"task\.name='dice' takes a DiceConfig, got a TaskConfig"):
        TaskConfig(name="dice").validate()  # the base has no size: dice could not run on it


def test_a_key_of_another_task_on_the_command_line_is_one_line_and_exit_2():
    """`--cfg job` composes as a run does: the same one-line message, exit status 2, no traceback."""
    import sys

    proc = run_stage([sys.executable, "-m", "topocut.run", "task=pyramid", "task.width=0.05", "--cfg", "job"],
                     cwd=Path(CONF).parent, timeout=120)
    assert proc.returncode == 2, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr and proc.stderr.strip().count("\n") == 0, proc.stderr
    assert proc.stderr.startswith("ConfigError: task.width: unknown key"), proc.stderr
    assert "valid keys of task=pyramid (PyramidConfig): name, success_threshold" in proc.stderr

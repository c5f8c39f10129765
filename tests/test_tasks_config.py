"""The additional tasks (cream_writing, scooping) compose with every stage and are refused, naming the keys,
where they have no pipeline; their fields are validated."""
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from topocut.config import STAGES, ConfigError, register_configs, validate
from topocut.tasks import TASKS, get_task
from topocut.tasks.config import TaskConfig

CONF = str(Path(__file__).resolve().parents[1] / "conf")
register_configs()
# the tasks that run with some stages only (their conf/task yaml fills task.stage from stage.name)
PARTIAL = sorted(n for n in TASKS if set(STAGES) - set(get_task(n).stages))


def _compose(*overrides):
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


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
        TaskConfig(name="cream_writing", word="CORX").validate()
    with pytest.raises(ValueError, match=r"task\.pen\.extrude_speed=0"):
        TaskConfig(name="cream_writing", pen=TaskConfig().pen.__class__(extrude_speed=0)).validate()
    with pytest.raises(ConfigError, match=r"task\.spoon\.depth"):
        validate(_compose("task=scooping", "task.spoon.depth=0.5"))
    with pytest.raises(ConfigError, match=r"task\.spoon\.cup_center.*inside the block"):
        validate(_compose("task=scooping", "task.spoon.cup_center=[0.4,0.5]"))

"""Task configuration (paper §4 task setup and the appendix's additional tasks; docs/reward.md#goals, docs/tasks.md).

``TaskConfig`` holds what every task has (its name, its success threshold, the stage running it); each task
module declares its own subclass beside its task class, with only the parameters that task reads
(``SliceConfig.thickness``, ``DiceConfig.size``, ``CreamWritingConfig.pen``, ...), and names it on the class
(``config = DiceConfig``).  ``KnifeTaskConfig`` adds what every knife task's code reads (the cut budget, the push,
the goal's points, MPPI's tilt), so the knife tasks subclass it and cream writing and scooping do not.  A key is
therefore accepted only by the tasks that read it: ``task=pyramid task.width=0.05`` is refused naming the
pyramid's keys (topocut.config.unknown_key_error).  ``topocut.tasks.task_config(name, **params)`` builds the
registered task's config; Hydra's ``task`` group is backed by the same dataclasses (``base_<task>`` in
topocut.config.register_configs), so a dataclass's defaults are the task's defaults.

What a task needs besides its parameters is the task's to say (``topocut.tasks.get_task(name)``): its stages
(``check_stage`` refuses the others: cream writing has simulate and mppi, scooping simulate) and its fewest cuts
(``min_cuts``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from topocut.sim.tools import PenConfig, SpoonConfig  # noqa: F401 - re-exported: the tools' settings live with the simulator
from topocut.utils.checks import check_positive

CUTTING_TASKS = ("slice", "stick", "dice", "pyramid")
TASKS = CUTTING_TASKS + ("cream_writing", "scooping")  # the registry's names (topocut.tasks.get_task)
SIZE_KEYS = ("thickness", "width", "size")  # the knife tasks' piece sizes, each on the tasks that read it


@dataclass
class TaskConfig:
    """What every task has; a task's own parameters live on its subclass (topocut/tasks/<task>.py)."""

    name: str = ""  # slice | stick | dice | pyramid | cream_writing | scooping | module.path:ClassName
    # the least total spectral reward (in [0, r_max]) a success needs: knife tasks also need every goal piece made
    # (N_C = G; KnifeTask.success, docs/tasks.md#success); cream writing and scooping the total alone (0.95)
    success_threshold: float = 0.5
    # the stage running this task: conf/task/{cream_writing,scooping}.yaml fill it from ${stage.name} so that
    # validate() refuses a stage without a pipeline for the task ("" = not checked)
    stage: str = ""
    # the task's parameters that must be > 0 (its pieces' sizes, the letters' height): validate() refuses them
    # naming the key; a class attribute, not a config key
    positive: ClassVar[tuple[str, ...]] = ()

    def validate(self) -> TaskConfig:
        """The checks every task shares; a subclass adds its own parameters' after calling this."""
        from topocut.tasks import task_config_class

        want = task_config_class(self.name)  # unknown names fail here with the list of tasks
        if not isinstance(self, want):  # e.g. TaskConfig(name="dice"): it has no size, so dice could not run
            raise ValueError(f"task.name={self.name!r} takes a {want.__name__}, got a {type(self).__name__}; build "
                             f"it with topocut.tasks.task_config({self.name!r}, ...)")
        if self.stage:
            check_stage(self.stage, self.name)
        self.check_positive(*self.positive)
        return self

    def check_positive(self, *keys: str) -> None:
        """Refuse a parameter <= 0 (the pieces' sizes, the letters' height), naming its key."""
        check_positive("task", self, keys)


@dataclass
class KnifeTaskConfig(TaskConfig):
    """What the knife tasks' shared code reads (topocut.tasks.base.KnifeTask, the stages, MPPI, the envs): every
    knife task has these, the pen's and the spoon's tasks none of them."""

    max_cuts: int = 5  # cuts per episode; also bounds the number of goal pieces
    # after each cut the blade slides the cut-off side aside (stick and dice in the paper); read for every knife
    # task (KnifeTask.make_goal orders the cuts push-safe, the stages and the envs push), so not one task's own
    push: bool = False
    num_goal_points: int = 2048  # Goal.points/labels are FPS-downsampled to this many points (0: keep all)
    # MPPI also samples the knife tilt (pipelines/mppi.py, topocut.envs): the pyramid's goal plane is tilted, but
    # any knife task's planner can sample it, so the key is the knife tasks', set true by the pyramid's config
    sample_tilt: bool = False

    def validate(self) -> KnifeTaskConfig:
        super().validate()
        if self.max_cuts < 1:  # the task's own minimum (min_cuts): topocut.config.validate and make_goal
            raise ValueError(f"task.max_cuts={self.max_cuts} must be >= 1")
        if self.num_goal_points < 0:
            raise ValueError(f"task.num_goal_points={self.num_goal_points} must be >= 0")
        return self


def check_max_cuts(max_cuts: int, task) -> None:
    """Refuse a cut budget below the task's ``min_cuts`` (dice with 2 cuts cannot free a die)."""
    if max_cuts < task.min_cuts:
        raise ValueError(f"task.max_cuts={max_cuts} is too few for task={task.name}: it needs at least "
                         f"{task.min_cuts} ({task.min_cuts_why}); set task.max_cuts>={task.min_cuts}")


def check_stage(stage: str, task: str) -> None:
    """Refuse stage x task combinations without a pipeline (e.g. stage=bc task=scooping): the task's ``stages``."""
    from topocut.tasks import get_task

    allowed = get_task(task).stages
    if stage not in allowed:
        others = [n for n in TASKS if stage in get_task(n).stages]
        raise ValueError(f"task={task} runs with stage in ({', '.join(allowed)}) only, got stage={stage} "
                         f"(stage.name); tasks for stage={stage}: {', '.join(others) or 'none'}")

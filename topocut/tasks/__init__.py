"""Tasks: one module per task (slice, stick, dice, pyramid, cream_writing, scooping), a Task protocol and a
registry.  Each task owns its goal construction (``make_goal``), its oracle sequence (``oracle``: Cut and
Turn steps), its success condition (``success``) and its scene set-up (``scene``); callers ask
``get_task(name)`` instead of branching on the name (docs/tasks.md).
"""
from __future__ import annotations

from topocut.tasks.base import Cut, Goal, KnifeTask, Task, Turn, object_axes, truncate_steps, turns_after
from topocut.tasks.config import (
    CUTTING_TASKS,
    TASKS,
    PenConfig,
    SpoonConfig,
    TaskConfig,
    check_max_cuts,
    check_stage,
)

_MODULES = {"slice": "slice", "stick": "stick", "dice": "dice", "pyramid": "pyramid",
            "cream_writing": "cream_writing", "scooping": "scooping"}


def get_task(name) -> Task:
    """The task object of ``name`` (a str or a TaskConfig); unknown names fail with the list of tasks."""
    import importlib

    name = getattr(name, "name", name)
    if name not in _MODULES:
        raise ValueError(f"task.name={name!r}; valid: {', '.join(TASKS)}")
    return importlib.import_module(f"topocut.tasks.{_MODULES[name]}").TASK


REGISTRY = _MODULES  # name -> module under topocut.tasks


def task_for_stage(task, stage: str) -> Task:
    """The task object of ``task`` (a name or a TaskConfig) for stage ``stage``: a stage the task has no pipeline
    for is refused (ValueError naming task and stage.name, and the tasks that run it)."""
    check_stage(stage, getattr(task, "name", task))
    return get_task(task)


def make_goal(task, object: str, pose=None, spacing: float = 0.008, board_z: float = 0.05, seed: int = 0,
              skin_thickness: float = 0.01) -> Goal:
    """The ideal goal of a knife task (slice, stick, dice, pyramid) on ``object`` at ``pose``."""
    task = (task or TaskConfig()).validate()  # unknown names fail here with the list of tasks
    t = get_task(task.name)
    if t.tool != "knife":
        raise ValueError(f"task.name={task.name!r} has no knife goal; make_goal takes {', '.join(CUTTING_TASKS)} "
                         f"(cream_writing, scooping: topocut.tasks.get_task(name).make_goal)")
    return t.make_goal(task, object, pose, spacing, board_z, seed, skin_thickness)


TASK_STAGES = {name: get_task(name).stages for name in TASKS}  # the stages each task runs with (its ``stages``)

__all__ = ["TASKS", "CUTTING_TASKS", "TASK_STAGES", "TaskConfig", "PenConfig", "SpoonConfig", "check_stage",
           "check_max_cuts", "Goal", "Cut", "Turn", "Task", "KnifeTask", "get_task", "task_for_stage", "make_goal",
           "object_axes", "truncate_steps", "turns_after", "REGISTRY"]

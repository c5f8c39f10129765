"""Tasks: one module per task (slice, stick, dice, pyramid, cream_writing, scooping), a Task protocol and a
registry.  Each task module registers its task class (``@register_task``); the task owns its goal construction
(``make_goal``), its oracle sequence (``oracle``: Cut and Turn steps), its success condition (``success``) and
which tool its scene holds (``tool``); callers ask ``get_task(name)`` instead of branching on the name
(docs/tasks.md).  A task of your own is a class named ``module.path:ClassName`` (docs/architecture.md).
"""
from __future__ import annotations

from topocut.tasks.base import (
    REGISTRY,
    Cut,
    Goal,
    KnifeTask,
    Task,
    Turn,
    object_axes,
    register_task,
    truncate_steps,
    turns_after,
)
from topocut.tasks.config import (
    CUTTING_TASKS,
    TASKS,
    PenConfig,
    SpoonConfig,
    TaskConfig,
    check_max_cuts,
    check_stage,
)
from topocut.utils.import_path import is_import_path

BUILTIN = {name: f"topocut.tasks.{name}" for name in TASKS}  # each module registers its task on import


is_task_path = is_import_path  # a task class of your own (docs/architecture.md, "Extending")


def get_task(name) -> Task:
    """The task object of ``name`` (a str or a TaskConfig): a registered name (the built-in modules import on
    first use), or ``module.path:ClassName``, which imports the module and registers the class under that entry
    (its episodes, goals and tables carry the entry as the task's name).  Anything else fails naming what is valid."""
    import importlib

    name = getattr(name, "name", name)
    if name not in REGISTRY:
        if name in BUILTIN:
            importlib.import_module(BUILTIN[name])
        elif is_task_path(name):
            _register_path(name)
    if name not in REGISTRY:
        raise ValueError(f"task.name={name!r}; valid: {', '.join(TASKS)}, or a task class of your own as "
                         f"module.path:ClassName (docs/architecture.md)")
    return REGISTRY[name]


def _register_path(entry: str) -> None:
    import importlib

    module_name, _, cls_name = entry.partition(":")
    try:
        cls = getattr(importlib.import_module(module_name), cls_name)
    except (ImportError, AttributeError) as e:
        raise ValueError(f"task {entry!r}: cannot import {cls_name} from {module_name!r} ({e}); the module must be "
                         f"importable (PYTHONPATH) and define the class") from None
    task = cls()
    task.name = entry  # goals, episodes and tables name the task by its entry
    REGISTRY[entry] = task


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
           "object_axes", "truncate_steps", "turns_after", "REGISTRY", "register_task", "is_task_path", "BUILTIN"]

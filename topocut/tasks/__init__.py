"""Tasks: one module per task (slice, stick, dice, pyramid, cream_writing, scooping), a Task protocol and a
registry.  Each task module registers its task class (``@register_task``) and declares beside it the dataclass of
its parameters (``config = DiceConfig``: only what the task reads); the task owns its goal construction
(``make_goal``), its oracle sequence (``oracle``: Cut and Turn steps), its success condition (``success``) and
which tool its scene holds (``tool``); callers ask ``get_task(name)`` instead of branching on the name, and build
a task's parameters with ``task_config(name, **params)`` (docs/tasks.md).  A task of your own is a class named
``module.path:ClassName`` (docs/architecture.md).
"""
from __future__ import annotations

import dataclasses

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
    SIZE_KEYS,
    TASKS,
    KnifeTaskConfig,
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


def task_config_class(name) -> type:
    """The dataclass of task ``name``'s parameters: the class's ``config`` (TaskConfig when it declares none)."""
    return getattr(get_task(name), "config", None) or TaskConfig


def task_keys(name) -> list[str]:
    """The keys task ``name`` takes (its dataclass's fields), in declaration order."""
    return [f.name for f in dataclasses.fields(task_config_class(name))]


def task_config(name: str, **params) -> TaskConfig:
    """Task ``name``'s parameters: its dataclass (``config``: DiceConfig for dice) with the class's ``defaults``
    (a task of your own may give them instead of a dataclass) and then ``params`` over its defaults.  A key the
    task does not have is refused naming the task's keys (``task_config("dice", thickness=0.05)``: dice reads
    ``size`` alone); the result is not validated (``.validate()``)."""
    task = get_task(name)
    cls = task_config_class(name)
    given = {**dict(getattr(task, "defaults", None) or {}), **params}
    bad = [k for k in given if k not in task_keys(name)]
    if bad:
        from topocut.config import unknown_key_error  # a ConfigError (ValueError): exit status 2 from a stage

        raise unknown_key_error(f"task.{bad[0]}", cls)
    return cls(**{**given, "name": task.name})


def piece_sizes(name, size: float) -> dict:
    """``{key: size}`` for each piece size task ``name`` has (SIZE_KEYS: slice a thickness, stick a thickness and a
    width, dice and the pyramid a size, the others none): one size for whichever task, as a sweep over tasks sets it
    (``task_config(name, **piece_sizes(name, 0.05))``)."""
    return {k: size for k in SIZE_KEYS if k in task_keys(name)}


def tasks_with_key(key: str) -> list[str]:
    """The built-in tasks whose config has ``key`` (for the message refusing it on another task)."""
    return [n for n in TASKS if key in task_keys(n)]


def task_for_stage(task, stage: str) -> Task:
    """The task object of ``task`` (a name or a TaskConfig) for stage ``stage``: a stage the task has no pipeline
    for is refused (ValueError naming task and stage.name, and the tasks that run it)."""
    check_stage(stage, getattr(task, "name", task))
    return get_task(task)


def make_goal(task, object: str, pose=None, spacing: float = 0.008, board_z: float = 0.05, seed: int = 0,
              skin_thickness: float = 0.01) -> Goal:
    """The ideal goal of a knife task (slice, stick, dice, pyramid) on ``object`` at ``pose``."""
    task = (task or task_config("slice")).validate()  # unknown names fail here with the list of tasks
    t = get_task(task.name)
    if t.tool != "knife":
        raise ValueError(f"task.name={task.name!r} has no knife goal; make_goal takes {', '.join(CUTTING_TASKS)} "
                         f"(cream_writing, scooping: topocut.tasks.get_task(name).make_goal)")
    return t.make_goal(task, object, pose, spacing, board_z, seed, skin_thickness)


TASK_STAGES = {name: get_task(name).stages for name in TASKS}  # the stages each task runs with (its ``stages``)

__all__ = ["TASKS", "CUTTING_TASKS", "TASK_STAGES", "TaskConfig", "KnifeTaskConfig", "task_config",
           "task_config_class", "task_keys", "tasks_with_key", "piece_sizes", "SIZE_KEYS", "PenConfig", "SpoonConfig", "check_stage",
           "check_max_cuts", "Goal", "Cut", "Turn", "Task", "KnifeTask", "get_task", "task_for_stage", "make_goal",
           "object_axes", "truncate_steps", "turns_after", "REGISTRY", "register_task", "is_task_path", "BUILTIN"]

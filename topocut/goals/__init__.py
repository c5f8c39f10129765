"""Goal shapes of the tasks: ideal pieces and cut planes of the cutting tasks (slice, stick, dice, pyramid),
letter point clouds of cream writing (topocut.goals.letters); task configuration (topocut.goals.config)."""
from topocut.goals.config import CUTTING_TASKS, TASK_STAGES, TASKS, PenConfig, SpoonConfig, TaskConfig, check_stage
from topocut.goals.shapes import Goal, object_axes
from topocut.goals.shapes import make_goal as _make_cutting_goal


def make_goal(task, object: str, pose=None, spacing: float = 0.008, board_z: float = 0.05, seed: int = 0,
              skin_thickness: float = 0.01) -> Goal:
    """The ideal goal of a cutting task (topocut.goals.shapes.make_goal); other tasks have their own goals."""
    if task is not None:
        task.validate()  # unknown names fail here with the list of tasks
    name = getattr(task, "name", "slice")
    if name not in CUTTING_TASKS:
        raise ValueError(f"task.name={name!r} has no knife goal; make_goal takes {', '.join(CUTTING_TASKS)} "
                         f"(cream_writing: topocut.goals.letters.word_goal; scooping: topocut.planning.scoop.target_chunk)")
    return _make_cutting_goal(task, object, pose, spacing, board_z, seed, skin_thickness)


__all__ = ["TASKS", "CUTTING_TASKS", "TASK_STAGES", "TaskConfig", "PenConfig", "SpoonConfig", "check_stage", "Goal",
           "make_goal", "object_axes"]

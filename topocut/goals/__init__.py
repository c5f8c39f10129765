"""Goal shapes of the cutting tasks (slice, stick, dice, pyramid): ideal pieces and ideal cut planes."""
from topocut.goals.config import TASKS, TaskConfig
from topocut.goals.shapes import Goal, make_goal, object_axes

__all__ = ["TASKS", "TaskConfig", "Goal", "make_goal", "object_axes"]

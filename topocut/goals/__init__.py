"""Goal shapes of the tasks: a thin re-export of ``topocut.tasks`` (kept so that old imports work).

``make_goal``, ``Goal``, ``object_axes`` and the task configuration come from topocut.tasks; letters from
topocut.tasks.letters.
"""
from topocut.tasks import (
           CUTTING_TASKS,
           TASK_STAGES,
           TASKS,
           Goal,
           PenConfig,
           SpoonConfig,
           TaskConfig,
           check_stage,
           make_goal,
           object_axes,
)

__all__ = ["TASKS", "CUTTING_TASKS", "TASK_STAGES", "TaskConfig", "PenConfig", "SpoonConfig", "check_stage", "Goal",
           "make_goal", "object_axes"]

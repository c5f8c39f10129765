"""Re-export of topocut.tasks.config (task configuration)."""
from topocut.tasks import TASK_STAGES
from topocut.tasks.config import CUTTING_TASKS, TASKS, PenConfig, SpoonConfig, TaskConfig, check_stage

__all__ = ["CUTTING_TASKS", "TASK_STAGES", "TASKS", "PenConfig", "SpoonConfig", "TaskConfig", "check_stage"]

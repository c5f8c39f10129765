"""Re-export of the knife tasks' goal construction (topocut.tasks; one module per task)."""
from topocut.tasks import Goal, make_goal, object_axes  # noqa: F401

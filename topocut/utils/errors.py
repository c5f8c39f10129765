"""Errors a stage raises for the run wrapper (topocut/run.py) to report as the user's to fix (exit status 2)."""
from __future__ import annotations


class NothingUsable(RuntimeError):
    """A stage ran to its end but produced nothing usable (every episode failed), so it committed nothing.

    ``failures`` lists each failure's reason (``[{"episode": e, "error": "..."}]``); the run's status.json
    keeps it.
    """

    def __init__(self, message: str, failures: list[dict]):
        super().__init__(message)
        self.failures = failures

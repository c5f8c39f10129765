"""The teleop log: its entries (JSON: object, pose, seed, task, actions [{type: cut|push|undo, action: [x, y, yaw,
tilt] | null}]) and their checks, all made before a replay runs its first cut."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

LOG_VERSION = 1
ENTRY_TYPES = ("cut", "push", "undo")


def entry_problem(entry) -> str | None:
    """Why a log entry cannot be replayed, or None."""
    if not isinstance(entry, dict):
        return f"{entry!r} is not an entry {{type, action}}"
    kind = entry.get("type")
    if kind not in ENTRY_TYPES:
        return f"entry type {kind!r}; valid: {', '.join(ENTRY_TYPES)}"
    if kind != "cut":
        return None
    if "action" not in entry:
        return "a cut has no 'action' (its [x, y, yaw, tilt])"
    try:
        v = np.asarray(entry["action"], np.float64)
    except (TypeError, ValueError):
        v = np.zeros(0)
    if v.shape != (4,) or not np.isfinite(v).all():
        return f"a cut's 'action' must be 4 finite numbers [x, y, yaw, tilt], got {entry['action']!r}"
    return None


def check_entries(actions, source: str = "teleop log") -> None:
    """Raise ValueError naming ``source`` and the entry's index for a log entry that cannot be replayed."""
    if not isinstance(actions, list):
        raise ValueError(f"{source}: 'actions' must be a list of entries, got {type(actions).__name__}")
    for i, entry in enumerate(actions):
        problem = entry_problem(entry)
        if problem:
            raise ValueError(f"{source}, entry {i}: {problem}")


def load_log(path) -> dict:
    try:
        log = json.loads(Path(path).read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"teleop log {path} is not valid JSON: {e.msg} (line {e.lineno}, column {e.colno})") from e
    if not isinstance(log, dict):
        raise ValueError(f"teleop log {path} must hold a JSON object, got {type(log).__name__}")
    missing = [k for k in ("object", "seed", "task", "actions") if k not in log]
    if missing:
        raise KeyError(f"teleop log {path} lacks {missing[0]!r}; a log has object, pose, seed, task, actions")
    check_entries(log["actions"], f"teleop log {path}")
    return log

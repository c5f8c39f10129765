"""Human teleoperation as the R̂ reference (``eval.reference=teleop``; paper Table 1).

The paper normalises every policy's reward by human teleoperation.  Here a human's session is a teleop log
(``stage=teleop``), committed by its replay as ``dataset/teleop-<task>-<object>`` with the log beside the data.
The eval stage re-runs each committed log as a policy (``TeleopReplay``) inside the same ``evaluate_episode``
as every other policy: same pose, simulator, topology discovery, reward config and episode length, so the
reference reward is measured exactly as the rewards it normalises.

What is replayed is the log's *effective* cut sequence: an undo removes the cut it undid; pushes are the
task's (``task.push``), as for every policy, not the human's extra presses.
"""
from __future__ import annotations

import hashlib
import json
import warnings
from dataclasses import dataclass

from topocut.sim.action import KnifeAction, executed_action

PREFIX = "teleop-"


def effective_cuts(log: dict, source: str = "teleop log") -> list[list[float]]:
    """The cut vectors left in place after the log's undos (undo restores the state before the last cut)."""
    cuts: list[list[float]] = []
    for i, entry in enumerate(log.get("actions", [])):
        kind = entry.get("type") if isinstance(entry, dict) else None
        if kind == "cut":
            if not isinstance(entry.get("action"), list | tuple) or len(entry["action"]) != 4:
                raise ValueError(f"{source}: actions[{i}] is a cut without a 4-vector 'action' [x, y, yaw, tilt]")
            cuts.append([float(v) for v in entry["action"]])
        elif kind == "undo":
            if cuts:
                cuts.pop()
        elif kind != "push":
            raise ValueError(f"{source}: actions[{i}] has type {kind!r}; valid: cut, push, undo")
    return cuts


class TeleopReplay:
    """A policy that plays back one human's cuts in order, then stops (act returns None).

    The logged vectors were executed through ``topocut.sim.action.executed_action`` (TeleopSession.cut) and
    evaluate_episode executes every policy's action through it again (idempotent): the replay runs the human's
    planes exactly."""

    def __init__(self, cuts: list[list[float]]):
        self.cuts, self._k = [list(c) for c in cuts], 0

    def reset(self, goal=None, seed: int | None = None) -> None:
        self._k = 0

    def act(self, obs) -> KnifeAction | None:
        if self._k >= len(self.cuts):
            return None
        self._k += 1
        return executed_action(KnifeAction.from_vector(self.cuts[self._k - 1]))


@dataclass
class TeleopReference:
    spec: object  # topocut.eval.protocol.EpisodeSpec
    cuts: list[list[float]]
    ref: str  # the dataset version it came from (keys the eval artifact)


def teleop_references(store, tasks, unseen=(), max_cuts: int | None = None) -> list[TeleopReference]:
    """One reference episode per distinct committed teleop log of a task in ``tasks``.

    A log replayed again (another sim config, device or points_per_step) is a new dataset version, not another
    human episode: it counts once, from its newest replay.

    Split: ``out`` for objects in ``unseen``, ``in`` otherwise.  Raises naming the missing task when a task
    has no log (an all-NaN R̂ column would otherwise be committed).
    """
    from topocut.eval.protocol import EpisodeSpec
    from topocut.sim.objects import ObjectPose

    by_log: dict[str, tuple] = {}  # sha256 of the log -> (log, dataset ref, log path)
    for name in store.names("dataset"):
        if not name.startswith(PREFIX):
            continue
        for version in store.versions("dataset", name):  # oldest first: the newest replay of a log wins
            path = store.resolve("dataset", name, version)
            log_path = path / "teleop_log.json"
            try:
                text = log_path.read_text()
                log = json.loads(text)
            except (OSError, json.JSONDecodeError) as e:
                raise ValueError(f"{log_path}: unreadable teleop log ({e}); delete {path} or re-run its replay") from e
            if log.get("task") in tasks:
                by_log[hashlib.sha256(text.encode()).hexdigest()] = (log, store.ref(path), log_path)
    found: dict[tuple[str, str], list] = {}
    for log, ref, log_path in sorted(by_log.values(), key=lambda t: t[1]):
        found.setdefault((log["task"], log["object"]), []).append((log, ref, log_path))
    missing = [t for t in tasks if not any(task == t for task, _ in found)]
    if missing:
        have = sorted({t for t, _ in found}) or "none"
        raise ValueError(f"eval.reference=teleop: no teleop log for task {missing[0]!r} under "
                         f"{store.root / 'dataset'}/{PREFIX}{missing[0]}-<object> (tasks with logs: {have}). "
                         f"Record one (stage=teleop task={missing[0]}) and replay it (stage.run.replay=<log.json>), "
                         "or use eval.reference=oracle")
    refs = []
    for (task, obj), logs in sorted(found.items()):
        split = "out" if obj in unseen else "in"
        for i, (log, ref, log_path) in enumerate(logs):
            pose = ObjectPose(**log["pose"]) if isinstance(log.get("pose"), dict) else ObjectPose()
            spec = EpisodeSpec(task, obj, split, i, int(log["seed"]), pose)
            cuts = effective_cuts(log, str(log_path))
            if max_cuts is not None and len(cuts) > max_cuts:
                warnings.warn(f"{log_path}: the human made {len(cuts)} cuts; the protocol replays the first "
                              f"{max_cuts} (eval.max_cuts), the budget every policy gets", stacklevel=2)
            refs.append(TeleopReference(spec, cuts, ref))
    return refs

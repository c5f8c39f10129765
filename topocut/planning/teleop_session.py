"""The window-free teleop state machine, ``TeleopSession.handle(event)`` (tests drive it with scripted events), and
``replay``, which re-executes a log in the simulator and yields the same records as the episode runner (labels and
rewards recomputed).  A push right after a cut belongs to that cut's record (x_t1 is the pushed state), exactly as
run_episode(push=True).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from topocut.data.store import write_json_atomic
from topocut.episode import Scorer, env_board_z, make_record, new_history
from topocut.episode.scoring import takes_start_positions
from topocut.planning.teleop_log import LOG_VERSION, check_entries, entry_problem, load_log
from topocut.sim.action import KnifeAction, executed_action

_logger = logging.getLogger("topocut.planning.teleop")  # the teleop logger, wherever its messages come from


@dataclass(frozen=True)
class MouseMove:
    x: float  # board coordinates, [0, 1]
    y: float


@dataclass(frozen=True)
class Key:
    name: str  # c, p, u, s, escape, left, right, up, down, a, d
    shift: bool = False


@dataclass(frozen=True)
class Wheel:
    delta: float  # notches; positive turns counter-clockwise
    shift: bool = False


@dataclass
class TeleopConfig:
    yaw_step_deg: float = 5.0
    tilt_step_deg: float = 2.0
    tilt_max: float = 0.6  # rad
    log_path: str = "teleop_log.json"


class TeleopSession:
    """Knife state, history of cuts with undo snapshots, the action log and the dataset records."""

    def __init__(self, env, goal, object: str = "cake", pose=None, seed: int = 0, task: str = "slice",
                 reward_cfg=None, topo_cfg=None, success_threshold: float | None = None,
                 cfg: TeleopConfig | None = None, scorer: Scorer | None = None):
        from topocut.data.episodes import _jsonable

        self.env, self.goal, self.cfg = env, goal, cfg or TeleopConfig()
        self.scorer = scorer or Scorer(goal, reward_cfg, topo_cfg, success_threshold)
        self.board_z = env_board_z(env)
        self.B = int(getattr(env, "batch_size", 1))
        env.reset(object, pose, seed=seed)
        st = env.state()
        self.x = np.asarray(st.x[0])  # N,3
        self.labels = self.scorer.labels(self.x, st.damage[0], None, None)  # N,
        self.knife = np.array([0.5, 0.5, 0.0, 0.0])  # x, y, yaw, tilt
        self.history = new_history()
        self.steps: list[dict] = []
        self._snapshots: list[tuple] = []  # state before each live cut, for undo
        self.log = {"version": LOG_VERSION, "object": object, "pose": _jsonable(pose), "seed": int(seed),
                    "task": task, "actions": []}
        self.done = False
        self.message = "ready"

    # -- commands ---------------------------------------------------------------
    @property
    def action(self) -> KnifeAction:
        return KnifeAction.from_vector(self.knife)

    def cut(self, vector=None) -> None:
        """Cut along the knife plane; a failed cut (SimulationDiverged) raises and changes nothing (scene restored)."""
        # the executed pose (executed_action, as demos and evaluation): the logged float32 vector replays exactly
        # this plane (float32(pi/2) would flip the normal)
        action = executed_action(KnifeAction.from_vector(self.knife if vector is None else vector))
        snapshot = (self.env.get_state(0), self.x, self.labels, list(self.history), len(self.steps))
        try:
            self.env.cut([action] * self.B if self.B > 1 else action)
            self._record_cut(action, self.labels, self.x, list(self.history), amend=False)
        except BaseException:
            self.env.set_state(snapshot[0], b=None)
            raise
        self._snapshots.append(snapshot)  # only a cut that happened can be undone
        self.history.append(action.pose_feature(self.board_z))
        self.log["actions"].append({"type": "cut", "action": [float(v) for v in action.to_vector()]})
        self.message = f"cut {len(self.steps)}: reward {self.steps[-1]['reward']:.3f}"

    def _record_cut(self, action: KnifeAction, labels_t, x_t, history, amend: bool) -> None:
        """Discover the topology after the last cut and write (or, after a push, rewrite: the cut's labels as the
        previous ones, no sweep) its record."""
        st = self.env.state()
        x1 = np.asarray(st.x[0])
        start = {"start_positions": x_t} if takes_start_positions(self.scorer.labels) else {}
        labels1 = self.scorer.labels(x1, st.damage[0], [], self.labels) if amend else \
            self.scorer.labels(x1, st.damage[0], st.sweeps[0], labels_t, **start)
        reward, success = self.scorer.reward(x1, labels1)
        step = make_record(x_t, labels_t, x1, labels1, action, history, reward, success, self.board_z)
        if amend:
            self.steps[-1] = step
        else:
            self.steps.append(step)
        self.x, self.labels = x1, labels1

    def _cut_is_open(self) -> bool:
        """True if the last non-push command was a cut that is still in place (not undone)."""
        kinds = [a["type"] for a in self.log["actions"] if a["type"] != "push"]
        return bool(kinds) and kinds[-1] == "cut"

    def push(self) -> None:
        state = self.env.get_state(0)
        try:
            self.env.push()
            if self._cut_is_open():
                # the push completes the last cut: its labels ride the push and discovery runs again without the
                # sweep (as the episode engine does), then its record is rewritten
                last = self.steps[-1]
                self._record_cut(KnifeAction.from_vector(last["action"]), last["f_t"], last["x_t"],
                                 list(last["history"]), amend=True)
            else:
                self.x = np.asarray(self.env.state().x[0])
        except BaseException:
            self.env.set_state(state, b=None)  # a failed push leaves the scene as it was
            raise
        self.log["actions"].append({"type": "push", "action": None})
        self.message = "pushed"

    def undo(self) -> bool:
        if not self._snapshots:
            self.message = "nothing to undo"
            return False
        state, self.x, self.labels, hist, n = self._snapshots.pop()
        self.env.set_state(state, b=None)
        self.history = new_history()
        self.history.extend(hist)
        del self.steps[n:]
        self.log["actions"].append({"type": "undo", "action": None})
        self.message = f"undone; {len(self.steps)} cuts"
        return True

    def save(self, path=None) -> Path:
        path = write_json_atomic(path or self.cfg.log_path, self.log)
        self.message = f"saved {path}"
        return path

    def apply(self, entry: dict) -> None:
        """Re-execute one log entry (replay)."""
        problem = entry_problem(entry)
        if problem:
            raise ValueError(f"teleop log entry: {problem}")
        kind = entry["type"]
        if kind == "cut":
            self.knife = np.asarray(entry["action"], np.float64)
            self.cut()
        elif kind == "push":
            self.push()
        else:
            self.undo()

    # -- input ------------------------------------------------------------------
    def _rotate(self, notches: float, tilt: bool) -> None:
        if tilt:
            step = math.radians(self.cfg.tilt_step_deg)
            self.knife[3] = float(np.clip(self.knife[3] + notches * step, -self.cfg.tilt_max, self.cfg.tilt_max))
        else:
            self.knife[2] += notches * math.radians(self.cfg.yaw_step_deg)

    def handle(self, event) -> str:
        """Apply one input event; returns the status message."""
        if isinstance(event, MouseMove):
            self.knife[0], self.knife[1] = float(np.clip(event.x, 0, 1)), float(np.clip(event.y, 0, 1))
        elif isinstance(event, Wheel):
            self._rotate(event.delta, tilt=event.shift)
        elif isinstance(event, Key):
            name = event.name.lower()
            rotations = {"left": 1, "a": 1, "right": -1, "d": -1}
            if name in rotations:
                self._rotate(rotations[name], tilt=event.shift)
            elif name in ("up", "down"):
                self._rotate(1 if name == "up" else -1, tilt=True)
            elif name in ("c", "p"):
                self._simulate(self.cut if name == "c" else self.push, "cut" if name == "c" else "push")
            elif name == "u":
                self.undo()
            elif name == "s":
                self.save()
            elif name in ("escape", "esc", "q"):
                self.done = True
                self.message = "quit"
        else:
            raise TypeError(f"unknown event {event!r}; expected MouseMove, Key or Wheel")
        return self.message

    def _simulate(self, command, what: str) -> None:
        """A cut/push from the keyboard: divergence is reported in the status line, the session goes on."""
        from topocut.episode import simulation_diverged_error

        try:
            command()
        except simulation_diverged_error() as e:  # anything else propagates as itself
            self.message = f"{what} failed, scene restored: {e}"
            _logger.warning("teleop: %s", self.message)

    def summary(self) -> dict:
        return {"status": "ok", "num_cuts": len(self.steps),
                "final_reward": self.steps[-1]["reward"] if self.steps else float("nan"),
                "success": bool(self.steps and self.steps[-1]["success"]),
                "rewards": [s["reward"] for s in self.steps], "log_entries": len(self.log["actions"])}


def replay(log, env, goal, reward_cfg=None, topo_cfg=None, success_threshold: float | None = None,
           scorer: Scorer | None = None) -> tuple[list[dict], dict]:
    """Re-execute a teleop log (dict or path) in ``env``; returns (records, summary) like run_episode.

    Every entry is checked before the first runs: a bad one raises ValueError naming the log and its index.
    """
    if isinstance(log, dict):
        check_entries(log.get("actions"), "teleop log")
    else:
        log = load_log(log)
    pose = log.get("pose")
    if isinstance(pose, dict):
        from topocut.sim.objects import ObjectPose

        pose = ObjectPose(**pose)
    session = TeleopSession(env, goal, log["object"], pose, log["seed"], log["task"], reward_cfg, topo_cfg,
                            success_threshold, scorer=scorer)
    for entry in log["actions"]:
        session.apply(entry)
    return session.steps, session.summary()

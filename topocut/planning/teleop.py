"""Teleoperation: steer the knife by mouse and keys, cut/push/undo, log the session, replay it headlessly.

The logic is a window-free state machine, ``TeleopSession.handle(event)``, so
tests drive it with scripted events.  The window (``run_window``) only turns
Taichi GUI input into events and draws a top view of the board:

    mouse x/y       knife board point (the window is the board square [0,1]^2 seen from above)
    wheel, <- ->    yaw (a/d too);  with shift, or up/down: tilt
    c cut   p push   u undo (back to before the last cut)   s save log   esc quit

Every effective command is appended to the log (JSON: object, pose, seed, task,
actions [{type: cut|push|undo, action: [x, y, yaw, tilt] | null}]); ``replay``
re-executes a log in the simulator and yields the same records as the episode
runner (labels and rewards recomputed).  A push right after a cut belongs to
that cut's record (x_t1 is the pushed state), exactly as run_episode(push=True).
"""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from topocut.data.store import write_json_atomic
from topocut.episode import Scorer, env_board_z, make_record, new_history
from topocut.sim.action import KnifeAction, executed_action

LOG_VERSION = 1
ENTRY_TYPES = ("cut", "push", "undo")
_logger = logging.getLogger(__name__)


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
        """Discover the topology after the last cut and write (or, after a push, rewrite) its record."""
        st = self.env.state()
        x1 = np.asarray(st.x[0])
        labels1 = self.scorer.labels(x1, st.damage[0], st.sweeps[0], labels_t)
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
                # the push completes the last cut: redo its discovery on the pushed state (as run_episode does)
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


PALETTE = np.array([0x4C72B0, 0xDD8452, 0x55A868, 0xC44E52, 0x8172B3, 0x937860, 0xDA8BC3, 0x8C8C8C,
                    0xCCB974, 0x64B5CD], np.uint32)


def _colors(labels) -> np.ndarray:  # N, 0xRRGGBB; unassigned particles grey
    labels = np.asarray(labels)
    return np.where(labels >= 0, PALETTE[np.maximum(labels, 0) % len(PALETTE)], 0x404040).astype(np.uint32)


def _knife_segment(session: TeleopSession) -> tuple[np.ndarray, np.ndarray]:
    """The blade's trace on the board, (2,) endpoints in window coordinates (top view)."""
    a = session.action
    c, u = np.array([a.x, a.y]), a.blade_axis[:2]
    return np.clip(c - 0.4 * u, 0, 1), np.clip(c + 0.4 * u, 0, 1)


def _status(session: TeleopSession) -> str:
    x, y, yaw, tilt = session.knife
    return (f"x={x:.3f} y={y:.3f} yaw={math.degrees(yaw):.0f} tilt={math.degrees(tilt):.0f} | "
            f"cuts={len(session.steps)} | {session.message}")


def _open_window(kind: str, res: int):
    """A GGUI window (kind "ggui", needs Vulkan) or a CPU ti.GUI ("gui")."""
    import taichi as ti

    if kind == "ggui":
        return ti.ui.Window("TopoCut teleop", (res, res), vsync=True)
    return ti.GUI("TopoCut teleop", (res, res), background_color=0xF2F2EB)


def _loop_ggui(session: TeleopSession, window) -> None:
    import taichi as ti

    canvas, n = window.get_canvas(), len(session.x)
    pos = ti.Vector.field(2, ti.f32, n)
    col = ti.Vector.field(3, ti.f32, n)
    seg = ti.Vector.field(2, ti.f32, 2)
    names = {ti.ui.LEFT: "left", ti.ui.RIGHT: "right", ti.ui.UP: "up", ti.ui.DOWN: "down", ti.ui.ESCAPE: "escape"}
    while window.running and not session.done:
        for e in window.get_events(ti.ui.PRESS):
            session.handle(Key(names.get(e.key, str(e.key)), shift=window.is_pressed(ti.ui.SHIFT)))
        session.handle(MouseMove(*window.get_cursor_pos()))
        rgb = _colors(session.labels)
        pos.from_numpy(session.x[:, :2].astype(np.float32))
        col.from_numpy(np.stack([(rgb >> 16) & 255, (rgb >> 8) & 255, rgb & 255], 1).astype(np.float32) / 255)
        seg.from_numpy(np.stack(_knife_segment(session)).astype(np.float32))
        canvas.set_background_color((0.95, 0.95, 0.92))
        canvas.circles(pos, radius=0.003, per_vertex_color=col)
        canvas.lines(seg, width=0.004, color=(0.8, 0.1, 0.1))
        with window.get_gui().sub_window("status", 0.0, 0.0, 1.0, 0.06) as w:
            w.text(_status(session))
        window.show()


def _loop_cpu_gui(session: TeleopSession, gui) -> None:
    import taichi as ti

    names = {ti.GUI.LEFT: "left", ti.GUI.RIGHT: "right", ti.GUI.UP: "up", ti.GUI.DOWN: "down",
             ti.GUI.ESCAPE: "escape"}
    while gui.running and not session.done:
        shift = gui.is_pressed(ti.GUI.SHIFT)
        for e in gui.get_events(ti.GUI.PRESS):
            if e.key == ti.GUI.WHEEL:
                session.handle(Wheel(float(np.sign(e.delta[1])), shift=shift))
            elif e.key not in (ti.GUI.LMB, ti.GUI.RMB, ti.GUI.MOVE, ti.GUI.SHIFT):
                session.handle(Key(names.get(e.key, str(e.key)), shift=shift))
        session.handle(MouseMove(*gui.get_cursor_pos()))
        gui.circles(session.x[:, :2], radius=1.5, color=_colors(session.labels))
        a, b = _knife_segment(session)
        gui.line(a, b, radius=2, color=0xCC2222)
        gui.text(_status(session), (0.01, 0.98), font_size=16, color=0x202020)
        gui.show()


def run_window(session: TeleopSession, backend: str = "auto", res: int = 720) -> TeleopSession:
    """Drive ``session`` from a Taichi window until esc: GGUI where Vulkan works, else the CPU ti.GUI.

    Only opening a window falls back or is reported as such: an error while the session runs propagates as
    itself (a diverged cut does not end it: session.handle reports it in the status line)."""
    from topocut.utils.runtime import DeviceUnavailable

    backends = ("auto", "ggui", "gui")
    if backend not in backends:
        raise ValueError(f"teleop backend {backend!r}; valid: {', '.join(backends)}")
    _ensure_taichi()
    if backend in ("auto", "ggui"):
        try:
            window = _open_window("ggui", res)
        except Exception as e:  # noqa: BLE001 - no Vulkan device / no display: fall back to the CPU GUI
            if backend == "ggui":
                raise DeviceUnavailable(f"GGUI window unavailable ({e}); try backend='gui'") from e
        else:
            _loop_ggui(session, window)
            return session
    try:
        gui = _open_window("gui", res)
    except Exception as e:  # noqa: BLE001
        # the user's to fix (exit 2, one line): no display here
        raise DeviceUnavailable(f"cannot open a teleop window ({e}); without a display, replay a saved log "
                                f"headlessly: stage=teleop stage.run.replay=examples/teleop_slice_cake.json") from e
    _loop_cpu_gui(session, gui)
    return session


def _ensure_taichi() -> None:
    import taichi as ti
    from taichi.lang import impl

    if impl.get_runtime().prog is None:  # never re-init: that would free the simulator's fields
        ti.init(arch=ti.cpu, offline_cache=True)

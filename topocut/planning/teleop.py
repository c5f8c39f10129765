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

The session is ``topocut.planning.teleop_session``, the log's format and checks ``topocut.planning.teleop_log``;
their names stay importable from here.
"""
from __future__ import annotations

import math

import numpy as np

from topocut.planning.teleop_log import ENTRY_TYPES, LOG_VERSION, check_entries, entry_problem, load_log
from topocut.planning.teleop_session import Key, MouseMove, TeleopConfig, TeleopSession, Wheel, replay

__all__ = ["ENTRY_TYPES", "LOG_VERSION", "check_entries", "entry_problem", "load_log", "Key", "MouseMove",
           "TeleopConfig", "TeleopSession", "Wheel", "replay", "run_window"]


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
        from topocut.sim.runtime import memoize_source_positions, offline_cache_size

        memoize_source_positions()
        ti.init(arch=ti.cpu, offline_cache=True, **offline_cache_size())

"""What the episode core reads from a simulator (or a test double): board height, particle spacing, one scene's
particles, where discovery runs, and the simulator's divergence error (imported late: the core stays free of
Taichi)."""
from __future__ import annotations

import numpy as np


def env_board_z(env, default: float = 0.05) -> float:
    """The board's top face of ``env`` (its cfg.board_z; ``default`` for a test double without one)."""
    return float(getattr(getattr(env, "cfg", None), "board_z", default))


def env_spacing(env) -> float:
    """The particle spacing of ``env`` (cfg.spacing or cfg.particle_spacing)."""
    cfg = getattr(env, "cfg", None)
    for name in ("spacing", "particle_spacing"):
        if hasattr(cfg, name):
            return float(getattr(cfg, name))
    raise ValueError("run_episodes: env.cfg has no particle spacing (spacing/particle_spacing); pass spacing=")


def scene_of(st, b):
    """(x (N,3), damage (N,)) of scene b of an env state."""
    if hasattr(st, "scene"):
        return st.scene(b)
    return np.asarray(st.x[b]), np.asarray(st.damage[b])


def topology_device(env) -> str:
    """Discovery runs where the simulator runs: its particles are already on that device's side."""
    return "cuda" if getattr(getattr(env, "cfg", None), "arch", "cpu") == "cuda" else "cpu"


class _NoSimulator(Exception):
    """Stands in for SimulationDiverged when topocut.sim.env cannot be imported (so nothing raises it)."""


def simulation_diverged_error() -> type:
    """topocut.sim.SimulationDiverged (imported late so that the episode core stays free of Taichi)."""
    try:
        from topocut.sim import SimulationDiverged
    except ImportError:
        try:
            from topocut.sim.env import SimulationDiverged
        except ImportError:
            return _NoSimulator
    return SimulationDiverged


"""TopoCut cutting simulator (Taichi MLS-MPM).  See docs/sim.md.

Lazy: ``topocut.sim.action``, ``.objects`` and ``.config`` are pure numpy;
Taichi is imported only when CuttingEnv, SimulationDiverged, init_taichi or
the solver is first touched.
"""
from __future__ import annotations

from topocut.utils.lazy import lazy_exports

_LAZY = {
    "CuttingEnv": "topocut.sim.env", "SimState": "topocut.sim.env", "CutInfo": "topocut.sim.env",
    "SimulationDiverged": "topocut.sim.env", "init_taichi": "topocut.sim.runtime", "reset_taichi": "topocut.sim.runtime",
    "MPMSolver": "topocut.sim.mpm",
    "SimConfig": "topocut.sim.config", "TuningConfig": "topocut.sim.config", "KnifeAction": "topocut.sim.action",
    "KnifeSweep": "topocut.sim.action", "cut_mask": "topocut.sim.action", "OBJECTS": "topocut.sim.objects",
    "SEEN": "topocut.sim.objects", "UNSEEN": "topocut.sim.objects", "ObjectPose": "topocut.sim.objects",
    "random_pose": "topocut.sim.objects", "object_sdf": "topocut.sim.objects", "sample_object": "topocut.sim.objects",
    "render_particles": "topocut.sim.render", "write_gif": "topocut.sim.render",
    "TurnRefused": "topocut.sim.primitives",
}
__all__ = sorted(_LAZY)
__getattr__ = lazy_exports(__name__, _LAZY)

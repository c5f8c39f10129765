"""Pyramid: carve the corner tetrahedron off a block (paper appendix, "Pyramid Cutting Task").

**Task.** One tilted plane, normal (a1 + a2 + z)/sqrt(3) (tilt atan(1/sqrt 2) = 35.3 deg), through the
three points at distance ``task.size`` from the top (+a1, +a2, +z) corner of the object's bounding box
along its edges.  Goal piece: the corner tetrahedron (volume size^3 / 6 for a box).
**Oracle.** That single cut.
**Randomisations.** As slice; MPPI also samples the knife tilt (task.sample_tilt).
**Success.** The tetrahedron made (N_C = 1) and the total at task.success_threshold (KnifeTask.success).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from topocut.tasks.base import KnifeTask, plane, register_task
from topocut.tasks.config import KnifeTaskConfig


@dataclass
class PyramidConfig(KnifeTaskConfig):
    name: str = "pyramid"
    # the corner tetrahedron's leg (scene units): 0.1 of the 0.16 cube holds ~150 particles at n_grid 48 (0.08
    # gives 76, a noisy spectrum; 0.05 ~18), and the 128^3 grid resolves it as well
    size: float = 0.1
    max_cuts: int = 1  # the one tilted cut
    sample_tilt: bool = True  # the goal plane is tilted 35 deg: MPPI samples tilt as well as x, y, yaw
    positive = ("size",)


@register_task
class PyramidTask(KnifeTask):
    config = PyramidConfig

    def pieces(self, cfg, pts, axes, pad, spacing, board_z):
        local = pts @ axes.T  # N,3 coordinates along a1, a2, z
        corner = (local + pad[:, None]).max(0) @ axes  # back to world (axes orthonormal)
        n = axes.sum(0) / np.sqrt(3.0)
        labels = ((pts - corner) @ n >= -cfg.size / np.sqrt(3.0)).astype(np.int32)
        return [plane(n, corner - cfg.size * axes[0], board_z)], labels


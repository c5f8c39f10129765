"""Pyramid: carve the corner tetrahedron off a block (paper appendix, "Pyramid Cutting Task").

**Task.** One tilted plane, normal (a1 + a2 + z)/sqrt(3) (tilt atan(1/sqrt 2) = 35.3 deg), through the
three points at distance ``task.size`` from the top (+a1, +a2, +z) corner of the object's bounding box
along its edges.  Goal piece: the corner tetrahedron (volume size^3 / 6 for a box).
**Oracle.** That single cut.
**Randomisations.** As slice; MPPI also samples the knife tilt (task.sample_tilt).
**Success.** The tetrahedron made (N_C = 1) and the total at task.success_threshold (KnifeTask.success).
"""
from __future__ import annotations

import numpy as np

from topocut.tasks.base import KnifeTask, plane, register_task


@register_task
class PyramidTask(KnifeTask):
    name = "pyramid"

    def pieces(self, cfg, pts, axes, pad, spacing, board_z):
        local = pts @ axes.T  # N,3 coordinates along a1, a2, z
        corner = (local + pad[:, None]).max(0) @ axes  # back to world (axes orthonormal)
        n = axes.sum(0) / np.sqrt(3.0)
        labels = ((pts - corner) @ n >= -cfg.size / np.sqrt(3.0)).astype(np.int32)
        return [plane(n, corner - cfg.size * axes[0], board_z)], labels


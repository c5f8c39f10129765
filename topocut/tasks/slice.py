"""Slice: cut slabs of ``thickness`` off one end of the object.

**Task.** Cut ``max_cuts`` slabs of thickness ``task.thickness`` off the +a1 end of the object (a1 its longer
horizontal axis), each plane normal to a1.  Goal pieces: the slabs, in the object's initial pose.
**Oracle.** ``max_cuts`` vertical cuts normal to a1, every ``thickness`` from the +a1 face; no turn.
**Randomisations.** Object (10 shapes), its pose (translation, yaw, scale; topocut.sim.objects.random_pose),
the particle jitter (seed); the thickness per task config (eval: task_overrides).
**Success.** Every slab made (N_C = number of goal pieces: a piece counts when its distance to its goal slab is
within reward.success_distance, i.e. its thickness within ~0.86-1.16 t) and the total at task.success_threshold (KnifeTask.success).
"""
from __future__ import annotations

from dataclasses import dataclass

from topocut.tasks.base import KnifeTask, register_task, slices
from topocut.tasks.config import KnifeTaskConfig


@dataclass
class SliceConfig(KnifeTaskConfig):
    name: str = "slice"
    thickness: float = 0.03  # slab thickness (scene units), along the object's longest horizontal axis
    positive = ("thickness",)


@register_task
class SliceTask(KnifeTask):
    config = SliceConfig

    def pieces(self, cfg, pts, axes, pad, spacing, board_z):
        return slices(pts, axes, cfg.thickness, cfg.max_cuts, board_z, pad)


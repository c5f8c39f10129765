"""Ice-cream scooping (paper appendix, "Additional Manipulation Tasks"): scoop chunks into a cup.

**Task.** A spherical-shell spoon scoops chunks of an elastoplastic block and pours them into a cup; each
chunk in the cup is its own cluster.  Goal: one target chunk per scoop, the block's particles at rest that the
bowl's mid-sphere encloses at the placement (topocut.tasks.scooping_scene.chunk_targets); scored by
topocut.tasks.scooping_reward (the cup's pieces matched to the targets; the block is not waste; spills cost).
**Oracle.** The spoon primitive at each ``spoon.scoops`` placement (topocut.sim.spoon.scoop_keyframes).
**Randomisations.** None beyond the placements and the block / cup layout (task.spoon).
**Success.** The total at task.success_threshold (0.95): a target without its own piece in the cup earns 0, so
that total needs every chunk in the cup as its own cluster.
Stages: simulate only.  Scene: topocut.tasks.scooping_scene.ScoopScene (spoon, cup, block).
"""
from __future__ import annotations

from dataclasses import dataclass, field

from topocut.sim.tools import SpoonConfig
from topocut.tasks.base import register_task
from topocut.tasks.config import TaskConfig
from topocut.utils.checks import check_positive


@dataclass
class ScoopingConfig(TaskConfig):
    """No knife: no cut budget, push or tilt (KnifeTaskConfig); the spoon, the block, the cup and the scoops."""

    name: str = "scooping"
    success_threshold: float = 0.95  # the total alone decides success (docs/tasks.md)
    spoon: SpoonConfig = field(default_factory=SpoonConfig)  # task.spoon.*: topocut/sim/tools.py

    def validate(self) -> ScoopingConfig:
        super().validate()
        s = self.spoon
        check_positive("task.spoon", s, ("radius", "thickness", "depth", "advance", "speed", "cup_radius", "cup_height",
                                         "cup_wall", "yield_stress"))
        if not -1.0 < s.opening < 1.0:
            raise ValueError(f"task.spoon.opening={s.opening} must lie in (-1, 1)")
        if s.depth >= 2 * s.radius:
            raise ValueError(f"task.spoon.depth={s.depth} must be < the bowl's diameter 2*radius={2 * s.radius}")
        if len(s.block) != 3 or min(s.block) <= 0:
            raise ValueError(f"task.spoon.block must be 3 positive sizes (x, y, z), got {list(s.block)}")
        for k in ("block_center", "cup_center"):
            if len(getattr(s, k)) != 2:
                raise ValueError(f"task.spoon.{k} must be (x, y), got {list(getattr(s, k))}")
        if not s.scoops or any(len(a) != 2 for a in s.scoops):
            raise ValueError(f"task.spoon.scoops must be a non-empty list of (x, y) offsets, got {s.scoops}")
        gap = abs(s.cup_center[0] - s.block_center[0]) - s.block[0] / 2 - s.cup_radius - s.cup_wall
        if gap < 0:
            raise ValueError(f"task.spoon.cup_center={list(s.cup_center)} puts the cup inside the block "
                             f"(x gap {gap:.3f} < 0)")
        return self


@register_task
class ScoopingTask:
    config = ScoopingConfig
    tool = "spoon"
    stages = ("simulate",)
    min_cuts = 1  # no knife: task.max_cuts is not used
    min_cuts_why = "task.max_cuts is not used"

    def make_goal(self, cfg, object: str = "", pose=None, spacing: float = 0.008, board_z: float = 0.05,
                  seed: int = 0, skin_thickness: float = 0.01):
        """One target chunk per scoop (list of (m_i,3)), from the block ScoopScene loads with this spacing and seed."""
        from topocut.tasks.scooping_scene import target_chunks

        cfg.validate()
        return target_chunks(cfg.spoon, spacing, board_z, seed)

    def oracle(self, goal) -> list:
        return []  # the placements live in task.spoon.scoops

    def success(self, result, cfg) -> bool:
        return bool(result.total >= cfg.success_threshold)


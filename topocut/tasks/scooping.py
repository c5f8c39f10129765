"""Ice-cream scooping (paper appendix, "Additional Manipulation Tasks"): scoop chunks into a cup.

**Task.** A spherical-shell spoon scoops chunks of an elastoplastic block and pours them into a cup; each
chunk in the cup is its own cluster.  Goal: one target chunk per scoop, the block's particles at rest that the
bowl's mid-sphere encloses at the placement (topocut.tasks.scooping_scene.chunk_targets); scored by
topocut.tasks.scooping_reward (the cup's pieces matched to the targets; the block is not waste; spills cost).
**Oracle.** The spoon primitive at each ``spoon.scoops`` placement (topocut.sim.spoon.scoop_keyframes).
**Randomisations.** None beyond the placements and the block / cup layout (task.spoon).
**Success.** Every chunk in the cup as its own cluster and the total at task.success_threshold.
Stages: simulate only.  Scene: topocut.tasks.scooping_scene.ScoopScene (spoon, cup, block).
"""
from __future__ import annotations

from topocut.tasks.base import register_task


@register_task
class ScoopingTask:
    name = "scooping"
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


"""Cream writing (paper appendix, "Additional Manipulation Tasks"): write a word with a cream pen.

**Task.** A nozzle at a fixed height above the board extrudes a von Mises cream; each continuous stroke is
one cluster.  Goal: per letter of ``task.word``, the pen's own bead laid along the letter's stroke (the nozzle's
layer every PenConfig.layer_pitch, one particle layer: topocut.tasks.letters).
**Oracle.** The scripted writer: each letter's stroke polyline, pen down, then lifted to the next letter
(topocut.tasks.writing_scene.write_scripted; MPPI over strokes: topocut.planning.stroke_mppi).
**Randomisations.** None beyond the word, letter height and gap (task config).
**Success.** The total at task.success_threshold: the geometric mean over the letters of R(d), each letter
against the stroke paired with it (d_spec + d_size + handedness; topocut.tasks.writing_scene.letter_rewards).
Stages: simulate and mppi only.  Scene: topocut.sim.pen (CreamPen, cream_sim_config) and
topocut.tasks.writing_scene (goal layout, scripted primitives, stroke clusters).
"""
from __future__ import annotations

from topocut.tasks.base import register_task


@register_task
class CreamWritingTask:
    name = "cream_writing"
    tool = "pen"
    stages = ("simulate", "mppi")
    min_cuts = 1  # no knife: task.max_cuts is not used
    min_cuts_why = "task.max_cuts is not used"

    def make_goal(self, cfg, object: str = "", pose=None, spacing: float = 0.008, board_z: float = 0.05,
                  seed: int = 0, skin_thickness: float = 0.01):
        """(per-letter goal clouds, the letters' stroke polylines): topocut.tasks.letters.word_goal."""
        from topocut.tasks.letters import word_goal

        cfg.validate()
        return word_goal(cfg.word, cfg.letter_height, cfg.letter_gap, spacing, board_z, cfg.pen)

    def oracle(self, goal) -> list:
        return list(goal[1])  # the stroke polylines, in writing order

    def success(self, result, cfg) -> bool:
        return bool(result.total >= cfg.success_threshold)


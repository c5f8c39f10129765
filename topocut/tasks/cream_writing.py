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

from dataclasses import dataclass, field

from topocut.sim.tools import PenConfig
from topocut.tasks.base import register_task
from topocut.tasks.config import TaskConfig
from topocut.utils.checks import check_positive


@dataclass
class CreamWritingConfig(TaskConfig):
    """No knife: no cut budget, push or tilt (KnifeTaskConfig); the word, its letters' layout and the pen."""

    name: str = "cream_writing"
    success_threshold: float = 0.95  # the total alone decides success (docs/tasks.md)
    word: str = "CORL"  # letters written, one stroke (cluster) each; topocut.tasks.letters.LETTERS
    letter_height: float = 0.12  # cap height of a letter [units]; width is LETTER_ASPECT times it
    letter_gap: float = 0.06  # space between letters [units] (>= ~5 spacings, or discovery joins them)
    pen: PenConfig = field(default_factory=PenConfig)  # task.pen.*: topocut/sim/tools.py
    positive = ("letter_height",)

    def validate(self) -> CreamWritingConfig:
        from topocut.tasks.letters import LETTERS

        super().validate()
        bad = [c for c in self.word.upper() if c not in LETTERS]
        if not self.word or bad:
            raise ValueError(f"task.word={self.word!r}: no stroke for {bad or 'an empty word'}; "
                             f"valid letters: {''.join(sorted(LETTERS))}")
        if self.letter_gap < 0:
            raise ValueError(f"task.letter_gap={self.letter_gap} must be >= 0")
        p = self.pen
        check_positive("task.pen", p, ("height", "nozzle_radius", "extrude_speed", "speed", "travel_speed", "step",
                                        "yield_stress", "mu", "lam"))
        if p.max_particles < 100:
            raise ValueError(f"task.pen.max_particles={p.max_particles} must be >= 100")
        return self


@register_task
class CreamWritingTask:
    config = CreamWritingConfig
    tool = "pen"
    stages = ("simulate", "mppi")
    min_cuts = 1  # no knife: no task.max_cuts (CreamWritingConfig), nothing to check
    min_cuts_why = "it has no cuts"

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


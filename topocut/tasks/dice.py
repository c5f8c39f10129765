"""Dice: cubes of side ``size``, cut as a cook does: slab, lay it flat, sticks, chop across.

**Task.** Cut a slab of thickness ``task.size`` off the +a1 end; lay it flat (``Turn``: 90 deg about a2, its
outer face on the board, cut face up, off the object's +a1/+a2 corner so that no cut reaches the rest; its
thickness, ``size``, is now vertical); cut it into sticks with
planes normal to a2 every ``size``; turn the knife 90 deg and chop the sticks with planes normal to a1
(the slab's former height) every ``size``.  Each die is size x size x size: its three principal extents
are all ~``size`` (unlike the old dice, size x size columns of the object's height).  Goal pieces: the grid
cells holding >= 3/4 of a full die's particles, in the object's initial pose.
**Oracle.** Slab cut, lay flat, the stick cuts (normal to a2), the chop cuts (normal to a1, turned frame):
``max_cuts - 1`` cuts after the slab at the band edges inside the slab; the band anchors (a face or
centred) and counts are chosen to make the most full dice.  Needs max_cuts >= 3 for a die bounded on
every side (slab cut + one cut each way; faces close the rest).
**Randomisations.** As slice; size per task config.
**Success.** Every die made (N_C = G) and the total at task.success_threshold (KnifeTask.success).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from topocut.tasks.base import KnifeTask, first_slab, lay_flat, plane, register_task
from topocut.tasks.config import KnifeTaskConfig
from topocut.tasks.grid import best_grid


@dataclass
class DiceConfig(KnifeTaskConfig):
    """A die's one side sets the slab, the sticks and the chops alike: dice has no thickness or width."""

    name: str = "dice"
    size: float = 0.03  # a die's side (scene units)
    push: bool = True  # the paper's dice task pushes the cut-off side aside after each cut
    positive = ("size",)


@register_task
class DiceTask(KnifeTask):
    name = "dice"
    config = DiceConfig
    turns = True
    min_cuts = 3
    min_cuts_why = "a slab cut, a stick cut and a chop to free a die"

    def pieces(self, cfg, pts, axes, pad, spacing, board_z):
        a1, a2, z = axes
        cut0, slab = first_slab(pts, axes, cfg.size, board_z, pad, key="task.size")
        p, d = pts[slab], pad[slab]
        coords = np.stack([p @ a2, p @ z], -1)
        faces = [((coords[:, 0] - d).min(), (coords[:, 0] + d).max()), (board_z, (coords[:, 1] + d).max())]
        lab, cuts, _ = best_grid(coords, faces, [cfg.size, cfg.size], cfg.max_cuts - 1, (cfg.size / spacing) ** 3,
                                  min_fill=0.75)
        labels = np.zeros(len(pts), np.int32)
        labels[slab] = lab
        turn = lay_flat(pts, slab, axes, board_z, beside=True)  # stick cuts miss the rest
        t, c0 = np.asarray(turn.target), np.asarray(turn.center)
        sticks = [plane(a2, t + (c - c0 @ a2) * a2, board_z) for c in cuts[0]]  # a2 kept by the turn, shifted
        chops = [plane(a1, t + (c - c0 @ z) * a1, board_z) for c in cuts[1]]
        return [cut0, turn] + sticks + chops, labels


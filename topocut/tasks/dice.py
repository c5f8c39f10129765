"""Dice: cubes of side ``size``, cut as a cook does: slab, lay it flat, sticks, chop across.

**Task.** Cut a slab of thickness ``task.size`` off the +a1 end; lay it flat (``Turn``: -90 deg about a2, its
cut face on the board, outer face up, off the object's +a1/+a2 corner so that no cut reaches the rest; its
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

from topocut.tasks.base import lay_flat, register_task
from topocut.tasks.config import KnifeTaskConfig
from topocut.tasks.slab import SlabGrid, SlabTask


@dataclass
class DiceConfig(KnifeTaskConfig):
    """A die's one side sets the slab, the sticks and the chops alike: dice has no thickness or width."""

    name: str = "dice"
    size: float = 0.03  # a die's side (scene units)
    push: bool = True  # the paper's dice task pushes the cut-off side aside after each cut
    positive = ("size",)


@register_task
class DiceTask(SlabTask):
    config = DiceConfig
    slab_key = "size"  # the slab is a die thick
    min_cuts = 3
    min_cuts_why = "a slab cut, a stick cut and a chop to free a die"

    def slab_grid(self, cfg, pts, slab, axes, pad, spacing, board_z):
        a1, a2, z = axes
        p, d = pts[slab], pad[slab]
        coords = np.stack([p @ a2, p @ z], -1)
        faces = [((coords[:, 0] - d).min(), (coords[:, 0] + d).max()), (board_z, (coords[:, 1] + d).max())]
        turn = lay_flat(pts, slab, axes, board_z, beside=True)  # stick cuts miss the rest
        # sticks normal to a2 (kept by the turn); chops normal to a1, the slab's former height (z) once laid flat
        return SlabGrid(coords, faces, [cfg.size, cfg.size], (cfg.size / spacing) ** 3, turn, [a2, z],
                        min_fill=0.75)

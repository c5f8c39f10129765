"""Stick: a slab cut into sticks of ``thickness`` x ``width`` with one long axis.

**Task.** Cut a slab of ``task.thickness`` off the +a1 end, then cut it into sticks of width ``task.width``.
A stick is thickness x width x L with L the slab's longer in-plane side, so it has one long axis:
if the slab is at least as tall as it is wide (cube, tall objects) the sticks stand upright (cuts normal to
a2 across the standing slab); if it is wider than tall (steak, cake, donut edge slabs) the slab is first
laid flat (``Turn``: -90 deg about a2, cut face down) and cut normal to its former height, so the sticks lie
along a2.  Either way the slab is first set where no stick cut reaches the rest of the object: a standing slab off
the object's +a1/+a2 corner (a ``Turn`` by 0 deg), a laid one beyond its +a1 end.  Goal pieces: the pieces the steps make that lie mostly in a full stick's band (a band holding >= half
a full stick's particles; topocut.tasks.ideal), initial pose.
**Oracle.** Slab cut; move the slab aside [laid flat]; ``max_cuts - 1`` cuts at the band edges that lie inside the slab
(bands anchored at a face or centred, whichever makes the most full sticks).
**Randomisations.** As slice; thickness and width per task config.
**Success.** Every stick made (N_C = G) and the total at task.success_threshold (KnifeTask.success).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from topocut.tasks.base import lay_flat, move_aside, register_task
from topocut.tasks.config import KnifeTaskConfig
from topocut.tasks.slab import SlabGrid, SlabTask


@dataclass
class StickConfig(KnifeTaskConfig):
    name: str = "stick"
    thickness: float = 0.03  # the slab's thickness (scene units), along the object's longest horizontal axis
    width: float = 0.03  # each stick's width, across the slab
    push: bool = True  # the paper's stick task pushes the cut-off side aside after each cut
    positive = ("thickness", "width")


@register_task
class StickTask(SlabTask):
    config = StickConfig
    min_cuts = 2
    min_cuts_why = "a slab cut, then a cut across the slab"

    def slab_grid(self, cfg, pts, slab, axes, pad, spacing, board_z):
        a1, a2, z = axes
        p, d = pts[slab], pad[slab]
        s2, h = p @ a2, p @ z
        tall = np.ptp(h) >= 0.95 * np.ptp(s2)  # a square slab (the cube) keeps its sticks upright
        if tall:  # upright sticks: bands across a2, the standing slab moved off the object's +a1/+a2 corner
            length = np.ptp(h) + spacing
            faces = [((s2 - d).min(), (s2 + d).max())]
            coords = s2[:, None]
            turn, cut_axes = move_aside(pts, slab, axes), [a2]
        else:  # lay the slab flat beyond the object's +a1 end, bands along its former height: cuts normal to a1
            length = np.ptp(s2) + spacing
            faces = [(board_z, (h + d).max())]
            coords = h[:, None]
            turn, cut_axes = lay_flat(pts, slab, axes, board_z), [z]
        full = cfg.thickness * cfg.width * length / spacing ** 3
        return SlabGrid(coords, faces, [cfg.width], full, turn, cut_axes)

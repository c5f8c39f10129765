"""The slab tasks (stick, dice): cut a slab off the +a1 end, set it down, then cut it into a grid of pieces.

Their oracles share one frame: the first slab (``first_slab``), the bands that make the most full pieces within
the cut budget (``best_grid``), the slab's goal labels, and the grid's cut planes moved to where the slab lies
after its ``Turn``.  A task says only how its slab is gridded and set down (``SlabTask.slab_grid``).
"""
from __future__ import annotations

from abc import abstractmethod
from dataclasses import dataclass

import numpy as np

from topocut.tasks.base import KnifeTask, Turn, first_slab, plane
from topocut.tasks.grid import MIN_FILL, best_grid


@dataclass
class SlabGrid:
    """How a slab task grids its slab (``best_grid``'s inputs) and where it sets the slab down before cutting it."""

    coords: np.ndarray  # (n, A) the slab's particles along the A grid axes, in the initial pose
    faces: list  # [(lo, hi)] the slab's faces per grid axis
    widths: list  # band width per grid axis
    full: float  # a full cell's particle count
    turn: Turn  # the slab set down (laid flat or moved aside): its grid cuts miss the rest of the object
    # per grid axis: the axis its coordinate is measured along in the initial pose (its cuts' normal is that axis
    # carried by the turn)
    cut_axes: list
    min_fill: float = MIN_FILL  # a cell is a goal piece from this share of a full cell's particles


class SlabTask(KnifeTask):
    """A knife task whose oracle frees a slab, sets it down and cuts it into a grid (stick, dice)."""

    turns = True
    slab_key = "thickness"  # the config key of the slab's thickness (task.<key>, named when the slab does not fit)

    @abstractmethod
    def slab_grid(self, cfg, pts, slab, axes, pad, spacing, board_z) -> SlabGrid:
        """The grid of the slab ``pts[slab]`` (cut off by the first cut) and the Turn that sets it down."""

    def pieces(self, cfg, pts, axes, pad, spacing, board_z):
        cut0, slab = first_slab(pts, axes, getattr(cfg, self.slab_key), board_z, pad, key=f"task.{self.slab_key}")
        grid = self.slab_grid(cfg, pts, slab, axes, pad, spacing, board_z)
        lab, cuts, _ = best_grid(grid.coords, grid.faces, grid.widths, cfg.max_cuts - 1, grid.full, grid.min_fill)
        labels = np.zeros(len(pts), np.int32)
        labels[slab] = lab
        t, c0, R = np.asarray(grid.turn.target), np.asarray(grid.turn.center), grid.turn.rotation()
        steps = [cut0, grid.turn]
        for along, positions in zip(grid.cut_axes, cuts):
            # a cut at c along ``along`` before the turn is the plane normal to R along through the turned point:
            # the turn carries the offset c - c0.along with it (a1 -> +z, z -> -a1 when laid flat)
            n = R @ along
            steps += [plane(n, t + (c - c0 @ along) * n, board_z) for c in positions]
        return steps, labels

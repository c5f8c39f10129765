"""A piece's body: the particles the reward describes, without the strays the blade dragged out of it.

The oscillating blade and the push drag a few particles out of a piece's face into a thread that stays joined to it
(the simulator's bonds do not break where nothing cut them): 5 to 10 particles, one particle thick, reaching 1-2 cm
out of a 3 cm die (dice / potato / episode 0 at 128^3 on the H200).  The spectral descriptor sees such a thread as a
second, thin body: the die's d_spec went from 0.003 without the 5 farthest of them to 0.236 with them, and R from
1 to 0, although a cook would call it a perfect die with a crumb on it.

``body`` keeps a piece's core (particles with at least ``CORE_NEIGHBOURS`` neighbours within ``LINK`` spacings: the
bulk and faces of a lattice, ~9-18; a one-particle thread has 2-4) and every particle within ``LINK`` spacings of
the core (the core's rim: faces, edges and corners, 3-9 neighbours, are one link from it), so a thread loses all
but its first link.  Where that would leave out more than ``max_share`` of the piece (a thin bead of cream, a flake
that is all rim), nothing is left out: the piece is what it is.  docs/reward.md#strays.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

LINK = 1.6  # neighbours within this many particle spacings (the simulator's bond radius, topocut.sim.pieces.LINK)
CORE_NEIGHBOURS = 6  # a core particle has at least this many (a lattice corner 3-6, a one-particle thread 2-4)


def body(points: np.ndarray, spacing: float, max_share: float) -> np.ndarray:
    """The particles of ``points`` (N,3) kept as the piece's body (M,3), M >= (1 - max_share) N: the core and its rim
    (module docstring); all of them when ``max_share`` is 0, the spacing is unknown or more would be left out."""
    p = np.asarray(points, np.float64)
    if not max_share > 0 or not spacing > 0 or len(p) < 2 * CORE_NEIGHBOURS:
        return p
    tree = cKDTree(p, balanced_tree=False)
    r = LINK * spacing
    core = tree.query_ball_point(p, r, return_length=True) - 1 >= CORE_NEIGHBOURS  # N, itself not counted
    if core.all() or not core.any():
        return p
    d, _ = cKDTree(p[core], balanced_tree=False).query(p[~core], distance_upper_bound=r)
    keep = core.copy()
    keep[~core] = np.isfinite(d)  # the rim: within one link of the core
    return p if (~keep).sum() > max_share * len(p) else p[keep]

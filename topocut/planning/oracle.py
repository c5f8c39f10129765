"""The oracle: the goal's own steps executed at the episode's true pose, the reference of Table 1.

``OraclePolicy`` cuts the goal's planes (``Goal.planes``, the Cut steps of ``Goal.steps``; the episode engine
performs the Turn steps between them) and stops when they are done: the protocol scores what is on the board,
and a cut past the plan would only cut a goal piece.

A cook looks where the piece is before each cut.  The plan places every plane on the ideal, unmoved material,
but the push after a cut slides pieces a couple of centimetres and pieces settle, so each plane is carried with
the pieces it splits: ``Goal.anchors[k]`` holds particles of those pieces at their initial and their planned
positions just before cut k, the piece each lies in and whether it ends in a goal piece (topocut.tasks.ideal).
The oracle finds the same particles in the scene (nearest initial position), keeps those of the pieces the cut
makes goal pieces of (a chop across three sticks the pushes slid apart follows the goal's stick), fits the
horizontal rigid motion (rotation about z, translation) from planned to current positions, and moves the plane by
the rotation and by the median displacement along its normal; where that plane leaves more than 5% of those
particles on the wrong side (a soft slab spreads when laid down), it sets the plane between the two sides'
particles where they are now.  It reads the scene's particles from the observation's ``particles`` (N,3), which the
episode engine adds only for a policy marked ``privileged`` (a reference, not a contender).
"""
from __future__ import annotations

import numpy as np

from topocut.planning.heuristic import GoalPlanesPolicy
from topocut.sim.action import KnifeAction

MIN_TRACKED = 16  # goal-piece anchor particles enough to track a cut by (else all of its anchor's)


def planar_rigid(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R 3x3 rotation about z, t 3,) minimising sum |R src_i + t - dst_i|^2 over the horizontal components
    (2-D Kabsch); t's z is 0: a push slides pieces on the board, it does not lift them."""
    a, b = np.asarray(src, np.float64)[:, :2], np.asarray(dst, np.float64)[:, :2]
    ca, cb = a.mean(0), b.mean(0)
    h = (a - ca).T @ (b - cb)  # 2,2
    ang = np.arctan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
    c, s = np.cos(ang), np.sin(ang)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    t = np.zeros(3)
    t[:2] = cb - R[:2, :2] @ ca
    return R, t


def _tracked(anchor, m: int) -> np.ndarray:
    """(m,) bool: the anchor particles a cut is carried by.  A cut that crosses several pieces (a chop across sticks
    the pushes slid apart, each its own way) cannot follow them all: it follows the pieces it makes goal pieces of,
    whose size it sets; a planned offcut's material is forgiven by volume wherever the plane parts it
    (docs/reward.md#planned-offcuts).  All of them where the anchor does not say (an older goal) or too few."""
    goal, piece = getattr(anchor, "goal", None), getattr(anchor, "piece", None)
    if goal is None or piece is None:
        return np.ones(m, bool)
    sel = np.isin(piece, np.unique(np.asarray(piece)[np.asarray(goal, bool)]))
    return sel if sel.sum() >= MIN_TRACKED else np.ones(m, bool)


class OraclePolicy(GoalPlanesPolicy):
    """Policy protocol: ``reset(goal)``, ``act(obs)``: the goal's planes in order, each carried with the piece it
    cuts (module docstring); None once they are done.  Without ``particles`` in the observation (or anchors in
    the goal) it cuts the planes where the plan put them."""

    privileged = True  # the episode engine adds the scene's particles to its observation (no learned policy's)
    observation_fields = ("goal", "particles", "cuts_done")  # topocut.policies.registry's inputs: no observed points

    def __init__(self, goal=None, board_z: float = 0.05, track: bool = True):
        self.board_z, self.track = float(board_z), bool(track)
        self.anchors: list = []
        self.initial = None  # N,3 the scene's particles before the first cut
        super().__init__(goal)

    def reset(self, goal) -> None:
        super().reset(goal)  # the goal's planes, from the first
        self.anchors = list(getattr(goal, "anchors", None) or [])
        self.initial = None

    def act(self, obs: dict | None = None) -> KnifeAction | None:
        if self.t >= len(self.planes):
            return None  # the plan is done
        obs = obs or {}
        x = obs.get("particles")
        if x is not None and self.initial is None and int(obs.get("cuts_done", 0)) == 0:
            self.initial = np.asarray(x, np.float64).copy()
        action = self.planes[self.t]
        if self.track and x is not None and self.initial is not None and self.t < len(self.anchors):
            action = self._carried(action, self.anchors[self.t], np.asarray(x, np.float64))
        self.t += 1
        return action

    def _carried(self, action: KnifeAction, anchor, x: np.ndarray) -> KnifeAction:
        from scipy.spatial import cKDTree

        if len(self.initial) != len(x):
            return action
        _, idx = cKDTree(self.initial).query(np.asarray(anchor.initial, np.float64))
        y = x[idx]  # m,3 the anchor particles now
        planned = np.asarray(anchor.planned, np.float64)
        side = getattr(anchor, "side", None)
        sel = _tracked(anchor, len(y))
        R, t = planar_rigid(planned[sel], y[sel])
        n = R @ action.normal  # the plan's normal (and sides), carried by R (the action's may flip into canonical form)
        p = R @ action.plane_point(self.board_z) + t
        # along the normal, the median displacement: pieces slid along the plane (a chop across pushed sticks) or
        # sagging at one end pull a least-squares fit's translation, not the median
        p = p + float(np.median((y[sel] - planned[sel] @ R.T - t) @ n)) * n
        moved = KnifeAction.from_plane(n, p, self.board_z)
        if side is None:
            return moved
        side = np.asarray(side, bool)[sel]
        s = y[sel] @ n
        if side.sum() < 5 or (~side).sum() < 5 or ((s > p @ n) == side).mean() >= 0.95:
            return moved
        # a soft piece also spreads or sags when laid down or pushed: where the moved plane no longer parts the
        # particles the plan leaves on either side of it (more than 5% on the wrong side), put it between them
        c = 0.5 * (np.quantile(s[~side], 0.9) + np.quantile(s[side], 0.1))
        return KnifeAction.from_plane(n, p + (c - p @ n) * n, self.board_z)

"""Open-loop plane policies: a goal's planes in order (``GoalPlanesPolicy``) and Table 1's "Heuristic".

``Goal.planes`` (topocut.tasks.make_goal; the Cut steps of the task's oracle) are the equally spaced planes that
produce the target pieces on the nominal, undeformed object.  ``GoalPlanesPolicy`` cuts them open loop at the pose
its goal was made for: on the episode's own goal that is the untracked oracle, and it is MPPI's initial guess and
horizon fill.  ``HeuristicPolicy`` cuts the planes of the object's *nominal* pose, blind to the episode's
randomisation: the evaluation's "Heuristic" baseline.  (The evaluation's oracle, ``topocut.planning.oracle``,
also carries each plane with the piece it cuts.)
"""
from __future__ import annotations

import numpy as np

from topocut.sim.action import KnifeAction

_NOMINAL: dict = {}  # (task config, object, spacing, board) -> the goal at the nominal pose, every HeuristicPolicy's


class GoalPlanesPolicy:
    """Policy protocol: ``reset(goal)``, ``act(obs) -> KnifeAction`` returning goal.planes[t]."""

    observation_fields: tuple = ()  # what it reads (topocut.policies.registry's inputs): none, the goal's planes are its plan

    def __init__(self, goal=None):
        self.planes: list[KnifeAction] = []
        self.t = 0
        if goal is not None:
            self.reset(goal)

    def reset(self, goal) -> None:
        planes = list(getattr(goal, "planes", []) or [])
        if not planes:
            raise ValueError("GoalPlanesPolicy needs a goal with at least one plane in goal.planes")
        self.planes = [p if isinstance(p, KnifeAction) else KnifeAction.from_vector(p) for p in planes]
        self.t = 0

    def sequence(self, start: int, n: int) -> np.ndarray:
        """Planes start .. start+n-1 as action vectors (n,4); past the last plane the last one repeats."""
        idx = np.minimum(np.arange(start, start + n), len(self.planes) - 1)
        return np.stack([self.planes[i].to_vector() for i in idx]).astype(np.float64)

    def act(self, obs: dict | None = None) -> KnifeAction:
        action = self.planes[min(self.t, len(self.planes) - 1)]
        self.t += 1
        return action


class HeuristicPolicy(GoalPlanesPolicy):
    """The evaluation's "Heuristic" baseline: the task's equally spaced planes for the object's *nominal*
    pose, executed open loop — blind to the episode's randomised translation, yaw and scale.

    (GoalPlanesPolicy on the episode's own goal knows the true pose: the oracle's open-loop core.)
    """

    def __init__(self, task_cfgs: dict, spacing: float, board_z: float = 0.05):
        super().__init__()
        self.task_cfgs, self.spacing, self.board_z = dict(task_cfgs), spacing, board_z

    def reset(self, goal) -> None:
        from topocut.sim.objects import ObjectPose
        from topocut.tasks import make_goal

        if goal.task not in self.task_cfgs:
            raise KeyError(f"HeuristicPolicy has no TaskConfig for task {goal.task!r}; known: {', '.join(self.task_cfgs)}")
        cfg = self.task_cfgs[goal.task]
        # kept in the module, not on the policy: the episode engine resets a copy of the policy per scene of each
        # batch (topocut.episode.run._slot_policy), and a copy's own cache died with it (a 128^3 goal: ~1 s each)
        key = (repr(cfg), goal.object, float(self.spacing), float(self.board_z))
        if key not in _NOMINAL:
            _NOMINAL[key] = make_goal(cfg, goal.object, ObjectPose(), spacing=self.spacing, board_z=self.board_z)
        super().reset(_NOMINAL[key])  # its planes only, read and never changed

"""A toy policy for `eval.policies=[oracle,my_policy:GoalPlanePolicy]` (docs/evaluation.md, "Evaluate your own
policy"): cut k separates goal piece k from the rest of the goal, reading the plane off the goal points and labels
the observation carries (no access to the oracle's planes, no learning).

Run with this folder on the import path:
    PYTHONPATH=examples python -m topocut.run stage=eval 'eval.policies=[oracle,my_policy:GoalPlanePolicy]'
"""
import numpy as np

from topocut.sim.action import KnifeAction


class GoalPlanePolicy:
    display_name = "Goal plane (example)"  # the report's row label (default: the class name)

    def reset(self, goal, seed=None):  # goal: topocut.tasks.Goal; seed: the episode's (for a stochastic policy)
        self.cuts = 0

    def act(self, obs):  # obs: points (n,3), labels (n,), history (3,7), goal (g,3), goal_labels (g,)
        goal, labels = np.asarray(obs["goal"], np.float64), np.asarray(obs["goal_labels"])
        pieces = sorted(int(i) for i in np.unique(labels) if i > 0)  # goal_labels: 0 the rest, i goal piece i
        if self.cuts >= len(pieces):
            return None  # every goal piece has had its cut: end the episode
        inside = labels == pieces[self.cuts]
        piece, other = goal[inside, :2], goal[~inside, :2]  # a vertical cut: the plan view is enough
        centre = piece.mean(0)
        d = other.mean(0) - centre  # the plane's normal: from the piece towards the bulk of the rest
        d /= max(float(np.linalg.norm(d)), 1e-9)
        edge = float((piece @ d).max())  # the piece's face towards the rest...
        beyond = other @ d
        beyond = beyond[beyond > edge]
        s = 0.5 * (edge + float(beyond.min())) if beyond.size else edge  # ...and halfway to the rest's nearest point
        x, y = centre + (s - centre @ d) * d  # the plane's point nearest the piece's centre
        self.cuts += 1
        # the blade plane through (x, y) with normal (cos yaw, sin yaw, 0); None would end the episode
        return KnifeAction(float(x), float(y), yaw=float(np.arctan2(d[1], d[0])), tilt=0.0).canonical()

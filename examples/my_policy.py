"""A toy policy for `eval.policies=[oracle,my_policy:CentrePlanePolicy]` (docs/evaluation.md, "Evaluate your own
policy"): each cut halves the largest observed piece with a vertical plane through its centre.

Run with this folder on the import path:
    PYTHONPATH=examples python -m topocut.run stage=eval 'eval.policies=[oracle,my_policy:CentrePlanePolicy]'
"""
import numpy as np

from topocut.sim.action import KnifeAction


class CentrePlanePolicy:
    display_name = "Centre plane (example)"  # the report's row label (default: the class name)

    def reset(self, goal, seed=None):  # goal: topocut.goals.Goal; seed: the episode's (for a stochastic policy)
        self.cuts = 0

    def act(self, obs):  # obs: points (n,3), labels (n,), history (3,7), goal (g,3), goal_labels (g,)
        points, labels = np.asarray(obs["points"]), np.asarray(obs["labels"])
        ids, counts = np.unique(labels, return_counts=True)
        piece = points[labels == ids[np.argmax(counts)]]  # the largest piece seen
        x, y = piece[:, :2].mean(0)
        yaw = 0.0 if self.cuts % 2 == 0 else np.pi / 2  # alternate cutting across x and across y
        self.cuts += 1
        return KnifeAction(float(x), float(y), yaw=yaw, tilt=0.0)  # None would end the episode

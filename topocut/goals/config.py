"""Cutting task configuration (paper §4 task setup; docs/reward.md#goals)."""
from __future__ import annotations

from dataclasses import dataclass

TASKS = ("slice", "stick", "dice", "pyramid")


@dataclass
class TaskConfig:
    name: str = "slice"  # slice | stick | dice | pyramid
    thickness: float = 0.03  # slice thickness (scene units), along the object's longest horizontal axis
    width: float = 0.03  # stick width, along the other horizontal axis
    size: float = 0.03  # dice side; pyramid: leg length of the corner tetrahedron
    max_cuts: int = 5  # cuts per episode; also bounds the number of goal pieces
    success_threshold: float = 0.95  # episode success when the total spectral reward (in [0, r_max]) reaches this
    push: bool = False  # gentle downward push after each cut (stick and dice in the paper)
    num_goal_points: int = 2048  # Goal.points/labels are FPS-downsampled to this many points (0: keep all)

    def validate(self) -> TaskConfig:
        if self.name not in TASKS:
            raise ValueError(f"task.name={self.name!r}; valid: {', '.join(TASKS)}")
        for k in ("thickness", "width", "size"):
            if getattr(self, k) <= 0:
                raise ValueError(f"task.{k}={getattr(self, k)} must be > 0")
        if self.max_cuts < 1:
            raise ValueError(f"task.max_cuts={self.max_cuts} must be >= 1")
        if self.num_goal_points < 0:
            raise ValueError(f"task.num_goal_points={self.num_goal_points} must be >= 0")
        return self

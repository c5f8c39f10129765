"""A cut its policy's planner has simulated already: MPPI executes the first cut of its best rollout, and that
rollout's scene after the cut (and its push) is the executed cut's outcome, so the episode restores it rather
than simulating the same cut from the same state again (docs/data.md, "The executed cut").

A scene's result does not depend on its batch-mates (tests/test_sim_batch_independent.py), so the restored
state is the one the cut would make in scene 0 alone; the episode still runs its own discovery on it (the
rollouts' batched discovery shares a voxel size across the batch, the episode's does not).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class SimulatedCut:
    action: object  # KnifeAction: the executed action (executed_action) the rollout cut with
    after: object  # SavedScene (CuttingEnv.save_scene_from): the scene after the cut, and after its push if pushed
    # (x (N,3), damage (N,), sweeps) after the cut, before the rollout's push; None: not pushed (the episode pushes
    # the restored cut itself where its task pushes: a rollout's last cut is not pushed unless planner.push_last)
    before_push: tuple | None
    scene: int  # the rollout's scene it came from

    @property
    def pushed(self) -> bool:
        return self.before_push is not None

    def is_of(self, action) -> bool:
        """Whether this is the cut of ``action`` (an executed_action), to the bit."""
        return action is not None and np.array_equal(np.asarray(self.action.to_vector()),
                                                     np.asarray(action.to_vector()))

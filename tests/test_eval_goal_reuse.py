"""What the evaluation reuses between the runs of one batch of episodes (a learned policy's training seeds run the
same episodes one after another): the episode's goal (``topocut.episode.scoring.task_goal``) and its pieces' bodies
and sizes (``topocut.reward.distance``), each equal to what is built afresh."""
import numpy as np
import pytest

from topocut.reward.config import RewardConfig
from topocut.reward.size import particle_spacing, size_descriptor
from topocut.reward.strays import body
from topocut.sim.objects import ObjectPose
from topocut.tasks import get_task, task_config


def test_a_kept_goal_is_the_goal_made_again_and_each_caller_gets_its_own_copy(monkeypatch):
    from topocut.episode import scoring

    scoring._GOALS.clear()
    task = get_task("slice")
    calls = []
    make = type(task).make_goal

    def counted(self, *a, **k):
        calls.append(a[1:3])
        return make(self, *a, **k)

    monkeypatch.setattr(type(task), "make_goal", counted)
    cfg = task_config("slice", max_cuts=3, thickness=0.05)
    pose = ObjectPose(0.51, 0.49, 0.2, 0.9)
    a = scoring.task_goal(cfg, "cube", pose, 0.0125, 0.05, seed=3)
    b = scoring.task_goal(cfg, "cube", pose, 0.0125, 0.05, seed=3)
    assert len(calls) == 1  # the second is the kept one
    fresh = make(task, cfg, "cube", pose, 0.0125, board_z=0.05, seed=3)
    for g in (a, b):
        np.testing.assert_array_equal(g.points, fresh.points)
        np.testing.assert_array_equal(g.labels, fresh.labels)
        assert len(g.fragments) == len(fresh.fragments) and len(g.planes) == len(fresh.planes)
        for f, h in zip(g.fragments, fresh.fragments):
            np.testing.assert_array_equal(f, h)
    a.fragments[0][:] = 0.0  # a policy changing what it was given changes no other episode's goal
    c = scoring.task_goal(cfg, "cube", pose, 0.0125, 0.05, seed=3)
    np.testing.assert_array_equal(c.fragments[0], fresh.fragments[0])
    assert len(calls) == 1
    # another seed, pose or config is another goal
    scoring.task_goal(cfg, "cube", pose, 0.0125, 0.05, seed=4)
    scoring.task_goal(cfg, "cube", ObjectPose(0.51, 0.49, 0.2, 0.91), 0.0125, 0.05, seed=3)
    scoring.task_goal(task_config("slice", max_cuts=3, thickness=0.04), "cube", pose, 0.0125, 0.05, seed=3)
    assert len(calls) == 4
    for i in range(scoring.GOALS_KEPT):  # the oldest goes once GOALS_KEPT newer ones are kept
        scoring.task_goal(cfg, "cube", pose, 0.0125, 0.05, seed=100 + i)
    scoring.task_goal(cfg, "cube", pose, 0.0125, 0.05, seed=3)
    assert len(calls) == 4 + scoring.GOALS_KEPT + 1


@pytest.mark.parametrize("strays", [0, 12])
def test_a_goal_pieces_body_and_size_are_those_estimated_on_its_body(strays):
    """_goal_piece estimates the spacing once; the size is the one the body's own estimate gives (the reward before:
    body, then size_descriptor(body) estimating again), with strays (the body drops them: estimated again) or
    without (an ideal piece: the same points, the same estimate)."""
    from topocut.reward.distance import _goal_piece

    s = 0.004
    rng = np.random.default_rng(1)
    g = np.stack(np.meshgrid(*[np.arange(12) * s] * 3, indexing="ij"), -1).reshape(-1, 3)
    g = g + rng.uniform(-0.25 * s, 0.25 * s, g.shape)
    g = np.concatenate([g, rng.uniform(0.2, 0.3, (strays, 3))])  # far strays: no neighbours
    cfg = RewardConfig()
    kept, size = _goal_piece(g, None, cfg)
    ref_body = body(g, particle_spacing(g), cfg.stray_share)
    np.testing.assert_array_equal(kept, ref_body)
    np.testing.assert_array_equal(size, size_descriptor(ref_body))
    assert (len(kept) < len(g)) == (strays > 0) and cfg.stray_share > 0
    kept2, size2 = _goal_piece(g, s, cfg)  # a known spacing: both take it
    np.testing.assert_array_equal(size2, size_descriptor(body(g, s, cfg.stray_share), s))

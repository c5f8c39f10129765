"""The episode engine (topocut.episode.run_episodes) batches episodes of different objects, poses and tasks in
one simulator batch, and each episode's log equals the same episode run alone (batch_size 1).

Scenes are independent (tests/test_sim_mixed_batch.py) and this session's Taichi runs on one CPU thread, so the
states agree to float rounding; discovery and reward of equal states are then equal.  Rewards are compared
at 1e-6, actions, turns, piece counts and labels exactly.  The batch holds a stick episode (push, a turn after
its first cut) beside slices (no push, no turn), and 3 episodes at batch size 2 leave the second batch with a
frozen padding scene.
"""
import numpy as np
import pytest

from topocut.episode import Episode, default_scoring, run_episodes
from topocut.planning.heuristic import HeuristicPolicy
from topocut.reward.config import RewardConfig
from topocut.sim.config import SimConfig
from topocut.sim.objects import ObjectPose
from topocut.tasks.config import TaskConfig
from topocut.topology.config import TopologyConfig

SIM = dict(n_grid=32, push_time=0.008, settle_time=0.0074)
EPISODES = [
    Episode("cube", ObjectPose(0.5, 0.5, 0.1, 1.0), 11, TaskConfig("stick", max_cuts=3, push=True)),
    Episode("cake", ObjectPose(0.51, 0.49, -0.2, 0.9), 12, TaskConfig("slice", max_cuts=3)),
    Episode("cube", ObjectPose(0.49, 0.5, 0.0, 1.1), 13, TaskConfig("slice", max_cuts=3, thickness=0.05)),
]


class Stopping(HeuristicPolicy):
    """The goal's planes; stops (None) after ``limit`` cuts in episodes of seed 12, so its scene idles."""

    def reset(self, goal, seed=None):
        super().reset(goal)
        self.limit = 1 if seed == 12 else None

    def act(self, obs):
        if self.limit is not None and self.t >= self.limit:
            return None
        return super().act(obs)


@pytest.fixture(scope="module")
def logs():
    from topocut.sim.env import CuttingEnv

    sc = default_scoring(RewardConfig(), TopologyConfig(resolution=48))
    out = {}
    for B in (2, 1):
        env = CuttingEnv(SimConfig(**SIM, batch_size=B))
        calls = []
        if B > 1:
            orig = env.reset_scenes
            env.reset_scenes = lambda *a, orig=orig, calls=calls, **k: calls.append(a[0]) or orig(*a, **k)
        out[B] = run_episodes(env, EPISODES, Stopping(), sc, max_cuts=3), calls
    return out


def test_batched_episodes_equal_episodes_run_alone(logs):
    (batched, calls), (alone, _) = logs[2], logs[1]
    assert calls == [["cube", "cake"], ["cube", "cube"]]  # two batches; the second padded with a copy
    for a, b in zip(alone, batched):
        assert a.status == b.status == "ok", (a.error, b.error)
        assert a.actions == b.actions and a.turns == b.turns and a.num_pieces == b.num_pieces
        assert np.allclose(a.rewards, b.rewards, atol=1e-6, rtol=0) and abs(a.initial_reward - b.initial_reward) < 1e-6
        assert np.array_equal(a.labels, b.labels)


def test_each_episode_follows_its_own_task(logs):
    stick, short, thick = logs[2][0]
    assert stick.turns == [1] and len(stick.actions) == 3  # the slab laid flat after the first cut
    assert short.turns == [] and len(short.actions) == 1  # its policy stopped: the scene idled after one cut
    assert thick.turns == [] and len(thick.actions) == 3
    assert stick.num_pieces[-1] >= 3 and thick.num_pieces[-1] >= 3  # the cuts made pieces
    assert len({len(e.labels) for e in (stick, short, thick)}) == 3  # three particle counts in the batches

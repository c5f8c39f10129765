"""Scenes of one batch may hold different objects (and poses): each evolves as it would alone.

CuttingEnv.reset_scenes pads every scene to the largest particle count with material -1, which no phase
(scatter, grid, gather, blade damage) visits.  Scene b of a mixed batch cut with action b must then equal
the same object cut alone at batch_size=1.  The session runs Taichi on one CPU thread (tests/conftest.py),
so the atomics add in the same order; 1e-5 leaves room for a multi-threaded or GPU runtime.
"""
import numpy as np
import pytest

from topocut.sim.action import KnifeAction
from topocut.sim.config import SimConfig
from topocut.sim.objects import ObjectPose

SMALL = dict(n_grid=32, push_time=0.008, settle_time=0.0074)
SCENES = [("cube", ObjectPose(), 0), ("cake", ObjectPose(x=0.52, yaw=0.4, scale=0.9), 3)]
ACTIONS = [KnifeAction(0.5, 0.5, yaw=0.3), KnifeAction(0.52, 0.5, depth=0.05)]
FIELDS = ("x", "v", "C", "F", "sigma_y", "damage", "material", "piece")


@pytest.fixture(scope="module")
def runs():
    from topocut.sim.env import CuttingEnv

    mixed = CuttingEnv(SimConfig(**SMALL, batch_size=2))
    st = mixed.reset_scenes([o for o, _, _ in SCENES], [p for _, p, _ in SCENES], [s for _, _, s in SCENES])
    before = [st.scene(b)[0].copy() for b in range(2)]
    info = mixed.cut(ACTIONS)
    mixed.push()
    together = [mixed.get_state(b) for b in range(2)]
    alone, infos = [None, None], [None, None]
    env = CuttingEnv(SimConfig(**SMALL, batch_size=1))  # one solver (one compile): the larger scene first sizes it
    for b in np.argsort(-mixed.counts):
        (obj, pose, seed), action = SCENES[b], ACTIONS[b]
        env.reset(obj, pose, seed)
        infos[b] = env.cut(action)
        env.push()
        alone[b] = env.get_state(0)
    return mixed, before, info, together, alone, infos


def test_scenes_hold_their_own_particle_counts(runs):
    mixed, before, _, together, alone, _ = runs
    counts = mixed.counts
    assert counts[0] != counts[1] and mixed.n == counts.max()
    assert [len(s["x"]) for s in together] == [len(s["x"]) for s in alone] == list(counts)
    small = int(np.argmin(counts))
    mat = mixed.solver.material.to_numpy()[small]
    assert (mat[counts[small]:] == -1).all() and (mat[:counts[small]] >= 0).all()
    # the padding rows never move (no phase visits them)
    assert np.abs(mixed.solver.x.to_numpy()[small, counts[small]:mixed.n]).max() == 0
    assert all(len(b) == c for b, c in zip(before, counts))


def test_each_scene_equals_its_object_cut_alone(runs):
    _, _, info, together, alone, infos = runs
    for b in range(2):
        for k in FIELDS:
            a, t = np.asarray(alone[b][k], np.float64), np.asarray(together[b][k], np.float64)
            assert a.shape == t.shape, k
            assert np.abs(a - t).max() < 1e-5, (b, k, float(np.abs(a - t).max()))
        assert info.sweeps[b] == infos[b].sweeps[0]
        assert abs(info.work[b] - infos[b].work[0]) <= 1e-5 * max(1.0, abs(infos[b].work[0]))
        assert info.newly_damaged[b] == infos[b].newly_damaged[0] > 0  # the knife cut in both scenes
    # the full cut separated the cube into two pieces; the partial cut left the cake in one
    assert len(np.unique(together[0]["piece"])) == 2 and len(np.unique(together[1]["piece"])) == 1


def test_a_scene_takes_a_state_of_another_size(runs):
    mixed, _, _, together, _, _ = runs
    big = int(np.argmax(mixed.counts))
    mixed.set_state(together[1 - big], b=big)  # the smaller scene's state into the larger scene's slot
    assert (mixed.counts == len(together[1 - big]["x"])).all() and mixed.scene_n is None
    with pytest.raises(ValueError, match="room for"):
        mixed.set_state({"x": np.zeros((mixed.solver.capacity + 1, 3))}, b=0)


def test_idle_and_diverged_scenes_stay_put_while_the_others_move(runs):
    mixed = runs[0]
    mixed.reset_scenes(["cube", "cake"], [ObjectPose(), ObjectPose()], [0, 0])
    x0 = [mixed.get_state(b)["x"].copy() for b in range(2)]
    info = mixed.cut([None, ACTIONS[1]])  # scene 0's episode has ended: no cut, no substep
    assert info.sweeps[0] is None and info.substeps_per_scene[0] == 0 and info.newly_damaged[0] == 0
    assert np.array_equal(mixed.get_state(0)["x"], x0[0]) and mixed.sweeps[0] == []
    assert np.abs(mixed.get_state(1)["x"] - x0[1]).max() > 1e-4
    # a NaN in scene 1: with freeze_diverged it is frozen and named in ``dead``, scene 0 goes on
    x = mixed.solver.x.to_numpy()
    x[1, 0] = np.nan
    mixed.solver.x.from_numpy(x)
    mixed.freeze_diverged = True
    try:
        before = mixed.get_state(0)["x"].copy()
        mixed.simulate(20)
        assert mixed.dead.tolist() == [False, True]
        frozen = mixed.get_state(1)["x"]
        mixed.simulate(10)
        assert np.array_equal(mixed.get_state(1)["x"], frozen, equal_nan=True)
        assert np.abs(mixed.get_state(0)["x"] - before).max() > 0  # scene 0 kept settling
    finally:
        mixed.freeze_diverged = False
    mixed.freeze_diverged = False
    with pytest.raises(Exception, match="diverged"):
        mixed.set_state(mixed.get_state(1), b=None)  # a fresh load clears ``dead``; the NaN now raises
        mixed.simulate(20)

"""A batched cut gives every scene its own substep budget: scene b equals the same cut run alone (B=1).

Scene b runs ceil(depth_b / (speed_b dt)) + dwell substeps (sim.dwell_time) and is then frozen (``frozen_at``:
no phase touches it) while deeper scenes finish.  Before, every scene ran the deepest scene's budget, so a
shallow cut kept settling under a resting knife and MPPI's replay of its best sample (B=1) disagreed with
the batched evaluation.  Scenes share no data, and the session's single CPU thread (tests/conftest.py)
adds every scene's atomics in the same order at B=1 and B=2, so the runs agree bit for bit here; the
1e-5 tolerance only leaves room for a multi-threaded or GPU runtime (atomics add in any order there).
"""
import numpy as np
import pytest

from topocut.sim.action import KnifeAction
from topocut.sim.config import SimConfig

# a shallow partial cut (stops 4 cm into the cube) and a tilted, yawed full cut down to the board
ACTIONS = [KnifeAction(0.5, 0.5, depth=0.04), KnifeAction(0.47, 0.5, yaw=0.3, tilt=0.2)]
SMALL = dict(n_grid=32, push_time=0.008, settle_time=0.0074)
FIELDS = ("x", "v", "C", "F", "sigma_y", "damage")


@pytest.fixture(scope="module")
def envs():
    from topocut.sim.env import CuttingEnv

    batched = CuttingEnv(SimConfig(**SMALL, batch_size=2))
    single = CuttingEnv(SimConfig(**SMALL, batch_size=1))
    batched.reset("cube")
    yield batched, single, batched.get_state(0)
    batched.cfg.cut_substeps = single.cfg.cut_substeps = None


def _cut(env, state, actions):
    env.set_state(state)
    info = env.cut(actions)
    return info, [dict(env.get_state(b), Jp=env.solver.Jp.to_numpy()[b, :env.n]) for b in range(env.B)]


def _compare(envs, cut_substeps):
    batched, single, state = envs
    batched.cfg.cut_substeps = single.cfg.cut_substeps = cut_substeps  # read per cut()
    info2, scenes2 = _cut(batched, state, ACTIONS)
    diffs = {}
    for b, action in enumerate(ACTIONS):
        info1, (scene1,) = _cut(single, state, action)
        for k in FIELDS + ("Jp",):
            diffs[f"{k}{b}"] = float(np.abs(scenes2[b][k].astype(np.float64) - scene1[k]).max())
        for k in ("force", "peak_force", "work", "knife_end", "newly_damaged"):
            diffs[f"{k}{b}"] = float(np.abs(np.asarray(getattr(info2, k)[b], np.float64) - getattr(info1, k)[0]).max())
        assert info2.substeps_per_scene[b] == info1.substeps_per_scene[0] == info1.substeps
        assert info2.sweeps[b] == info1.sweeps[0]
    assert info2.substeps == info2.substeps_per_scene.max()
    assert max(diffs.values()) < 1e-5, {k: v for k, v in diffs.items() if v >= 1e-5}
    assert info2.work.min() > 0 and info2.newly_damaged.min() > 0  # the knife really cut in both scenes
    assert (batched.solver.frozen_at.to_numpy() == 2 ** 30).all()  # every scene moves again after the cut
    return info2, scenes2, diffs


def test_batched_cut_equals_single_cuts_of_different_depth(envs):
    info, scenes, _ = _compare(envs, None)
    short, full = info.substeps_per_scene
    assert full - short > 100  # scene 0 sat frozen for >100 substeps of scene 1's travel
    assert np.abs(scenes[0]["v"]).max() > 1e-3  # and it was still moving: running on would have changed it


def test_batched_cut_with_cut_substeps_uses_each_scenes_own_speed(envs):
    # cut_substeps fixes the travel substeps: both scenes get the same budget, each its own knife speed
    info, _, _ = _compare(envs, 120)
    assert info.substeps_per_scene[0] == info.substeps_per_scene[1]
    speeds = envs[0].solver.k_speed.to_numpy()
    assert speeds[1] > 3 * speeds[0]  # the full cut travels much further in the same substeps


def test_frozen_scene_does_not_move_inside_a_graph_chunk(envs):
    batched, _, state = envs
    batched.set_state(state)
    batched.simulate(5)
    after5 = batched.get_state(1)  # scene 1 after 5 free substeps
    batched.set_state(state)
    s = batched.solver
    s.frozen_at.from_numpy(np.array([2 ** 30, batched.step_count + 5], np.int32))
    try:
        batched.simulate(16)  # one ti.graph chunk: scene 1 freezes at its 6th substep, scene 0 runs on
        # the last substep's clear and grid update left the idle scene out (MPMSolver.wrote): its grid is empty
        assert s.wrote.to_numpy().tolist() == [1, 0]
        m = s.grid_m.to_numpy()  # B*K,n,n,n
        assert m[s.K:].max() == 0 and m[:s.K].max() > 0
    finally:
        s.frozen_at.fill(2 ** 30)
    moved, frozen = batched.get_state(0), batched.get_state(1)
    for k in ("x", "v", "C", "F"):
        np.testing.assert_array_equal(frozen[k], after5[k], err_msg=k)
    assert np.abs(moved["x"] - after5["x"]).max() > 0  # scene 0 kept going (it starts from the same state)

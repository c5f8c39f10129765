"""CuttingEnv.turn: pieces picked up, turned rigidly and laid on the board (docs/tasks.md#turn-primitive).

Expected values from the rotation matrix written out by hand (90 deg about +y: x -> -z, z -> +x)."""
import numpy as np
import pytest

from topocut.sim.action import KnifeAction
from topocut.sim.config import SimConfig
from topocut.sim.env import CuttingEnv
from topocut.sim.objects import ObjectPose
from topocut.sim.runtime import init_taichi
from topocut.tasks import Turn

R_Y90 = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # about +y by +90 deg: x -> -z, z -> x


@pytest.fixture(scope="module")
def cut_cube():
    init_taichi("cpu", cpu_threads=1)
    cfg = SimConfig(n_grid=32, settle_time=0.0, turn_settle_time=0.0)
    env = CuttingEnv(cfg, batch_size=1)
    env.reset("cube", ObjectPose(x=0.45, y=0.5, yaw=0.0, scale=1.0))
    env.cut(KnifeAction(x=0.49, y=0.5))
    env.push()
    return env


def test_turn_is_the_rigid_motion_and_keeps_the_rest(cut_cube):
    env = cut_cube
    before = env.get_state(0)
    x = before["x"].astype(np.float64)
    assert len(np.unique(env.piece[0])) == 2
    slab = env.piece[0] == np.bincount(env.piece[0][x[:, 0] > 0.5]).argmax()  # the piece right of the cut
    assert slab.sum() < (~slab).sum()
    c = x[slab].mean(0)
    target = (0.75, 0.5, 0.2)
    turn = Turn("slab", (0.0, 1.0, 0.0), np.pi / 2, tuple(c + [0.01, 0.0, 0.0]), target)  # centre: nearest piece
    np.testing.assert_allclose(turn.rotation(), R_Y90, atol=1e-12)
    mask = env.turn(turn)[0]  # turn_settle_time 0: the state right after the move
    np.testing.assert_array_equal(mask, slab)
    after = env.get_state(0)
    q = (x[slab] - c) @ R_Y90.T + target
    q[:, 2] += env.cfg.board_z + 0.5 * env.cfg.dx - q[:, 2].min()  # set down half a cell above the board
    np.testing.assert_allclose(after["x"][slab], q, atol=1e-5)
    np.testing.assert_array_equal(after["x"][~slab], before["x"][~slab])  # the rest untouched
    np.testing.assert_allclose(after["F"][slab], R_Y90 @ before["F"][slab] @ R_Y90.T, atol=1e-5)
    assert not after["v"][slab].any()
    assert np.ptp(after["x"][slab][:, 2]) == pytest.approx(np.ptp(x[slab][:, 0]), abs=1e-5)  # thickness vertical
    np.testing.assert_array_equal(after["piece"], before["piece"])
    assert env.sweeps[0] == []


def test_turned_piece_settles_on_the_board_and_a_turn_out_of_the_box_is_refused(cut_cube):
    env = cut_cube
    env.simulate(env.cfg.substeps(0.05))
    x = env.state().x[0]
    assert x[:, 2].min() >= env.cfg.board_z - 0.5 * env.cfg.dx
    with pytest.raises(ValueError, match="simulation box"):
        env.turn(Turn("slab", (0.0, 1.0, 0.0), np.pi / 2, (0.75, 0.5, 0.1), (0.99, 0.5, 0.2)))


def test_a_turn_settles_for_turn_settle_time_not_settle_time(cut_cube):
    """The turned scene runs sim.turn_settle_time of substeps after the move (a laid slab comes to rest before it is
    cut); the push's sim.settle_time does not enter."""
    env = cut_cube
    x = env.state().x[0].astype(np.float64)
    slab = env.piece[0] == np.bincount(env.piece[0][x[:, 0] > 0.6]).argmax()
    c = x[slab].mean(0)
    old = env.cfg.turn_settle_time, env.cfg.settle_time
    try:
        env.cfg.turn_settle_time, env.cfg.settle_time = 0.004, 0.05
        n0 = env.step_count
        env.turn(Turn("slab", (0.0, 0.0, 1.0), 0.0, tuple(c), tuple(c)))  # lay it down where it is
        assert env.step_count - n0 == env.cfg.substeps(0.004) > 0
    finally:
        env.cfg.turn_settle_time, env.cfg.settle_time = old

"""The oracle policy: the goal's planes, carried with the piece each cuts, and nothing after its steps."""
import numpy as np
import pytest

from topocut.planning.oracle import OraclePolicy, planar_rigid
from topocut.sim.objects import ObjectPose
from topocut.tasks import TaskConfig, make_goal

SP = 0.5 / 48


def test_planar_rigid_recovers_a_turn_about_z_and_a_slide():
    rng = np.random.default_rng(0)
    src = rng.uniform(0.4, 0.6, (200, 3))
    ang, t = 0.3, np.array([0.02, -0.01, 0.0])
    R = np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1]])
    R_fit, t_fit = planar_rigid(src, src @ R.T + t)
    np.testing.assert_allclose(R_fit, R, atol=1e-9)
    np.testing.assert_allclose(t_fit, t, atol=1e-9)


def _goal():
    return make_goal(TaskConfig(name="slice", thickness=0.05, max_cuts=2), "cube", ObjectPose(), SP)


def _obs(x, k):
    return {"particles": x, "cuts_done": k}


def test_the_oracle_cuts_its_planes_and_then_stops():
    goal = _goal()
    pol = OraclePolicy(goal)
    acts = [pol.act({}) for _ in range(len(goal.planes) + 2)]
    assert acts[:len(goal.planes)] == goal.planes and acts[len(goal.planes):] == [None, None]


def test_a_pushed_piece_takes_its_plane_along():
    """The rest slides 2 cm along -a1 (a push) before the second cut: the second plane moves 2 cm with it."""
    goal = _goal()
    x0 = np.concatenate([np.asarray(a.initial, np.float64) for a in goal.anchors])  # the scene's particles
    pol = OraclePolicy(goal)
    first = pol.act(_obs(x0, 0))
    side = lambda a, x: (x - a.plane_point()) @ a.normal > 0  # noqa: E731
    # nothing has moved: the planned split (but a jittered particle or two straddling the plan's plane)
    assert (side(first, x0) == side(goal.planes[0], x0)).mean() > 0.99
    a1 = goal.axes[0]
    moved = x0 - 0.02 * a1
    second = pol.act(_obs(moved, 1))
    assert (side(second, moved) == side(goal.planes[1], x0)).mean() > 0.99  # the same particles, moved
    shift = (second.plane_point() - goal.planes[1].plane_point()) @ a1
    assert shift == pytest.approx(-0.02, abs=0.5 * SP)  # (midway between two particle layers, not on the plan's)
    assert abs(second.yaw - goal.planes[1].yaw) < 1e-3


def test_a_spread_piece_is_cut_between_its_planned_sides():
    """The material beyond the second plane has spread 1 cm further out (a soft slab laid down): the rigid fit alone
    would leave the plane inside it; the oracle puts it between the particles planned on either side."""
    goal = _goal()
    anchor = goal.anchors[1]
    x0 = np.asarray(anchor.initial, np.float64)
    n = goal.planes[1].normal
    plus = anchor.side
    x = x0.copy()
    x[plus] += 0.01 * n  # only the + side moves out
    pol = OraclePolicy(goal)
    pol.act(_obs(x0, 0))
    second = pol.act(_obs(x, 1))
    s = x @ second.normal
    c = second.plane_point() @ second.normal
    assert (s[plus] > c).mean() > 0.95 and (s[~plus] < c).mean() > 0.95

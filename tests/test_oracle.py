"""The oracle policy: the goal's planes, carried with the piece each cuts, and nothing after its steps."""
import numpy as np
import pytest

from topocut.planning.oracle import OraclePolicy, planar_rigid
from topocut.sim.objects import ObjectPose
from topocut.tasks import make_goal, task_config

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
    return make_goal(task_config("slice", thickness=0.05, max_cuts=2), "cube", ObjectPose(), SP)


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
    assert first == goal.planes[0]  # nothing has moved: the plan's own plane
    a1 = goal.axes[0]
    moved = x0 - 0.02 * a1
    second = pol.act(_obs(moved, 1))
    assert (side(second, moved) == side(goal.planes[1], x0)).mean() > 0.99  # the same particles, moved
    shift = (second.plane_point() - goal.planes[1].plane_point()) @ a1
    assert shift == pytest.approx(-0.02, abs=0.5 * SP)  # (midway between two particle layers, not on the plan's)
    assert abs(second.yaw - goal.planes[1].yaw) < 1e-3


def test_a_piece_that_did_not_move_as_planned_is_cut_between_its_planned_sides():
    """The plan expected the material beyond the second plane 2 cm further in than it lies (a soft slab that spread
    when laid down, seen from the plan): the rigid fit, which averages both sides, would put the plane 1 cm into
    that material; the oracle sees its anchor particles on the wrong side and puts the plane between the sides."""
    import dataclasses

    goal = _goal()
    anchor = goal.anchors[1]
    n = goal.planes[1].normal
    plus = anchor.side
    planned = np.asarray(anchor.planned, np.float64).copy()
    planned[plus] -= 0.02 * n
    goal.anchors[1] = dataclasses.replace(anchor, planned=planned.astype(np.float32))
    x = np.asarray(anchor.initial, np.float64)  # nothing moved: the scene is the initial material
    rigid = goal.planes[1].shifted(0.01)  # where the rigid fit alone would cut
    s_rigid = x @ rigid.normal - rigid.plane_point() @ rigid.normal
    assert ((s_rigid > 0) == plus).mean() < 0.95  # the case the correction is for
    pol = OraclePolicy(goal)
    pol.act(_obs(x, 0))
    second = pol.act(_obs(x, 1))
    # back where the material parts (the plan's plane cuts through a jittered layer: within 2 mm of it), not 1 cm in
    off = (second.plane_point() - goal.planes[1].plane_point()) @ n
    assert abs(off) < 0.002 and abs(second.yaw - goal.planes[1].yaw) < 0.05  # (the odd plan turns the fit 1.3 deg)


def test_a_plane_turned_across_the_canonical_yaw_wrap_keeps_its_sides():
    """A stick cut normal to a2 (yaw 88.9 deg) whose piece turned 3 deg (to 91.9 deg): the canonical action flips its
    normal, the planned sides must not flip with it (else every such cut would take the midpoint branch)."""
    goal = make_goal(task_config("stick", thickness=0.05, width=0.05, max_cuts=3), "cube", ObjectPose(yaw=-0.02),
                     SP)
    k = 1  # the first stick cut
    anchor = goal.anchors[k]
    x0 = np.asarray(anchor.initial, np.float64)
    ang = np.radians(3.0)
    R = np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1]])
    planned = np.asarray(anchor.planned, np.float64)
    c = planned.mean(0)
    now = (planned - c) @ R.T + c  # the piece turned about its centre
    pol = OraclePolicy(goal)
    pol.initial, pol.t = x0, k  # the scene is the anchor's particles, initially at x0, now turned
    cut = pol.act(_obs(now, k))
    rigid = goal.planes[k]
    n_rigid = R @ rigid.normal
    assert abs(abs(cut.normal @ n_rigid) - 1) < 1e-6  # the rigidly turned plane: no midpoint shift needed
    off = (cut.plane_point() - (R @ (rigid.plane_point() - c) + c)) @ n_rigid
    assert abs(off) < 1e-6


def test_a_chop_across_pieces_that_moved_apart_follows_the_goal_pieces():
    """A chop (normal x) across two sticks: the goal's stick slid 5 mm along -x, the offcut stick was pushed 2 cm
    aside and 1 cm along +x.  The plane goes with the goal's stick (-5 mm); a least-squares fit of both would have
    put it ~2.5 mm the other way of its planned place, a layer off the die it sizes."""
    from topocut.sim.action import KnifeAction
    from topocut.tasks.ideal import Anchor

    g = np.stack(np.meshgrid(np.arange(-0.018, 0.02, 0.004), np.arange(-0.008, 0.01, 0.004),
                             np.arange(0.055, 0.08, 0.004), indexing="ij"), -1).reshape(-1, 3)
    pts = np.concatenate([g + [0.5, 0.45, 0.0], g + [0.5, 0.55, 0.0]])  # 2 sticks along x, split by x = 0.5
    piece = np.repeat([0, 1], len(g))
    anchor = Anchor(pts.astype(np.float32), pts.astype(np.float32), pts[:, 0] > 0.5, np.arange(len(pts)), piece,
                    piece == 0)
    plan = KnifeAction.from_plane(np.array([1.0, 0.0, 0.0]), np.array([0.5, 0.5, 0.06]), 0.05)
    now = pts + np.where((piece == 0)[:, None], [-0.005, 0.0, 0.0], [0.01, 0.02, 0.0])
    pol = OraclePolicy()
    pol.initial = pts
    cut = pol._carried(plan, anchor, now)
    shift = (cut.plane_point(0.05) - plan.plane_point(0.05)) @ np.array([1.0, 0.0, 0.0])
    assert shift == pytest.approx(-0.005, abs=1e-6) and abs(abs(cut.normal[0]) - 1) < 1e-9
    anchor.goal = None  # an anchor that does not say: all of it, the median of both sticks' slides
    both = (pol._carried(plan, anchor, now).plane_point(0.05) - plan.plane_point(0.05))[0]
    assert abs(both - shift) > 0.002

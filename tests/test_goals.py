"""Goal shapes: piece dimensions, the pyramid corner, plane order and pose following."""
import numpy as np
import pytest

from topocut.sim.action import cut_mask
from topocut.sim.objects import ObjectPose
from topocut.tasks import make_goal, task_config

SP = 0.008  # particle spacing


def extent(points, direction):
    s = points @ direction
    return s.max() - s.min()


def test_slice_has_the_requested_thickness_and_planes_bound_it():
    pose = ObjectPose(yaw=0.4)
    g = make_goal(task_config("slice", thickness=0.04, max_cuts=3), "cube", pose, SP)
    assert len(g.fragments) == 3 and len(g.planes) == 3
    n = g.planes[0].normal
    a1 = g.axes[0]
    assert abs(abs(n @ a1) - 1) < 1e-9  # planes normal to the object's long axis (yaw included)
    assert abs(abs(a1 @ [np.cos(0.4), np.sin(0.4), 0]) - 1) < 1e-9 or abs(a1 @ [np.cos(0.4), np.sin(0.4), 0]) < 1e-9
    for f in g.fragments:
        # the lattice is world-aligned, so at yaw 0.4 the slab's particles fill its thickness nearly continuously
        assert extent(f.astype(float), a1) == pytest.approx(0.04, abs=0.5 * SP)
    g0 = make_goal(task_config("slice", thickness=0.04, max_cuts=3), "cube", ObjectPose(), SP)
    for f in g0.fragments:  # yaw 0: t / SP = 5 particle layers spanning t - SP (+- jitter)
        assert extent(f.astype(float), g0.axes[0]) == pytest.approx(0.04 - SP, abs=0.5 * SP)
    # the first plane separates exactly the first slab (its side of the plane)
    pts = np.concatenate(g.fragments).astype(float)
    m = cut_mask(pts, g.planes[0])
    first = m[: len(g.fragments[0])]
    assert first.min() == first.max() and (m[len(g.fragments[0]):] != first[0]).all()


def test_stick_and_dice_dimensions():
    # cube slab 0.04 thick, 0.16 tall and wide: upright sticks, two bands of 0.024 from a face; the standing slab
    # is set off the object's corner unturned (a Turn by 0 deg) so that the stick cuts miss the rest
    g = make_goal(task_config("stick", thickness=0.04, width=0.024, max_cuts=3), "cube", ObjectPose(), SP)
    assert len(g.planes) == 3 and len(g.fragments) == 2 and [t.angle for t in g.turns] == [0.0]
    a1, a2 = g.axes[0], g.axes[1]
    for f in g.fragments:
        assert extent(f.astype(float), a1) == pytest.approx(0.04 - SP, abs=0.5 * SP)
        assert extent(f.astype(float), a2) == pytest.approx(0.024 - SP, abs=0.5 * SP)
    # dice: slab, lay it flat, one stick cut, one chop: a cube of side 0.032 (4 layers) on every axis
    d = make_goal(task_config("dice", size=0.032, max_cuts=3), "cube", ObjectPose(), SP)
    assert [s.kind for s in d.steps] == ["cut", "turn", "cut", "cut"]
    f = d.fragments[0].astype(float)
    for ax in d.axes:
        assert extent(f, ax) == pytest.approx(0.032 - SP, abs=0.5 * SP)
    with pytest.raises(ValueError, match=r"task.max_cuts=2 is too few for task=dice: it needs at least 3"):
        make_goal(task_config("dice", size=0.032, max_cuts=2), "cube", ObjectPose(), SP)


def test_pyramid_is_the_corner_tetrahedron():
    a = 0.08
    g = make_goal(task_config("pyramid", size=a), "cube", ObjectPose(yaw=0.3), SP)
    f = g.fragments[0].astype(float)
    # particle count ~ volume / SP^3: a^3/6 for the corner tetrahedron (cube object is 0.16 wide)
    assert len(f) == pytest.approx(a ** 3 / 6 / SP ** 3, rel=0.15)
    tilt = g.planes[0].canonical().tilt
    assert abs(tilt) == pytest.approx(np.arctan(1 / np.sqrt(2)), abs=1e-6)
    # the piece touches the three faces at the corner: its extents along a1, a2, z are ~a
    for ax in g.axes:
        assert a - 3 * SP < extent(f, ax) <= a  # the tip holds few particles, each >= ~SP/2 inside


def test_goal_follows_the_object_pose():
    task = task_config("stick", thickness=0.04, width=0.04, max_cuts=2)
    p0, p1 = ObjectPose(x=0.5, y=0.5, yaw=0.0), ObjectPose(x=0.52, y=0.47, yaw=0.5)
    g0, g1 = make_goal(task, "ham", p0, SP), make_goal(task, "ham", p1, SP)
    c, s = np.cos(0.5), np.sin(0.5)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    np.testing.assert_allclose(g1.axes, g0.axes @ R.T, atol=1e-9)
    # the piece's centroid moves with the object (rotate about the old centre, translate)
    shift = np.array([0.02, -0.03, 0.0])
    c0 = g0.fragments[0].mean(0) - [0.5, 0.5, 0]
    np.testing.assert_allclose(g1.fragments[0].mean(0), R @ c0 + [0.5, 0.5, 0] + shift, atol=SP)
    n0, n1 = g0.planes[1].normal, g1.planes[1].normal
    assert abs(abs(n1 @ (R @ n0)) - 1) < 1e-9


def test_goal_points_and_labels():
    g = make_goal(task_config("slice", num_goal_points=500, max_cuts=2), "cake", ObjectPose(), SP)
    assert g.points.shape == (500, 3) and g.labels.shape == (500,)
    assert set(np.unique(g.labels)) <= {0, 1, 2} and (g.labels > 0).any()
    with pytest.raises(ValueError, match="task.name"):
        make_goal(task_config("julienne"), "cake")
    with pytest.raises(ValueError, match=r"task.max_cuts=1 is too few for task=dice: it needs at least 3"):
        make_goal(task_config("dice", max_cuts=1), "cube")
    with pytest.raises(ValueError, match=r"task.size=0.5 exceeds"):
        make_goal(task_config("dice", size=0.5), "cube")


def test_goal_labels_name_the_fragments_when_a_plane_catches_nothing():
    """Slabs thinner than the particle spacing: some planes fall between particle layers and cut off nothing; the
    plan leaves them out (a goal is what its steps make).  Label i + 1 must still be fragments[i], with no label
    past the last fragment."""
    g = make_goal(task_config("slice", thickness=0.003, max_cuts=8, num_goal_points=0), "cube", ObjectPose(),
                  0.008)
    assert len(g.fragments) <= len(g.planes) < 8  # the planes that caught no particle are gone
    assert g.labels.max() == len(g.fragments)
    assert [int((g.labels == i + 1).sum()) for i in range(len(g.fragments))] == [len(f) for f in g.fragments]
    for i, f in enumerate(g.fragments):
        np.testing.assert_array_equal(g.points[g.labels == i + 1], f)
    with pytest.raises(KeyError, match="cake"):
        make_goal(task_config("slice"), "pizza")

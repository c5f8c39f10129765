"""Ice-cream scooping: spoon kinematics and the shell SDF.  One simulated scoop (its chunk against the target's rule),
the targets and the score: tests/test_reference_scooping.py."""
import math

import numpy as np
import pytest

from topocut.sim.spoon import Keyframe, SpoonPath, bowl_axis, scoop_keyframes, spoon_sdf_np
from topocut.tasks.config import SpoonConfig
from topocut.tasks.scooping_scene import block_particles, in_cup


def test_path_interpolates_pose_and_rigid_velocity():
    path = SpoonPath([Keyframe(0.0, np.zeros(3), 0.0), Keyframe(0.5, np.array([0.1, 0.0, 0.2]), math.pi / 2, "a")])
    c, a, vc, om = path.pose(0.25)
    np.testing.assert_allclose(c, [0.05, 0.0, 0.1])
    np.testing.assert_allclose(a, [math.sin(math.pi / 4), 0, math.cos(math.pi / 4)])
    np.testing.assert_allclose(vc, [0.2, 0.0, 0.4])
    np.testing.assert_allclose(om, [0.0, math.pi, 0.0])
    # a point fixed on the spoon, 3 cm along the axis: its velocity is vc + om x (p - c)
    p = lambda t: path.pose(t)[0] + 0.03 * path.pose(t)[1]  # noqa: E731
    fd = (p(0.25 + 1e-6) - p(0.25 - 1e-6)) / 2e-6
    np.testing.assert_allclose(fd, vc + np.cross(om, 0.03 * a), atol=1e-6)
    assert path.phase(0.1) == "a" and path.phase(0.6) == "done"
    np.testing.assert_allclose(path.pose(9.0)[0], [0.1, 0, 0.2]) and not path.pose(9.0)[2].any()


def test_scoop_primitive_phases():
    sp = SpoonConfig()
    top, cup_top = 0.15, 0.12
    path = scoop_keyframes(sp, (0.3, 0.44), top, cup_top, t0=1.0)
    keys = {k.phase: k for k in path.keys}
    assert [k.phase for k in path.keys] == ["start", "lower", "advance", "lift", "move", "tilt", "pour", "withdraw"]
    low, adv, lift, move, tilt = (keys[p] for p in ("lower", "advance", "lift", "move", "tilt"))
    assert low.c[2] - sp.radius == pytest.approx(top - sp.depth)  # the sphere dips depth into the block
    assert low.phi == pytest.approx(math.pi) and adv.phi == 0.0
    np.testing.assert_allclose(adv.c - low.c, [sp.advance, 0, 0], atol=1e-12)
    assert lift.phi == 0 and lift.c[2] - sp.radius > max(top, cup_top)  # level, and the bowl clears the cup
    assert move.c[0] == pytest.approx(sp.cup_center[0] - sp.radius / 2) and move.c[1] == pytest.approx(0.44)
    assert tilt.phi == pytest.approx(math.radians(110))
    # the spoon moves at spoon.speed while lowering (a straight 5 cm drop)
    assert low.t - 1.0 == pytest.approx(0.05 / sp.speed)
    # a wrong scoop (experiments/reference_scooping.py): 2 cm shallower, poured 2 cm short; the rest as before
    keys = {k.phase: k for k in scoop_keyframes(sp, (0.3, 0.44), top, cup_top, t0=1.0, depth=0.025, pour_dx=-0.02).keys}
    assert keys["lower"].c[2] - sp.radius == pytest.approx(top - 0.025)
    assert keys["move"].c[0] == pytest.approx(sp.cup_center[0] - sp.radius / 2 - 0.02)
    np.testing.assert_allclose(keys["lift"].c[[0, 2]], lift.c[[0, 2]])


def test_shell_sdf():
    sp = SpoonConfig()
    c, r, t = np.zeros(3), sp.radius, sp.thickness
    up = bowl_axis(0.0)
    pts = np.array([[0, 0, -(r + t / 2)], [0, 0, 0], [0, 0, r + t / 2], [r + t / 2, 0, -1e-4]])
    # inside the shell's bottom; the centre; above the rim (cut off); on the rim, where the rim plane is nearer
    np.testing.assert_allclose(spoon_sdf_np(pts, c, up, sp), [-t / 2, r, r + t / 2, -1e-4], atol=1e-6)


def test_block_and_cup_regions():
    sp = SpoonConfig()
    x = block_particles(sp, 0.01, 0.05, seed=0, jitter=0.0)
    assert len(x) == 24 * 24 * 10
    np.testing.assert_allclose(x.mean(0), [*sp.block_center, 0.05 + sp.block[2] / 2], atol=1e-5)  # float32
    inside = np.array([[*sp.cup_center, 0.06], [sp.cup_center[0] + sp.cup_radius + 0.001, sp.cup_center[1], 0.06],
                       [*sp.cup_center, 0.05 + sp.cup_height + 0.01], [*sp.cup_center, 0.05 + sp.cup_height + 2 * sp.radius]])
    # chunks may heap above the rim (up to a bowl's diameter); beside the wall it is out
    assert in_cup(inside, sp, 0.05).tolist() == [True, False, True, False]



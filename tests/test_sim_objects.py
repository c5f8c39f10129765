"""Objects: SDF sampling, skin fraction against analytic shell volumes, pose bounds, names (pure numpy)."""
import numpy as np
import pytest

from topocut.sim.objects import OBJECTS, SEEN, UNSEEN, ObjectPose, object_sdf, random_pose, sample_object, sample_sdf


def test_name_lists_follow_the_contract():
    assert set(SEEN) | set(UNSEEN) | {"tomato"} == set(OBJECTS) and len(OBJECTS) == 10


@pytest.mark.parametrize("name", OBJECTS)
def test_every_object_samples_inside_its_sdf_and_rests_on_the_board(name):
    pose = ObjectPose(x=0.52, y=0.48, yaw=0.2, scale=1.1)
    x, mat = sample_object(name, pose, spacing=0.01, seed=1)
    assert x.dtype == np.float32 and mat.dtype == np.int32 and len(x) > 500
    assert (object_sdf(name, x, pose) < 0).all()
    assert x[:, 2].min() >= 0.05 and x[:, 2].min() < 0.05 + 0.01  # bottom layer sits on the board
    ext = x.max(0) - x.min(0)
    assert 0.1 < ext[:2].max() < 0.4  # sizes ~0.15-0.3 scene units (x 1.1)
    assert abs(x[:, 0].mean() - 0.52) < 0.03 and abs(x[:, 1].mean() - 0.48) < 0.03
    assert set(np.unique(mat)) == {0, 1}


def test_skin_fraction_matches_shell_volume_of_cube_and_sphere():
    h, t, s = 0.1, 0.01, 0.0025  # cube half side, skin, spacing
    box = lambda p: np.abs(p - 0.5).max(-1) - h  # noqa: E731 (Chebyshev = exact inside distance of a box)
    _, mat = sample_sdf(box, [0.3] * 3, [0.7] * 3, s, t, seed=0)
    expected = 1 - ((h - t) / h) ** 3  # 1 - (0.9)^3 = 0.271
    assert abs(mat.mean() - expected) < 0.01
    r = 0.1
    ball = lambda p: np.linalg.norm(p - 0.5, axis=-1) - r  # noqa: E731
    x, mat = sample_sdf(ball, [0.3] * 3, [0.7] * 3, s, t, seed=0)
    assert abs(mat.mean() - (1 - ((r - t) / r) ** 3)) < 0.01
    assert abs(len(x) * s ** 3 - 4 / 3 * np.pi * r ** 3) < 0.02 * 4 / 3 * np.pi * r ** 3  # volume


def test_cube_sdf_is_exact_at_known_points():
    pose = ObjectPose(0.5, 0.5, 0.0, 1.0)  # cube: side 0.16, bottom on z = 0.05
    pts = np.array([[0.5, 0.5, 0.13], [0.5 + 0.1, 0.5, 0.13], [0.5, 0.5, 0.05 + 0.16 + 0.03]])
    np.testing.assert_allclose(object_sdf("cube", pts, pose), [-0.08, 0.02, 0.03], atol=1e-9)
    # yaw 90 deg and scale 1.5: the same point along y is outside by 0.1 - 0.12 -> inside by 0.02
    np.testing.assert_allclose(object_sdf("cube", [[0.5, 0.6, 0.13]], ObjectPose(0.5, 0.5, np.pi / 2, 1.5)), [-0.02],
                               atol=1e-9)


def test_random_pose_respects_bounds_and_seed():
    rng = np.random.default_rng(3)
    poses = [random_pose(rng, translation=0.03, yaw_deg=15, scale=(0.8, 1.2)) for _ in range(400)]
    a = np.array([[p.x, p.y, p.yaw, p.scale] for p in poses])
    assert (np.abs(a[:, :2] - 0.5) <= 0.03).all() and (np.abs(a[:, 2]) <= np.deg2rad(15)).all()
    assert (a[:, 3] >= 0.8).all() and (a[:, 3] <= 1.2).all()
    assert a[:, 3].max() - a[:, 3].min() > 0.35  # actually spread over the range
    assert random_pose(np.random.default_rng(7)) == random_pose(np.random.default_rng(7))
    with pytest.raises(ValueError, match="scale"):
        random_pose(rng, scale=(1.2, 0.8))


def test_sampling_is_seeded():
    a, _ = sample_object("potato", spacing=0.01, seed=4)
    b, _ = sample_object("potato", spacing=0.01, seed=4)
    c, _ = sample_object("potato", spacing=0.01, seed=5)
    np.testing.assert_array_equal(a, b)
    assert len(a) != len(c) or not np.array_equal(a, c)


def test_unknown_object_lists_valid_names():
    with pytest.raises(KeyError, match="carrot.*cake.*tomato"):
        sample_object("carrot")
    with pytest.raises(KeyError, match="valid"):
        object_sdf("carrot", np.zeros((1, 3)))


def test_sim_package_does_not_import_taichi():
    import subprocess
    import sys

    code = ("import sys, topocut.sim, topocut.sim.objects, topocut.sim.config, topocut.sim.action;"
            "assert 'taichi' not in sys.modules, 'taichi imported eagerly'")
    subprocess.run([sys.executable, "-c", code], check=True)

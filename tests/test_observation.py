"""Observation pipeline: particle FPS and the noisy depth-camera reconstruction."""
import numpy as np
import pytest

from topocut.topology.observation import ObservationConfig, _fps, _fps_numpy, make_cameras, observe, render_depth

S = 0.01


def lattice(lo, hi, s=S, seed=0):
    axes = [np.arange(a, b + 1e-9, s) for a, b in zip(lo, hi)]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return g + np.random.default_rng(seed).uniform(-0.15 * s, 0.15 * s, g.shape)  # N,3


def box():
    return lattice((0.40, 0.45, 0.055), (0.60, 0.55, 0.145))


def distance_to_box(p, lo, hi):  # P, distance outside the axis-aligned box (0 inside)
    return np.linalg.norm(np.maximum(np.maximum(lo - p, p - hi), 0.0), axis=1)


def test_particles_mode_is_fps_of_the_particles():
    x = box()
    lab = (x[:, 0] > 0.5).astype(int)
    p, l = observe(x, lab, ObservationConfig(mode="particles", num_points=300), seed=3)
    assert p.shape == (300, 3) and p.dtype == np.float32 and l.dtype == np.int32
    idx = np.array([np.flatnonzero(np.all(np.isclose(x, q, atol=1e-6), axis=1))[0] for q in p])
    assert len(np.unique(idx)) == 300 and np.array_equal(l, lab[idx])
    # farthest point sampling covers the box: every particle is within 2.5 spacings of a sample
    d = np.linalg.norm(x[:, None] - p[None].astype(np.float64), axis=-1).min(1)
    assert d.max() < 2.5 * S
    p, _ = observe(x[:50], lab[:50], ObservationConfig(num_points=300))
    assert len(p) == 50  # never more points than particles


@pytest.mark.parametrize("fps", [_fps, _fps_numpy])
def test_fps_picks_the_farthest_points(fps):
    pts = np.array([[0, 0, 0], [1, 0, 0], [0.5, 0, 0], [0.9, 0, 0], [0.1, 0, 0]], float)
    for seed in range(5):
        idx = fps(pts, 3, seed=seed)  # whatever the start: both ends and the midpoint (up to a start at 0.1/0.9)
        assert len(set(idx.tolist())) == 3
        chosen = np.sort(pts[idx, 0])
        assert np.diff(chosen).min() >= 0.4 - 1e-9


def test_depth_of_a_flat_sheet_seen_from_above():
    # a sheet at z = 0.1 under the top camera at height target_z + d: depth = 0.6 - 0.02 - radius at the centre
    sheet = lattice((0.4, 0.4, 0.1), (0.6, 0.6, 0.1), s=0.005)
    cfg = ObservationConfig(views=0, top_view=True, camera_distance=0.6, target=[0.5, 0.5, 0.08])
    (cam,) = make_cameras(cfg)
    img = render_depth(sheet, cam, radius=0.004)
    c = img[cfg.image_height // 2 - 2: cfg.image_height // 2 + 2, cfg.image_width // 2 - 2: cfg.image_width // 2 + 2]
    assert np.all(np.abs(c - (0.6 - 0.02 - 0.004)) < 0.002)
    assert np.isinf(img[0, 0])  # the corner of the image sees only background
    # footprint: the sheet's 0.2 x 0.2 at distance 0.58 covers (0.2 f / 0.58)^2 pixels
    side = 0.2 * cam.f / 0.58
    assert np.isfinite(img).sum() == pytest.approx(side ** 2, rel=0.15)


def test_depth_mode_points_lie_on_the_box_within_the_noise_bound():
    x = box()
    cfg = ObservationConfig(mode="depth", num_points=800, noise_std=0.001)
    p, l = observe(x, np.zeros(len(x), int), cfg, seed=0)
    assert p.shape == (800, 3) and l.shape == (800,)
    radius = 0.75 * S  # the default splat radius for this lattice
    bound = radius + cfg.noise_margin * cfg.noise_std + cfg.voxel_size * np.sqrt(3) + 0.003
    lo, hi = x.min(0), x.max(0)
    assert distance_to_box(p.astype(np.float64), lo, hi).max() < bound
    # the reconstruction fills the box: its sample spans the box in every direction
    assert np.all(p.min(0) < lo + 0.01) and np.all(p.max(0) > hi - 0.01)
    assert p[:, 2].min() >= cfg.board_z


def test_depth_mode_keeps_labels_away_from_the_cut():
    x = box()
    x[x[:, 0] > 0.5, 0] += 0.004  # two pieces with a small gap at x = 0.5
    lab = np.where(x[:, 0] > 0.5, 7, 3)
    p, l = observe(x, lab, ObservationConfig(mode="depth", num_points=600), seed=1)
    far = np.abs(p[:, 0] - 0.502) > 0.02
    assert far.sum() > 300
    assert np.array_equal(l[far], np.where(p[far, 0] > 0.502, 7, 3))
    assert set(np.unique(l).tolist()) == {3, 7}


def test_observation_config_errors():
    with pytest.raises(ValueError, match="particles, depth"):
        ObservationConfig(mode="lidar").validate()
    with pytest.raises(ValueError, match="labels"):
        observe(box(), np.zeros(3), ObservationConfig())


@pytest.mark.parametrize("mode", ["particles", "depth"])
def test_no_points_or_one_point_observe_nothing_without_crashing(mode):
    cfg = ObservationConfig(mode=mode, num_points=64)
    for n in (0, 1) if mode == "depth" else (0,):
        pts, lab = observe(np.full((n, 3), 0.5), np.zeros(n, int), cfg)
        assert pts.shape == (0, 3) and pts.dtype == np.float32 and lab.shape == (0,) and lab.dtype == np.int32
    # a cloud behind every camera renders background only
    cam = make_cameras(ObservationConfig())[0]
    far = cam.t - 5.0 * cam.R[2]  # behind the camera along its viewing axis
    assert np.isinf(render_depth(far[None], cam, 0.01)).all()


def test_the_scenes_fps_in_one_launch_equals_fps_of_each_scene(monkeypatch):
    """fps_clouds' one launch (``_fps_padded``: the clouds padded into one float64 batch, each start found as
    ``fps`` finds it; run here on the CPU's Warp) picks what ``fps`` picks on each cloud, to the index: clouds of
    different sizes, one smaller than the sample (all its points, no padding copies), and an unjittered lattice
    whose distances tie exactly.  ``observe_scenes`` built on it (the evaluation's ``observe.batch`` on a GPU)
    gives each scene's ``observe``; a start taken from a centroid summed in another order (the device's) is not
    what the test accepts: it compares indices, not sets."""
    from topocut.eval.protocol import make_observe_fn
    from topocut.metrics import fps, sampling
    from topocut.topology import observation

    rng = np.random.default_rng(0)
    g = np.stack(np.meshgrid(*[np.arange(9) * S] * 3, indexing="ij"), -1).reshape(-1, 3)  # 729 exact ties
    clouds = [box(), box()[::3] + 0.01, g, rng.uniform(0, 0.1, (40, 3))]
    picked = sampling._fps_padded([np.asarray(c, np.float64) for c in clouds], 200, "cpu")
    for c, idx in zip(clouds, picked):
        np.testing.assert_array_equal(idx, fps(c, min(200, len(c))))
    assert len(picked[3]) == 40 and len(set(picked[3].tolist())) == 40

    cfg = ObservationConfig(mode="particles", num_points=200)
    labels = [np.arange(len(c)) % 5 for c in clouds]
    monkeypatch.setattr("topocut.metrics.fps_clouds", lambda xs, n, device: sampling._fps_padded(xs, n, "cpu"))
    many = observation.observe_scenes(clouds, labels, cfg, seeds=[1, 2, 3, 4], device="cuda")
    fn = make_observe_fn("particles", 200, device="cuda")
    for c, lab, s, (p, lb), (p2, lb2) in zip(clouds, labels, [1, 2, 3, 4], many, fn.batch(clouds, labels, [1, 2, 3, 4])):
        q, ql = observe(c, lab, cfg, s)
        np.testing.assert_array_equal(p, q)
        np.testing.assert_array_equal(lb, ql)
        np.testing.assert_array_equal(p2, fn(c, lab, s)[0])
        np.testing.assert_array_equal(lb2, fn(c, lab, s)[1])
    # depth mode goes scene by scene: the same as observe with each scene's seed
    dcfg = ObservationConfig(mode="depth", num_points=100)
    for (p, _), c, s in zip(observation.observe_scenes(clouds[:2], labels[:2], dcfg, [5, 6], "cuda"), clouds, [5, 6]):
        np.testing.assert_array_equal(p, observe(c, np.zeros(len(c), int), dcfg, s)[0])

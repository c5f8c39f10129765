"""Spectral reward: invariances, discrimination, the eigenvector term, R(d), matching, torch path."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from topocut.reward import (
    RewardConfig,
    descriptor,
    match,
    piece_distance,
    piecewise_reward,
    reward_from_distances,
    spectral_descriptors,
    spectral_distance,
    spectral_reward,
    spectral_rewards,
)
from topocut.reward.spectral import hks_signature, laplacian, resample, smallest_eigenpairs

H = 0.004  # lattice spacing of the test shapes


def box(a, b, c, seed=0, h=H):
    rng = np.random.default_rng(seed)
    g = np.stack(np.meshgrid(*[np.arange(h / 2, s, h) for s in (a, b, c)], indexing="ij"), -1).reshape(-1, 3)
    return g + rng.uniform(-h / 4, h / 4, g.shape)  # jitter breaks lattice ties (FPS is then exactly equivariant)


def sphere(r, seed=0):
    p = box(2 * r, 2 * r, 2 * r, seed) - r
    return p[np.linalg.norm(p, axis=1) < r]


def moved(p, seed):
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=seed).as_matrix()
    return (p @ R.T + rng.uniform(-1, 1, 3))[rng.permutation(len(p))]


CFG = RewardConfig(num_point=256, knn=20, num_eig=12)  # smaller than the defaults: fast tests


def test_paper_eigenvector_term_vanishes_but_ours_does_not():
    p = resample(box(0.03, 0.03, 0.06), CFG)
    w, v = smallest_eigenpairs(laplacian(p, 0.006, CFG.knn), CFG.num_eig + 1)
    # the paper's ||Phi^T Phi - Phi'^T Phi'||: Phi^T Phi = I for any orthonormal eigenbasis
    np.testing.assert_allclose(v.T @ v, np.eye(v.shape[1]), atol=1e-8)
    sig = hks_signature(w[1:], v[:, 1:], CFG)
    assert np.ptp(sig) > 0.1  # the HKS distribution is not constant


def test_invariance_to_rotation_translation_permutation():
    x = box(0.03, 0.05, 0.08)
    y = box(0.03, 0.03, 0.03, seed=2)
    d0 = spectral_distance(x, y, CFG)
    for s in range(3):
        d = spectral_distance(moved(x, s), moved(y, s + 10), CFG)
        assert abs(d - d0) / d0 < 1e-3
    wx, sx = descriptor(x, 0.006, CFG)
    wm, sm = descriptor(moved(x, 5), 0.006, CFG)
    np.testing.assert_allclose(wm, wx, rtol=1e-6)
    np.testing.assert_allclose(sm, sx, rtol=1e-6, atol=1e-9)
    assert spectral_distance(x, moved(x, 7), CFG) < 1e-8


DIMS = {"slice_t": (0.012, 0.06, 0.05), "slice_2t": (0.024, 0.06, 0.05), "stick": (0.016, 0.016, 0.06),
        "die": (0.016, 0.016, 0.016), "cube": (0.026, 0.026, 0.026)}


def make(k, seed=0):
    return sphere(0.016, seed) if k == "sphere" else box(*DIMS[k], seed=seed)


def test_distinct_shapes_are_farther_apart_than_poses_and_resamplings():
    for a, b in [("slice_t", "slice_2t"), ("stick", "die"), ("sphere", "cube")]:
        d = piece_distance(make(a), make(b), CFG)  # spectral shape + size terms
        pose = max(piece_distance(make(k), moved(make(k), 3), CFG) for k in (a, b))  # same particles moved
        resampled = max(piece_distance(make(k), moved(make(k, seed=9), 3), CFG) for k in (a, b))
        # sphere vs cube of ~250 particles: the size terms' resampling noise is larger on so few particles
        factor = 1.5 if a == "sphere" else 4
        assert d > 1e4 * pose and d > factor * resampled, (a, b, d, pose, resampled)


def test_eigenvector_term_alone_separates_shapes():
    cfg = RewardConfig(num_point=256, knn=20, num_eig=12, alpha=0.0, beta=1.0)
    stick, die = box(0.016, 0.016, 0.06), box(0.016, 0.016, 0.016)
    same = spectral_distance(stick, moved(box(0.016, 0.016, 0.06, seed=4), 1), cfg)
    assert spectral_distance(stick, die, cfg) > 10 * same


def test_piecewise_reward_matches_the_paper_formula():
    cfg = RewardConfig(r_max=1.0, gamma=1.0, tau=0.1, delta=4.0)
    assert piecewise_reward(0.0, cfg) == 1.0
    assert piecewise_reward(0.05, cfg) == pytest.approx(0.95)
    assert piecewise_reward(0.1, cfg) == pytest.approx(0.9)  # continuous at tau
    assert piecewise_reward(0.2, cfg) == pytest.approx(1.0 - 0.1 - 4.0 * 0.1)
    assert piecewise_reward(10.0, cfg) == 0.0 and piecewise_reward(np.inf, cfg) == 0.0
    with pytest.raises(ValueError, match="reward.delta"):
        spectral_distance(box(0.02, 0.02, 0.02), box(0.02, 0.02, 0.02), RewardConfig(gamma=2.0, delta=1.0))


def test_size_terms_make_wrong_thicknesses_earn_nothing():
    """docs/reward.md#sweep: slabs of 3/4/6 layers: 1.33x and 1.5x and 2x the goal thickness earn nothing,
    the same slab scores ~1 (the spectral term alone is scale-free and does not see the thickness)."""
    from experiments.reward_lattice import shape_gallery

    g, cfg = shape_gallery(), RewardConfig()
    R = {(a, b): piecewise_reward(piece_distance(g[a], g[b], cfg), cfg)
         for a, b in (("slice3", "slice3"), ("slice4", "slice3"), ("slice6", "slice4"), ("slice6", "slice3"))}
    assert R["slice3", "slice3"] == pytest.approx(cfg.r_max, abs=1e-3)
    assert R["slice4", "slice3"] == 0.0 and R["slice6", "slice4"] == 0.0 and R["slice6", "slice3"] == 0.0
    assert spectral_distance(g["slice4"], g["slice3"], cfg) < 0.05  # the shape term alone: nearly blind


def test_wrong_cut_that_crosses_a_good_slab_lowers_the_total():
    """Paper Q1 on hand-built slabs: a yawed 4th-plane cut that runs into slab 2 scores below the state
    before it; the right cut scores above both."""
    t, W, Z = 3 * H, 12 * H, 8 * H
    block = box(8 * t, W, Z, 11)
    x, y = block[:, 0], block[:, 1]

    def pieces(*planes):  # each plane: x position as a function of y; a point lies past it if x >= that
        lab = sum((x >= p(y)).astype(int) for p in planes)
        return [block[lab == i] for i in np.unique(lab)]

    at = lambda c: (lambda yy: np.full_like(yy, c))  # noqa: E731
    yawed = lambda yy: 3 * t + (yy - W / 2) * np.tan(np.deg2rad(50))  # noqa: E731
    goal = [box(t, W, Z, s) for s in (1, 2, 3)]
    before, right, wrong = pieces(at(t), at(2 * t)), pieces(at(t), at(2 * t), at(3 * t)), pieces(at(t), at(2 * t), yawed)
    assert len(wrong[1]) < len(right[1])  # the yawed plane took material off the second slab
    r = {k: spectral_reward(v, goal, CFG).total for k, v in (("before", before), ("right", right), ("wrong", wrong))}
    assert r["right"] > r["before"] + 0.2 and r["wrong"] < r["before"] - 0.05


def test_bad_points_name_the_fragment():
    goal = [box(0.02, 0.02, 0.02)]
    frag = box(0.02, 0.02, 0.02)
    frag[5, 1] = np.nan
    with pytest.raises(ValueError, match=r"fragments\[1\] has 1 point\(s\) with NaN"):
        spectral_reward([box(0.02, 0.02, 0.02), frag], goal, CFG)
    with pytest.raises(ValueError, match=r"goal_fragments\[0\] has 1 point"):
        spectral_reward([goal[0]], [frag], CFG)
    with pytest.raises(ValueError, match="distinct points"):
        spectral_reward([goal[0]], [np.zeros((40, 3))], CFG)


def test_matching_maximises_reward_not_closeness():
    """A far-off extra fragment (R = 0 wherever it goes) must not pull a perfect one off its goal piece."""
    cfg = RewardConfig()
    D = np.array([[0.0, 0.3], [0.3, 1.0]])  # fragment 0 is goal 0 exactly; 0.3 and 1.0 both earn R = 0
    assert match(D, cfg) == [(0, 0), (1, 1)]  # summed distance 1.0 (minimising it would pick 0.6, reward 0)
    r = reward_from_distances(D, 2, cfg)
    assert r.matching == [(0, 0)] and r.stock == 1  # the extra piece is the uncut rest: worth 0
    assert r.total == pytest.approx(cfg.r_max / 2)  # kappa = 1/2, R(0) = r_max
    # a second piece that matches nothing is waste: it costs a full piece (weight 1 without volumes)
    r3 = reward_from_distances(np.array([[0.0, 0.3], [0.3, 1.0], [0.5, 0.5]]), 2, cfg)
    assert r3.unclipped == pytest.approx((cfg.r_max - cfg.waste_cost * cfg.r_max) / 2)
    # a half-volume extra fragment costs half (volumes given)
    r4 = reward_from_distances(np.array([[0.0, 0.3], [0.3, 1.0], [0.5, 0.5]]), 2, cfg, volumes=[1, 3, 0.5],
                               goal_volumes=[1, 1])
    assert r4.unclipped == pytest.approx((cfg.r_max - 0.5 * cfg.waste_cost * cfg.r_max) / 2) and r4.stock == 1
    # an inf pair counts as no pair
    D = np.array([[0.01, 0.05], [0.5, np.inf]])
    assert match(D, cfg) == [(0, 0)]
    R = lambda d: cfg.r_max - cfg.gamma * d  # noqa: E731  (d <= tau)
    r6 = reward_from_distances(D, 2, cfg)
    assert r6.stock == 1 and r6.total == pytest.approx((R(0.01) - cfg.mismatch_cost * (cfg.r_max - R(0.01))) / 2)
    assert match(np.array([[0.5, 0.9], [0.6, 2.0]]), cfg) == [(0, 1), (1, 0)]
    # a matched piece of partial credit pays for the material it wasted: R - (r_max - R) w
    d = 0.1
    r5 = reward_from_distances(np.array([[d]]), 1, cfg)
    Rd = piecewise_reward(d, cfg)
    assert r5.unclipped == pytest.approx(Rd - cfg.mismatch_cost * (cfg.r_max - Rd))


def test_matching_is_order_invariant_and_bounded():
    D = np.array([[0.5, 0.1, 3.0], [0.2, 0.9, 0.4], [np.inf, np.inf, np.inf], [0.3, 0.2, 0.1]])
    pairs = match(D)
    assert pairs == [(0, 1), (1, 0), (3, 2)]  # total 0.4: the optimum (checked by hand)
    perm = [2, 0, 3, 1]
    pairs_p = match(D[perm])
    assert sorted((perm[f], g) for f, g in pairs_p) == pairs

    die = box(0.016, 0.016, 0.016)
    frags = [box(0.03, 0.03, 0.03), moved(box(0.016, 0.016, 0.016, seed=3), 2), box(0.004, 0.004, 0.008)]
    goals = [die, box(0.016, 0.016, 0.04)]
    cfg = RewardConfig(num_point=256, knn=20, num_eig=12, success_distance=0.05)
    r = spectral_reward(frags, goals, cfg)
    r_p = spectral_reward(frags[::-1], goals, cfg)
    assert r.total == pytest.approx(r_p.total) and r.cut_count == r_p.cut_count
    assert (1, 0) in r.matching  # the moved die goes to the die goal
    assert np.isinf(r.distances[2]).all()  # 8 points < min_points
    assert 0.0 <= r.total <= CFG.r_max and np.all((0 <= r.per_goal) & (r.per_goal <= CFG.r_max))
    assert r.per_goal[0] > 0.8
    assert r.cut_count == sum(r.distances[f, g] <= 0.05 for f, g in r.matching) >= 1
    # kappa scales the sum
    r2 = spectral_reward(frags, goals, RewardConfig(num_point=256, knn=20, num_eig=12, kappa=1.0, clip_total=False))
    assert r2.total == pytest.approx(r.values.sum())
    # no fragment -> every goal unmatched -> 0
    assert spectral_reward([], goals, CFG).total == 0.0


def test_torch_batch_matches_scipy_path():
    torch = pytest.importorskip("torch")
    clouds = [resample(box(0.02, 0.03, 0.05, seed=s), CFG) for s in range(2)]
    n = min(len(c) for c in clouds)
    clouds = [c[:n] for c in clouds]
    w, s = spectral_descriptors(torch.tensor(np.stack(clouds)), CFG, sigma=0.006)
    for i, c in enumerate(clouds):
        wr, sr = descriptor(c, 0.006, CFG)
        np.testing.assert_allclose(w[i].numpy(), wr, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(s[i].numpy(), sr, rtol=1e-5, atol=1e-7)
    torch_cfg = RewardConfig(num_point=256, knn=20, num_eig=12, backend="torch")
    a, b = box(0.016, 0.016, 0.04), box(0.016, 0.016, 0.016)
    r1, r2 = spectral_reward([a, b], [b], CFG), spectral_reward([a, b], [b], torch_cfg)
    np.testing.assert_allclose(r1.distances, r2.distances, rtol=1e-5, atol=1e-9)


def test_metric_table_wrong_cut_scores_below_right_cut_and_pose_moves_only_hurt_distances():
    from experiments.reward_q1_sim import metric_table

    t = 3 * H  # goal: two slabs of 3 layers cut off a 9-layer block
    slab = lambda x0, seed: box(t, 12 * H, 8 * H, seed) + [x0, 0, 0]  # noqa: E731
    goal = [slab(0, 1), slab(t, 2)]
    rest = box(3 * t, 12 * H, 8 * H, 3) + [2 * t, 0, 0]
    wedge = box(2 * t, 12 * H, 8 * H, 4)
    wedge = wedge[wedge[:, 0] < 2 * t * wedge[:, 1] / (12 * H)] + [t, 0, 0]  # a cut yawed across the slab
    toppled = moved(slab(t, 5), 6)  # the right slab, fallen over somewhere else on the board
    states = [[slab(0, 7), box(4 * t, 12 * H, 8 * H, 8) + [t, 0, 0]],  # one cut
              [slab(0, 7), slab(t, 5), rest],  # right second cut
              [slab(0, 7), wedge, rest],  # wrong second cut
              [slab(0, 7), toppled, rest]]  # right cut, slab moved rigidly
    tab = metric_table(states, goal, CFG)
    r = tab["reward"]
    assert r[1] > r[0] + 0.2 and r[1] > r[2] + 0.2  # the right cut raises the reward, the wrong one less
    assert abs(r[3] - r[1]) < 1e-6  # a rigid move of a piece changes nothing
    # CD sees the move: goal piece 2 now takes a neighbouring piece, one slab away, as its closest fragment
    assert tab["cd"][3] > 2 * tab["cd"][1] and tab["cd_score"][3] < tab["cd_score"][1]
    assert tab["cd_score"].min() == 0.0 and tab["cd_score"].max() < 1.0  # 1 - d / max d over the steps


@pytest.mark.parametrize("backend", ["scipy", "torch"])
def test_rewards_of_many_scenes_equal_one_scene_at_a_time(backend):
    """spectral_rewards batches every scene's fragments through one descriptor call (MPPI's K scenes);
    each scene's result must equal spectral_reward of that scene alone, empty scenes included."""
    if backend == "torch":
        pytest.importorskip("torch")
    cfg = RewardConfig(num_point=256, knn=20, num_eig=12, backend=backend, success_distance=0.05)
    goals = [box(0.016, 0.016, 0.016), box(0.016, 0.016, 0.04)]
    scenes = [[box(0.03, 0.03, 0.03), moved(box(0.016, 0.016, 0.016, seed=3), 2)],
              [],
              [moved(box(0.016, 0.016, 0.04, seed=1), 5), box(0.004, 0.004, 0.008)]]
    batched = spectral_rewards(scenes, goals, cfg)
    assert len(batched) == len(scenes)
    for frags, r in zip(scenes, batched):
        alone = spectral_reward(frags, goals, cfg)
        assert r.total == pytest.approx(alone.total, rel=1e-6, abs=1e-9)
        assert r.matching == alone.matching and r.cut_count == alone.cut_count
        np.testing.assert_allclose(r.distances, alone.distances, rtol=1e-6)
    assert batched[1].total == 0.0 and batched[0].per_goal[0] > 0.5 and batched[2].per_goal[1] > 0.9


def test_spacing_of_a_large_piece_from_sampled_queries_matches_every_particles_median():
    """particle_spacing queries SPACING_QUERIES particles of a larger piece (against all of them): the lattice
    spacing within 2% (NN_RATIO's calibration), and within 0.2% of the median over every particle (own KD-tree);
    a piece of at most SPACING_QUERIES particles is measured on all of them, exactly as before."""
    from scipy.spatial import cKDTree

    from topocut.reward.size import NN_K, NN_RATIO, SPACING_QUERIES, particle_spacing

    big = box(0.2, 0.16, 0.08)  # 50 x 40 x 20 = 40,000 particles
    assert len(big) > 4 * SPACING_QUERIES
    full = np.median(cKDTree(big).query(big, NN_K + 1)[0][:, 1:]) / NN_RATIO
    got = particle_spacing(big)
    assert abs(got / H - 1) < 0.02
    assert abs(got / full - 1) < 0.002
    small = big[:SPACING_QUERIES]
    assert particle_spacing(small) == np.median(cKDTree(small).query(small, NN_K + 1)[0][:, 1:]) / NN_RATIO


@pytest.mark.parametrize("backend", ["scipy", "torch"])
def test_a_fragment_past_zero_by_size_alone_is_not_described_and_scores_as_if_it_were(backend):
    """d = d_spec + d_size >= the extent and fill terms of d_size: a fragment whose extents and fill alone put R at 0
    for every goal piece (the uncut stock) is neither described spectrally nor profiled; its reported d is those
    terms (a lower bound of the full d, recomputed here from spectral_distance + size_distance), and the total and
    roles equal those of the full distance matrix."""
    if backend == "torch":
        pytest.importorskip("torch")
    from topocut.reward.size import size_descriptor, size_distance

    cfg = RewardConfig(num_point=256, knn=20, num_eig=12, backend=backend)
    goals = [box(0.016, 0.016, 0.016), box(0.016, 0.016, 0.04)]
    frags = [box(0.08, 0.06, 0.04, seed=2), moved(box(0.016, 0.016, 0.016, seed=3), 2), box(0.016, 0.02, 0.04, seed=4)]
    full = np.array([[spectral_distance(f, g, cfg) + size_distance(size_descriptor(f), size_descriptor(g))
                      for g in goals] for f in frags])
    got = spectral_reward(frags, goals, cfg)
    assert (piecewise_reward(full[0], cfg) == 0).all()  # the stock: R = 0 whatever its shape
    # not described, not profiled: its extent and fill terms alone (the profile term is >= 0)
    d_size = [size_distance(size_descriptor(frags[0]), size_descriptor(g), profile_weight=0.0) for g in goals]
    np.testing.assert_allclose(got.distances[0], d_size, rtol=1e-9)
    assert (got.distances[0] < full[0] - 1e-6).all() and (got.distances[0] > 0.5).all()  # a strict lower bound
    np.testing.assert_allclose(got.distances[1:], full[1:], rtol=1e-6)  # the others: described as before
    # weights by material: sampled on one lattice, a piece weighs its particle count (docs/reward.md#weights)
    ref = reward_from_distances(full, len(goals), cfg, [len(f) for f in frags], [len(g) for g in goals])
    assert got.total == pytest.approx(ref.total, abs=1e-9) and got.stock == ref.stock == 0
    assert got.matching == ref.matching and got.cut_count == ref.cut_count


def test_a_torn_sheet_weighs_its_particles_not_its_spread():
    """w_f counts material (docs/reward.md#weights): pieces sampled on one lattice weigh their particle counts over a
    goal piece's.  A chip the blade tears into a one-layer sheet spreads its particles (its own spacing estimate
    ~1.6 H, its size descriptor's V ~4x its particles' cells); weighed by that V, two such chips overran the planned
    offcuts' budget and charged the scene (dice / burger / 0 at 128^3: R 0.34 for a perfect die)."""
    from topocut.reward.size import particle_spacing, size_descriptor

    die, offcut = box(0.03, 0.03, 0.03), box(0.03, 0.03, 0.03, seed=5) + [0.06, 0.0, 0.0]
    rng = np.random.default_rng(7)

    def sheet(x0):  # 8 x 5 particles in one layer, 1.6 lattice steps apart
        g = np.stack(np.meshgrid(np.arange(8) * 1.6 * H, np.arange(5) * 1.6 * H, [0.0], indexing="ij"), -1)
        return g.reshape(-1, 3) + rng.uniform(-H / 8, H / 8, (40, 3)) + [x0, 0.08, 0.0]

    sheets = [sheet(0.0), sheet(0.03)]
    n = len(die)
    assert all(size_descriptor(s)[3] > 3.0 * len(s) * particle_spacing(die) ** 3 for s in sheets)  # V inflated
    cfg = RewardConfig(num_point=128, knn=12, num_eig=8)
    clean = spectral_reward([die, offcut], [die], cfg, offcuts=[offcut])
    torn = spectral_reward([die, offcut, *sheets], [die], cfg, offcuts=[offcut])
    np.testing.assert_allclose(torn.weights, [1.0, 1.0, 40 / n, 40 / n], rtol=1e-12)
    assert 2 * 40 / n < cfg.offcut_slack  # within the slack: forgiven in full, the scene scores as without them
    assert torn.total == pytest.approx(clean.total, abs=1e-12) and clean.total > 0.99
    # fragments sampled on another lattice (twice the spacing: an eighth of the particles) weigh their own cells
    coarse = box(0.03, 0.03, 0.03, seed=9, h=2 * H)
    other = spectral_reward([coarse], [die], cfg)
    cell = lambda p: particle_spacing(p) ** 3  # noqa: E731
    assert len(coarse) < len(die) / 4 and other.weights[0] == pytest.approx(min(1.0, len(coarse) * cell(coarse)
                                                                               / (n * cell(die))), rel=1e-9)
    assert other.weights[0] > 0.8


def test_size_tolerance_forgives_up_to_its_spacings_and_charges_the_excess():
    """Boxes on an unjittered lattice of spacing s: n layers have extent exactly n s and fill 1 (size.py), so a box
    one layer thicker than the goal costs size_weight * log((n + 1 - t) / n)^2 with a tolerance of t spacings (none
    from t = 1), and the default (t = 0) is the plain log ratio."""
    from topocut.reward.size import size_descriptor, size_distance

    s = 0.004

    def box(nx, ny, nz):
        g = np.stack(np.meshgrid(*(np.arange(k) * s for k in (nx, ny, nz)), indexing="ij"), -1).reshape(-1, 3)
        return g @ np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))[0].T  # posed: extents are invariant

    goal, thick = size_descriptor(box(8, 12, 16), s), size_descriptor(box(9, 12, 16), s)
    for t, want in ((0.0, 3 * np.log(9 / 8) ** 2), (0.5, 3 * np.log(8.5 / 8) ** 2), (1.0, 0.0), (2.0, 0.0)):
        assert size_distance(thick, goal, profile_weight=0.0, tolerance=t) == pytest.approx(want, abs=1e-9), t
    # two layers thinner: one spacing forgiven, one charged
    thin = size_descriptor(box(6, 12, 16), s)
    assert size_distance(thin, goal, profile_weight=0.0, tolerance=1.0) == pytest.approx(3 * np.log(7 / 8) ** 2,
                                                                                         abs=1e-9)
    with pytest.raises(ValueError, match="reward.size_tolerance"):
        RewardConfig(size_tolerance=-1).validate()

"""The batched torch reward path: masked FPS on padded clouds, device resampling, per-set goals.

References are computed independently: numpy ``fps`` on each cloud alone, the numpy-resample descriptor
path, and ``spectral_reward`` called one scene (with its own goal) at a time.
"""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from topocut.metrics.sampling import fps, fps_torch, valid_rows
from topocut.reward import RewardConfig, spectral_reward, spectral_rewards
from topocut.reward.distance import _descriptors, _raw_descriptors
from topocut.reward.matching import _is_per_set, spectral_rewards_per_goal
from topocut.reward.spectral import resample, resample_groups

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.usefixtures("one_thread")  # tiny tensors: a second OpenMP thread only spin-waits

H = 0.004  # lattice spacing of the test shapes
CFG = dict(num_point=96, knn=12, num_eig=8, min_points=16, success_distance=0.05)  # small: fast tests


def box(a, b, c, seed=0, h=H):
    rng = np.random.default_rng(seed)
    g = np.stack(np.meshgrid(*[np.arange(h / 2, s, h) for s in (a, b, c)], indexing="ij"), -1).reshape(-1, 3)
    return g + rng.uniform(-h / 4, h / 4, g.shape)  # jitter breaks lattice ties


def moved(p, seed):
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=seed).as_matrix()
    return (p @ R.T + rng.uniform(-1, 1, 3))[rng.permutation(len(p))]


def padded(clouds, rng, fill=np.nan):
    """Clouds (N_i,3) scattered into one (B,N,3) batch at random valid positions; padding holds ``fill``."""
    N = max(len(c) for c in clouds) + 7
    P, M = np.full((len(clouds), N, 3), fill), np.zeros((len(clouds), N), bool)
    for b, c in enumerate(clouds):
        pos = np.sort(rng.choice(N, len(c), replace=False))  # keeps the cloud's order among its valid slots
        P[b, pos], M[b, pos] = c, True
    return P, M


def test_masked_fps_equals_numpy_fps_of_each_cloud():
    rng = np.random.default_rng(0)
    clouds = [rng.normal(size=(n, 3)) * rng.uniform(0.1, 2, 3) for n in (300, 41, 180, 5, 64)]
    P, M = padded(clouds, rng)  # NaN padding: must never leak into a distance
    n = 64
    idx = fps_torch(torch.tensor(P), n, torch.tensor(M)).numpy()
    assert idx.shape == (len(clouds), n)
    for b, c in enumerate(clouds):
        valid = np.flatnonzero(M[b])
        k = min(n, len(c))
        np.testing.assert_array_equal(idx[b, :k], valid[fps(c, k)])  # mapped back to padded positions
        assert M[b, idx[b]].all()  # never an invalid point
        # fewer valid points than n: every valid point once, then copies of the last pick
        np.testing.assert_array_equal(idx[b, k:], np.full(n - k, idx[b, k - 1]))
        assert valid_rows(idx[b]).sum() == k
    # with a mask n may exceed the padded width: 3 points asked for 5 picks
    tiny = fps_torch(torch.tensor(clouds[3][None, :3]), 5, torch.ones(1, 3, dtype=bool))[0].numpy()
    np.testing.assert_array_equal(tiny, np.r_[fps(clouds[3][:3], 3), [fps(clouds[3][:3], 3)[-1]] * 2])
    # mask=None keeps the old signature and equals the all-valid mask
    full = torch.tensor(np.stack([clouds[0], clouds[0][::-1].copy()]))
    np.testing.assert_array_equal(fps_torch(full, 32).numpy(), fps_torch(full, 32, torch.ones(2, 300, dtype=bool)).numpy())
    np.testing.assert_array_equal(fps_torch(full, 32)[0].numpy(), fps(clouds[0], 32))


def test_masked_fps_rejects_bad_input():
    with pytest.raises(ValueError, match="no valid point"):
        fps_torch(torch.zeros(2, 4, 3), 2, torch.tensor([[True] * 4, [False] * 4]))
    with pytest.raises(ValueError, match="mask shape"):
        fps_torch(torch.zeros(2, 4, 3), 2, torch.ones(2, 3, dtype=bool))
    with pytest.raises(ValueError, match="n=5"):
        fps_torch(torch.zeros(1, 4, 3), 5)  # without a mask n may not exceed N, as before


def test_resample_groups_equal_numpy_resample():
    cfg = RewardConfig(**CFG)
    rng = np.random.default_rng(1)
    clouds = [rng.random((n, 3)) for n in (400, 96, 50, 1000, 50, 97)]
    groups = resample_groups(clouds, cfg)
    assert [len(b[0]) for _, b in groups] == [50, 96]  # whole clouds of 50, and everything with >= 96 points
    seen = []
    for ids, batch in groups:
        for j, i in enumerate(ids):
            np.testing.assert_array_equal(batch[j].numpy(), resample(clouds[i], cfg))  # the same points, in order
        seen += ids
    assert sorted(seen) == list(range(len(clouds)))


def test_device_resampled_descriptors_equal_numpy_resample_path():
    cfg = RewardConfig(**CFG, backend="torch")
    clouds = [box(0.02, 0.03, 0.05, seed=1), box(0.016, 0.016, 0.016, seed=2), box(0.012, 0.012, 0.016),
              box(0.004, 0.004, 0.008), moved(box(0.03, 0.02, 0.02, seed=3), 4)]  # 5 sizes, one below min_points
    got = _raw_descriptors(clouds, None, cfg)
    ref = _descriptors([resample(c, cfg) for c in clouds], None, cfg)
    assert [g is None for g in got] == [r is None for r in ref] == [False, False, False, True, False]
    for g, r in zip(got, ref):
        if r is not None:
            np.testing.assert_allclose(g[0], r[0], rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(g[1], r[1], rtol=1e-9, atol=1e-12)


def test_is_per_set_tells_shared_from_per_set_goals():
    g = box(0.008, 0.008, 0.008)
    assert not _is_per_set([g, g]) and not _is_per_set([g.tolist()]) and not _is_per_set([torch.tensor(g)])
    assert _is_per_set([[g], [g, g]]) and _is_per_set([(torch.tensor(g),)]) and _is_per_set([[g.tolist()]])


@pytest.mark.parametrize("backend", ["scipy", "torch"])
def test_scenes_with_their_own_goals_equal_one_scene_at_a_time(backend):
    cfg = RewardConfig(**CFG, backend=backend)
    cube, bar = box(0.016, 0.016, 0.016), box(0.012, 0.012, 0.032)
    goals_a, goals_b = [cube], [bar, cube]  # two different goals (different piece counts) in one call
    scenes = [[moved(box(0.016, 0.016, 0.016, seed=3), 2), box(0.03, 0.02, 0.02)],
              [moved(box(0.012, 0.012, 0.032, seed=1), 5), moved(box(0.016, 0.016, 0.016, seed=4), 6)],
              [],
              [box(0.012, 0.012, 0.032, seed=7)]]
    goal_sets = [goals_a, goals_b, goals_a, goals_a]
    batched = spectral_rewards(scenes, goal_sets, cfg)
    assert len(batched) == len(scenes)
    explicit = spectral_rewards_per_goal(scenes, goal_sets, cfg)
    for frags, goals, r, e in zip(scenes, goal_sets, batched, explicit):
        alone = spectral_reward(frags, goals, cfg)
        for x in (r, e):
            assert x.total == pytest.approx(alone.total, rel=1e-9, abs=1e-12)
            assert x.matching == alone.matching and x.cut_count == alone.cut_count
            assert x.per_goal.shape == (len(goals),)
            np.testing.assert_allclose(x.distances, alone.distances, rtol=1e-9)
            np.testing.assert_allclose(x.weights, alone.weights, rtol=1e-12)
    # each scene was scored against its own goal: the bar matches goal b's bar, not goal a's cube
    assert batched[1].per_goal[0] > 0.9 and batched[3].per_goal[0] < batched[1].per_goal[0]
    assert batched[2].total == 0.0
    with pytest.raises(ValueError, match="goal lists"):
        spectral_rewards_per_goal(scenes, goal_sets[:2], cfg)
    with pytest.raises(ValueError, match=r"goal_sets\[1\]"):
        spectral_rewards_per_goal(scenes[:2], [goals_a, []], cfg)


def test_torch_backend_equals_scipy_on_shared_goals():
    """The device-resampled torch path scores like the scipy path (same FPS picks, dense vs sparse eigen)."""
    goals = [box(0.016, 0.016, 0.016), box(0.012, 0.012, 0.032)]
    scenes = [[moved(box(0.012, 0.012, 0.032, seed=1), 5), box(0.03, 0.02, 0.02)], [box(0.016, 0.016, 0.016, seed=2)]]
    a = spectral_rewards(scenes, goals, RewardConfig(**CFG))
    b = spectral_rewards(scenes, goals, RewardConfig(**CFG, backend="torch"))
    for x, y in zip(a, b):
        np.testing.assert_allclose(x.distances, y.distances, rtol=1e-5, atol=1e-9)
        assert x.matching == y.matching


def test_host_and_device_eigen_solvers_agree():
    """reward.eig_solver: LAPACK's subset solver gives torch.linalg.eigh's smallest pairs (the
    signature uses phi^2 over whole kept eigenspaces, so bases and signs do not matter)."""
    import dataclasses

    from topocut.reward.config import RewardConfig
    from topocut.reward.spectral import spectral_descriptors

    rng = np.random.default_rng(4)
    batch = torch.as_tensor(rng.uniform(0, 1, (3, 128, 3)) * [0.3, 0.1, 0.05])
    cfg = RewardConfig(backend="torch", num_point=128)
    wh, sh = spectral_descriptors(batch, dataclasses.replace(cfg, eig_solver="host"))
    wd, sd = spectral_descriptors(batch, dataclasses.replace(cfg, eig_solver="device"))
    assert wh.shape == wd.shape == (3, cfg.num_eig) and sh.shape == sd.shape
    assert torch.allclose(wh, wd, rtol=1e-9, atol=1e-12) and torch.allclose(sh, sd, rtol=1e-6, atol=1e-9)
    with pytest.raises(ValueError, match="reward.eig_solver"):
        RewardConfig(eig_solver="gpu").validate()


DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.mark.parametrize("device", DEVICES)
def test_fps_kernel_picks_equal_the_loop_and_numpy_lattice_ties_included(device, monkeypatch):
    """fps_torch's one-launch kernel (the default) against its tensor loop and numpy's fps of each cloud alone: an
    unjittered lattice (exact distance ties everywhere: the first maximum must win, whatever the block's reduction
    order), random clouds, a masked batch with padding between valid points, float32, a given start, and block
    sizes from one thread a cloud to 1024.  Warp runs one thread a block on the CPU, so the reduction across a
    block's threads is checked on CUDA only (run there: benchmarks/gpu.sh)."""
    import topocut.metrics.fps_kernel as fk

    rng = np.random.default_rng(8)
    # integer multiples of 2^-8: every coordinate difference and square is exact, so distances tie exactly; one
    # point off the corner makes the start (the farthest from the centroid) unique
    grid = np.stack(np.meshgrid(*[np.arange(9)] * 3, indexing="ij"), -1).reshape(-1, 3)
    lattice = np.r_[grid, [[-3, -3, -3]]] / 256.0  # 730 points
    clouds = [lattice, rng.permutation(lattice)] + [rng.random((int(n), 3)) * [0.03, 0.15, 0.1]
                                                   for n in rng.integers(250, 900, 4)]
    P, M = padded(clouds, rng)
    p, m = torch.tensor(P, device=device), torch.tensor(M, device=device)
    loop = fps_torch(p, 200, m, method="loop").cpu().numpy()
    for b, c in enumerate(clouds):
        np.testing.assert_array_equal(loop[b], np.flatnonzero(M[b])[fps(c, 200)])
    for block in (1, 32, 256, 1024):
        monkeypatch.setattr(fk, "BLOCK_DIM", block)
        np.testing.assert_array_equal(fps_torch(p, 200, m).cpu().numpy(), loop, err_msg=f"block_dim={block}")
    start = torch.tensor([int(np.flatnonzero(M[b])[b]) for b in range(len(clouds))], device=device)
    for dtype in (torch.float64, torch.float32):
        q = p.to(dtype)
        np.testing.assert_array_equal(fps_torch(q, 64, m, start=start).cpu().numpy(),
                                      fps_torch(q, 64, m, start=start, method="loop").cpu().numpy())
    whole = torch.tensor(lattice[None], device=device)  # no mask
    np.testing.assert_array_equal(fps_torch(whole, 300).cpu().numpy(), fps_torch(whole, 300, method="loop").cpu().numpy())
    with pytest.raises(ValueError, match="method"):
        fps_torch(whole, 3, method="graph")

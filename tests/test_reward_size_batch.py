"""Every fragment's size descriptor at once (topocut.reward.size_batch, reward.size_solver=device) against the host's,
one fragment at a time (topocut.reward.distance._fragment_size): the same spacing, extents, volume, thickness profile
and kept particles, on the torch CPU backend.  The cell-list neighbour search against brute force."""
import dataclasses

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from topocut.reward import RewardConfig, distances_and_volumes
from topocut.reward.distance import _fragment_size
from topocut.reward.size import size_descriptor
from topocut.reward.size_batch import fragment_sizes, near

H = 0.004  # lattice spacing


def lattice(nx, ny, nz, seed, turn=True):
    """The simulator's jittered lattice (+-0.25 spacing an axis), nx x ny x nz particles, turned and moved at random."""
    rng = np.random.default_rng(seed)
    g = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"), -1).reshape(-1, 3) * H
    g = g + rng.uniform(-0.25, 0.25, g.shape) * H
    if turn:
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        g = g @ q.T + rng.normal(size=3) * 0.05
    return g


def pieces():
    """A slab, a stick, a die, a block past SPACING_QUERIES particles, a die with a dragged thread, a wedge, a piece
    under HOST_BELOW particles, a lone thread, and the goals they are measured against (a slab's, a die's, none)."""
    die_thread = np.concatenate([lattice(8, 8, 8, 4, turn=False),
                                 np.array([[0.032 + H * i, 0.014, 0.014] for i in range(6)])])
    wedge = lattice(25, 20, 6, 5)
    tilt = wedge @ np.array([0.3, 0.2, 1.0])
    # a lone thread: its principal box is flat, so its cells are narrower than its neighbour distances (brute force)
    thread = np.array([[H * i, 0.0, 0.0] for i in range(24)]) + np.random.default_rng(9).uniform(-H / 8, H / 8, (24, 3))
    slab_goal = np.array([size_descriptor(lattice(20, 20, 4, 10))])
    die_goal = np.array([size_descriptor(lattice(7, 7, 7, 11))] * 2)
    return [(lattice(20, 20, 4, 0), slab_goal), (lattice(30, 5, 5, 1), slab_goal), (lattice(7, 7, 7, 2), die_goal),
            (lattice(30, 25, 20, 3), die_goal), (die_thread, die_goal), (wedge[tilt < np.median(tilt)], slab_goal),
            (lattice(2, 2, 3, 6), die_goal), (lattice(20, 20, 4, 7), np.zeros((0, 13))),
            (lattice(30, 25, 20, 8), slab_goal), (thread, die_goal)]


@pytest.mark.parametrize("spacing", [None, H])
@pytest.mark.parametrize("method,budget", [("kernel", 1 << 25), ("tensor", 1 << 25), ("tensor", 1 << 16)])
def test_the_device_sizes_are_the_hosts_fragment_by_fragment(spacing, method, budget):
    """Spacing, extents, volume and profile within 1e-12 of the host's; the profile left out (NaN) where the host
    leaves it out (the block against the die's goal: past R's zero by its extents); the same particles kept (the
    die's thread loses all but its first link on both).  The neighbour queries by the Warp kernel and by tensor
    blocks; a small budget splits every tensor pass into many blocks."""
    items = pieces()
    cfg = RewardConfig(backend="torch", size_solver="device")
    dev = fragment_sizes(items, cfg, spacing, budget=budget, near_method=method)
    host = [_fragment_size(p, g, cfg, spacing) for p, g in items]
    assert np.isnan(host[3][0]).any() and not np.isnan(host[0][0]).any()  # both branches are exercised
    assert len(host[4][1]) < len(items[4][0])  # the thread was trimmed on the host
    for i, ((dd, dp), (hd, hp)) in enumerate(zip(dev, host)):
        assert np.array_equal(np.isnan(dd), np.isnan(hd)), i
        m = ~np.isnan(hd)
        np.testing.assert_allclose(dd[m], hd[m], rtol=1e-12, atol=0, err_msg=f"piece {i}")
        assert np.array_equal(dp, hp), (i, len(dp), len(hp))


@pytest.mark.parametrize("device", ["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
@pytest.mark.parametrize("method", ["kernel", "tensor"])
def test_near_counts_and_nearest_match_brute_force(method, device):
    """Counts within r <= h (less the particle itself), the k nearest (where the k-th lies within h) and the nearest
    of another set (where within h) of every particle, by cell lists of side h, equal a KD-tree's, for fragments far
    apart and fragments whose boxes overlap (each only sees its own); the Warp kernel and the tensor blocks alike."""
    rng = np.random.default_rng(3)
    frags = [lattice(9, 7, 5, 20), lattice(6, 6, 6, 21, turn=False), lattice(6, 6, 6, 22, turn=False) + H * 0.5,
             rng.uniform(0, 0.02, (300, 3))]
    count = [len(f) for f in frags]
    X = torch.from_numpy(np.concatenate(frags)).to(device)
    seg = torch.from_numpy(np.repeat(np.arange(len(frags)), count)).to(device)
    rows = torch.arange(len(X), device=device)
    h = torch.full((len(frags),), 1.6 * H, dtype=torch.float64, device=device)
    r = torch.full((len(frags),), 1.6 * H, dtype=torch.float64, device=device)
    got_n = near(X, rows, seg, rows, seg, h, len(frags), "count", radius=r, method=method).cpu()
    got_k = near(X, rows, seg, rows, seg, h, len(frags), "knn", 5, budget=1000, method=method).cpu()
    odd = rows % 3 == 0  # the nearest of the others
    got_m = near(X, rows[~odd], seg[~odd], rows[odd], seg[odd], h, len(frags), "min", method=method)[:, 0].cpu().numpy()
    X, odd = X.cpu(), odd.cpu()
    lo = 0
    for f in frags:
        tree = cKDTree(f)
        want_n = tree.query_ball_point(f, 1.6 * H, return_length=True) - 1
        want_k = tree.query(f, 5)[0]
        np.testing.assert_array_equal(got_n[lo:lo + len(f), 0].numpy(), want_n)
        sure = want_k[:, -1] <= 1.6 * H
        assert sure.sum() > len(f) // 2
        np.testing.assert_allclose(got_k[lo:lo + len(f)].numpy()[sure], want_k[sure], rtol=1e-12)
        mine = np.arange(lo, lo + len(f))
        others = mine[mine % 3 == 0]
        want_m = cKDTree(X.numpy()[others]).query(X.numpy()[mine[mine % 3 != 0]])[0]
        got = got_m[np.isin(np.flatnonzero(~odd.numpy()), mine)]
        within = want_m <= 1.6 * H
        assert within.sum() > len(want_m) // 2 and (got >= want_m * (1 - 1e-12)).all()  # past h: a farther one, or inf
        np.testing.assert_allclose(got[within], want_m[within], rtol=1e-12)
        lo += len(f)
    with pytest.raises(ValueError, match="mode"):
        near(X, rows, seg, rows, seg, h, len(frags), "mean", method=method)


def test_the_reward_distances_are_the_same_with_either_size_solver():
    """distances_and_volumes over two fragment sets (an MPPI batch) with reward.size_solver host and device: the same
    (F,G) distances and volumes, so R, roles and N_C follow."""
    items = pieces()
    goals = [items[0][0], items[2][0]]
    sets = [[p for p, _ in items[:5]], [p for p, _ in items[5:]]]
    host = RewardConfig(backend="torch", size_solver="host")
    Dh, vh, gh = distances_and_volumes(sets, goals, host)
    Dd, vd, gd = distances_and_volumes(sets, goals, dataclasses.replace(host, size_solver="device"))
    for a, b in zip(Dh, Dd):
        assert np.array_equal(np.isinf(a), np.isinf(b))
        np.testing.assert_allclose(b[np.isfinite(b)], a[np.isfinite(a)], rtol=1e-9, atol=1e-12)
    for a, b in zip(vh, vd):
        np.testing.assert_allclose(b, a, rtol=1e-12)
    np.testing.assert_array_equal(gh, gd)


def test_size_solver_is_checked():
    assert RewardConfig(size_solver="device").validate().size_solver == "device"
    with pytest.raises(ValueError, match="reward.size_solver"):
        RewardConfig(size_solver="gpu").validate()

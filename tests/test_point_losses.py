"""Device point-set losses (topocut/models/point_losses.py): Chamfer/Hausdorff against a numpy brute force,
the auction EMD against scipy's exact assignment within its stated bound emd <= d <= (1 + tol)·emd."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.optimize import linear_sum_assignment

from topocut.models.losses import position_losses
from topocut.models.point_losses import auction_assignment, chamfer, emd, emd_auction, exact_rows, hausdorff

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def brute(a: np.ndarray, b: np.ndarray):
    d = np.sqrt(((a[:, None] - b[None]) ** 2).sum(-1))
    ab, ba = d.min(1), d.min(0)
    rows, cols = linear_sum_assignment(d)
    return 0.5 * (ab.mean() + ba.mean()), max(ab.max(), ba.max()), d[rows, cols].mean()


def rand(B, N, M=None, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(B, N, 3, generator=g, dtype=dtype), torch.rand(B, M or N, 3, generator=g, dtype=dtype)


def test_chamfer_hausdorff_match_brute_force_unequal_sizes():
    a, b = rand(3, 50, 37)
    cd, hd = chamfer(a, b), hausdorff(a, b)
    for i in range(3):
        c, h, _ = brute(a[i].numpy(), b[i].numpy())
        assert float(cd[i]) == pytest.approx(c, rel=1e-9) and float(hd[i]) == pytest.approx(h, rel=1e-9)


def test_masked_losses_equal_the_restricted_sets():
    a, b = rand(4, 40, seed=1)
    valid = torch.rand(4, 40, generator=torch.Generator().manual_seed(2)) < 0.7
    cd, hd, ed = chamfer(a, b, valid), hausdorff(a, b, valid), emd_auction(a, b, valid, tol=0.01)
    for i in range(4):
        c, h, e = brute(a[i][valid[i]].numpy(), b[i][valid[i]].numpy())
        assert float(cd[i]) == pytest.approx(c, rel=1e-9) and float(hd[i]) == pytest.approx(h, rel=1e-9)
        assert e * (1 - 1e-12) <= float(ed[i]) <= e * 1.01


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("n", [64, 128, 256])
def test_auction_emd_within_bound_of_exact(n, device):
    tol = 0.01
    a, b = rand(2 if n == 256 else 3, n, seed=n)
    b = torch.cat([b[:1], a[1:] + 0.05 * b[1:]])  # one far pair (unit cube vs unit cube), the rest close
    got = emd_auction(a.to(device), b.to(device), tol=tol).cpu()
    for i in range(a.shape[0]):
        exact = brute(a[i].numpy(), b[i].numpy())[2]
        assert exact * (1 - 1e-12) <= float(got[i]) <= exact * (1 + tol)


@pytest.mark.parametrize("warm", [0, 150])
def test_identical_and_permuted_sets_are_exact(warm):
    a, _ = rand(3, 128, seed=3)
    perm = torch.stack([torch.randperm(128, generator=torch.Generator().manual_seed(i)) for i in range(3)])
    ar = torch.arange(3)[:, None]
    d, cols = emd_auction(a, a.clone(), return_assignment=True, warm_iters=warm)
    assert torch.all(d == 0) and torch.equal(cols, torch.arange(128).expand(3, 128))
    b = a[ar, perm]  # b[perm^-1[i]] = a[i]
    d, cols = emd_auction(a, b, return_assignment=True, warm_iters=warm)
    assert torch.all(d == 0) and torch.equal(perm[ar, cols], torch.arange(128).expand(3, 128))


def test_a_round_budget_leaves_the_unfinished_items_to_scipy_and_the_bound_holds():
    """A lattice against jittered copies of itself: a row left free must displace a chain of others across the
    cloud, one step a round (as on the simulator's particle clouds: docs/perception.md), so the auction needs ~100
    rounds alone (32-132 here).  With a budget of 16 the close item (jitter 0.05, 8 rounds: each item goes through its
    ε phases on its own, not at the batch's pace) finishes in the auction and the far ones go to the host's exact
    assignment; every item stays within the bound, the host's equal scipy's value, and with padding
    rows (``valid``) the host solves the valid block only."""
    ax = torch.arange(4, dtype=torch.float64)
    lat = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)  # 64 points, spacing 1
    g = torch.Generator().manual_seed(0)
    jitter = torch.tensor([0.05, 0.5, 0.5, 1.0], dtype=torch.float64)[:, None, None]
    a, b = lat.expand(4, 64, 3).clone(), lat + jitter * torch.randn(4, 64, 3, generator=g, dtype=torch.float64)
    valid = torch.ones(4, 64, dtype=torch.bool)
    valid[3, ::7] = False
    emd_auction(a, b, valid, tol=0.01)
    assert auction_assignment.last_rounds > 32  # what the budget cuts
    got, cols = emd_auction(a, b, valid, tol=0.01, return_assignment=True, rounds=16)
    assert auction_assignment.last_rounds <= 16 and exact_rows.last_items == 3
    for i in range(4):
        v = valid[i]
        exact = brute(a[i][v].numpy(), b[i][v].numpy())[2]
        assert exact * (1 - 1e-12) <= float(got[i]) <= exact * 1.01
        if i > 0:  # solved on the host
            assert float(got[i]) == pytest.approx(exact, rel=1e-12)
        assert sorted(cols[i][v].tolist()) == v.nonzero().flatten().tolist() and torch.all(cols[i][~v] == -1)


def test_batched_equals_per_item():
    a, b = rand(4, 96, seed=4)
    b = torch.cat([b[:2], a[2:] + 0.03 * b[2:]])
    d, cols = emd_auction(a, b, return_assignment=True)
    for i in range(4):
        di, ci = emd_auction(a[i:i + 1], b[i:i + 1], return_assignment=True)
        assert torch.equal(ci[0], cols[i]) and float(di[0]) == pytest.approx(float(d[i]), rel=1e-12)


def test_gradient_matches_exact_path_and_methods_agree():
    a, b = rand(2, 64, seed=5)
    b = a + 0.02 * b  # the exact and auction assignments coincide here
    grads = {}
    for method in ("exact", "auction"):
        x = a.clone().requires_grad_(True)
        v = emd(x, b, method=method)
        v.sum().backward()
        grads[method] = (v.detach(), x.grad)
    assert torch.allclose(grads["exact"][0], grads["auction"][0], rtol=1e-12)
    assert torch.allclose(grads["exact"][1], grads["auction"][1], rtol=1e-9, atol=1e-12)
    assert emd(a, b).equal(emd(a, b, method="exact"))  # auto is exact off CUDA


def test_position_losses_auction_close_to_exact_with_padding():
    a, b = rand(3, 80, seed=6)
    b = a + 0.05 * b
    valid = torch.ones(3, 80, dtype=torch.bool)
    valid[1, 60:] = False
    ex = position_losses(b, a, 0.1, valid, "exact")
    au = position_losses(b, a, 0.1, valid, "auction", 0.01)
    assert torch.equal(ex["chamfer"], au["chamfer"]) and torch.equal(ex["hausdorff"], au["hausdorff"])
    assert torch.all(au["emd"] >= ex["emd"] * (1 - 1e-12)) and torch.all(au["emd"] <= ex["emd"] * 1.01)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a GPU")
def test_cuda_graphs_give_the_eager_result(monkeypatch):
    import topocut.models.point_losses as pl

    a, b = rand(4, 128, seed=7)
    a, b = a.cuda(), (a + 0.05 * b).cuda()
    valid = torch.ones(4, 128, dtype=torch.bool, device="cuda")
    valid[2, 100:] = False
    runs = []
    for graphs in (True, True, False):  # twice with graphs: capture, then replay of the cached graph
        monkeypatch.setattr(pl, "USE_CUDA_GRAPHS", graphs)
        runs.append(emd_auction(a, b, valid, return_assignment=True))
    for d, cols in runs[:2]:
        assert torch.equal(cols, runs[2][1]) and torch.equal(d, runs[2][0])

"""The batched subspace eigensolver (topocut.reward.eigen) against closed forms and LAPACK."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.linalg
import torch

from topocut.reward.config import RewardConfig
from topocut.reward.eigen import smallest_eigenpairs_subspace
from topocut.reward.spectral import spectral_descriptors


def path_laplacian(n: int, cycle: bool = False) -> torch.Tensor:
    """Unit-weight path (or cycle) graph Laplacian (n,n)."""
    W = np.zeros((n, n))
    i = np.arange(n - 1)
    W[i, i + 1] = W[i + 1, i] = 1.0
    if cycle:
        W[0, -1] = W[-1, 0] = 1.0
    return torch.tensor(np.diag(W.sum(1)) - W)


def knn_laplacians(clouds: np.ndarray, k: int = 30) -> torch.Tensor:
    """The reward's Laplacians (Gaussian kNN graph, each cloud's own width) of clouds (B,n,3)."""
    x = torch.tensor(clouds)
    d = torch.cdist(x, x)
    dk, jk = d.topk(k + 1, dim=-1, largest=False)
    dk, jk = dk[..., 1:], jk[..., 1:]
    s = dk.mean((1, 2)).reshape(-1, 1, 1)
    W = torch.zeros_like(d).scatter_(-1, jk, torch.exp(-(dk / s) ** 2))
    W = torch.maximum(W, W.transpose(1, 2))
    return torch.diag_embed(W.sum(-1)) - W


def fragment_clouds(n: int = 512) -> np.ndarray:
    """A slab, a ball, a rod and an L-shaped block, n points each (B,n,3)."""
    rng = np.random.default_rng(3)
    out = []
    for kind in range(4):
        p = rng.uniform(-1, 1, (6000, 3))
        if kind == 0:
            p = p * [2.5, 2.5, 0.6]
        elif kind == 1:
            p = p[(p ** 2).sum(1) < 1]
        elif kind == 2:
            p = p * [3.0, 0.5, 0.5]
        else:
            p = p[(p[:, 0] < 0) | (p[:, 1] < 0)]
        out.append(p[rng.choice(len(p), n, replace=False)])
    return np.stack(out)


@pytest.mark.parametrize("cycle", [False, True])
def test_path_and_cycle_spectra_in_closed_form(cycle):
    """Path graph: lambda_k = 2 - 2 cos(pi k / n); cycle: 2 - 2 cos(2 pi k / n), every nonzero value twice
    (degenerate pairs straddle the cut at m when m is even)."""
    n, m = 160, 12
    L = path_laplacian(n, cycle)[None]
    w, v = smallest_eigenpairs_subspace(L, m)
    k = np.arange(n)
    exact = np.sort(2 - 2 * np.cos((2 if cycle else 1) * np.pi * k / n))[:m]
    np.testing.assert_allclose(w[0].numpy(), exact, atol=1e-10)
    np.testing.assert_allclose((v[0].T @ v[0]).numpy(), np.eye(m), atol=1e-10)  # orthonormal
    res = (L[0] @ v[0] - v[0] * w[0]).norm(dim=0)
    assert res.max() < 1e-8


@pytest.mark.parametrize("power", [2, 4])
def test_fragment_laplacians_match_lapack(power):
    """The reward's 512-point Laplacians: the 21 smallest values equal LAPACK's subset solver to 1e-9 of the
    largest kept value, vectors span the same eigenspaces (projector onto the first 20), residuals tiny; with A^-2
    steps and with A^-4 steps (the default)."""
    m = 21
    L = knn_laplacians(fragment_clouds())
    w, v = smallest_eigenpairs_subspace(L, m, power=power)
    assert w.shape == (4, m) and v.shape == (4, 512, m)
    for b, A in enumerate(L.numpy()):
        wr, vr = scipy.linalg.eigh(A, subset_by_index=[0, m - 1])
        np.testing.assert_allclose(w[b].numpy(), wr, rtol=0, atol=1e-9 * wr[-1])
        # compare projectors on the first 20 pairs: the gap after lambda_20 is kept in this set, so bases may
        # rotate inside an eigenspace but the projector is fixed
        gap = np.min(np.abs(wr[:20, None] - wr[None, 20:]))
        assert gap > 1e-3
        P, Pr = v[b, :, :20].numpy() @ v[b, :, :20].numpy().T, vr[:, :20] @ vr[:, :20].T
        assert np.abs(P - Pr).max() < 1e-7
        res = np.linalg.norm(A @ v[b].numpy() - v[b].numpy() * w[b].numpy(), axis=0)
        assert res.max() <= 1e-9 * np.abs(np.diag(A)).max()


def test_a_inverse_fourth_power_step_halves_the_steps(monkeypatch):
    """Convergence goes like ((lambda_j + s) / (lambda_33 + s))^power a step: A^-4 steps take about half the
    orthonormalisations of A^-2 steps on the fragments (counted here), and four Rayleigh-Ritz checks or fewer
    where A^-2 needs more; an unknown power is refused."""
    from topocut.reward import eigen

    calls = {"orth": 0, "ritz": 0}

    def counted(fn, key):
        def wrapper(*args):
            calls[key] += 1
            return fn(*args)
        return wrapper

    monkeypatch.setattr(eigen, "_orthonormalise", counted(eigen._orthonormalise, "orth"))
    monkeypatch.setattr(eigen, "_small_eigh", counted(eigen._small_eigh, "ritz"))
    L = knn_laplacians(fragment_clouds())
    counts = {}
    for power in (2, 4):
        calls.update(orth=0, ritz=0)
        smallest_eigenpairs_subspace(L, 21, power=power)
        counts[power] = dict(calls)
    steps2 = counts[2]["orth"]  # a step's Cholesky QR (A^-2: no second one at the checks)
    steps4 = counts[4]["orth"] - counts[4]["ritz"]  # less the checks' second Cholesky QR
    assert steps4 <= 0.6 * steps2, counts
    assert counts[4]["ritz"] < counts[2]["ritz"], counts
    with pytest.raises(ValueError, match="power=3; valid: 2, 4"):
        smallest_eigenpairs_subspace(L, 21, power=3)


def test_disconnected_graph_has_one_zero_per_component():
    """Three far-apart blobs: exactly three (numerically) zero eigenvalues, then the blobs' own spectra."""
    rng = np.random.default_rng(5)
    blobs = [rng.uniform(0, 1, (170, 3)) + [6.0 * i, 0, 0] for i in range(3)]
    x = np.concatenate(blobs)[None]  # 1,510,3
    L = knn_laplacians(x, k=12)
    w, _ = smallest_eigenpairs_subspace(L, 8)
    wr = scipy.linalg.eigh(L[0].numpy(), subset_by_index=[0, 7])[0]
    assert np.all(np.abs(w[0, :3].numpy()) < 1e-9) and w[0, 3] > 1e-3
    np.testing.assert_allclose(w[0].numpy(), wr, atol=1e-10 * wr[-1])


def test_small_matrices_use_the_dense_solver():
    """A block of half the matrix or more: the dense path (still the m smallest, ascending)."""
    L = path_laplacian(40)[None]
    w, v = smallest_eigenpairs_subspace(L, 21)
    exact = np.sort(2 - 2 * np.cos(np.pi * np.arange(40) / 40))[:21]
    np.testing.assert_allclose(w[0].numpy(), exact, atol=1e-12)
    assert v.shape == (1, 40, 21)


def test_descriptors_equal_the_host_solver():
    """reward.eig_solver=subspace gives the host (LAPACK) descriptors: eigenvalues and the HKS signature (built
    from phi^2 over whole kept eigenspaces, so the basis inside an eigenspace does not matter)."""
    batch = torch.tensor(fragment_clouds(256)) * 0.01
    cfg = RewardConfig(backend="torch", num_point=256)
    wh, sh = spectral_descriptors(batch, dataclasses.replace(cfg, eig_solver="host"))
    ws, ss = spectral_descriptors(batch, dataclasses.replace(cfg, eig_solver="subspace"))
    torch.testing.assert_close(ws, wh, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(ss, sh, rtol=1e-6, atol=1e-8)
    assert RewardConfig(eig_solver="subspace").validate().eig_solver == "subspace"
    with pytest.raises(ValueError, match="valid: auto, host, device, subspace"):
        RewardConfig(eig_solver="lobpcg").validate()


def test_a_batch_gives_what_each_matrix_gives_alone():
    """Matrices leave the batch when they converge (different speeds: a path graph converges slower than a
    fragment): each row equals the matrix solved alone (eigenvalues to 1e-9 of lambda_m)."""
    frags = knn_laplacians(fragment_clouds(160))
    L = torch.cat([frags, path_laplacian(160)[None] * 3.0])  # B=5
    w, _ = smallest_eigenpairs_subspace(L, 21)
    for b in range(len(L)):
        wb, _ = smallest_eigenpairs_subspace(L[b:b + 1], 21)
        np.testing.assert_allclose(w[b].numpy(), wb[0].numpy(), rtol=0, atol=1e-9 * float(wb[0, -1]))
    exact = 3.0 * np.sort(2 - 2 * np.cos(np.pi * np.arange(160) / 160))[:21]
    np.testing.assert_allclose(w[-1].numpy(), exact, atol=1e-9 * exact[-1])


def test_groups_of_different_sizes_share_one_padded_eigen_call():
    """Fragments of 256 and of 90 points in one subspace call (the smaller Laplacians padded with isolated nodes
    above every eigenvalue) give each group's host (LAPACK) descriptors; the solver is called once."""
    import topocut.reward.eigen as eigen
    from topocut.reward.spectral import spectral_descriptors_groups

    clouds = torch.tensor(fragment_clouds(256)) * 0.01
    small = clouds[:, ::3][:, :90].contiguous()  # 4 clouds of 90 points
    cfg = RewardConfig(backend="torch", num_point=256)
    calls = []
    real = eigen.smallest_eigenpairs_subspace

    def counted(L, m, **kw):
        calls.append(tuple(L.shape))
        return real(L, m, **kw)

    eigen.smallest_eigenpairs_subspace = counted
    try:
        got = spectral_descriptors_groups([clouds, small], dataclasses.replace(cfg, eig_solver="subspace"))
    finally:
        eigen.smallest_eigenpairs_subspace = real
    assert calls == [(8, 256, 256)]
    for batch, (w, s) in zip([clouds, small], got):
        wh, sh = spectral_descriptors(batch, dataclasses.replace(cfg, eig_solver="host"))
        torch.testing.assert_close(w, wh, rtol=1e-9, atol=1e-12)
        torch.testing.assert_close(s, sh, rtol=1e-6, atol=1e-8)


def test_a_matrix_not_converged_by_max_iter_is_said():
    """Too few steps: the pairs come back (Ritz pairs of the last block) with a RuntimeWarning naming the count."""
    L = knn_laplacians(fragment_clouds(160))
    with pytest.warns(RuntimeWarning, match=r"4 of 4 matrices not converged after max_iter=2"):
        w, v = smallest_eigenpairs_subspace(L, 21, max_iter=2, min_iter=1)
    assert w.shape == (4, 21) and v.shape == (4, 160, 21) and torch.isfinite(w).all()
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the default budget converges without a word
        smallest_eigenpairs_subspace(L, 21)

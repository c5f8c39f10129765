"""Spectral shape descriptors and the spectral distance d_spec (paper §3.2, appendix).

Pipeline for one point cloud X (docs/reward.md has the derivations):
  1. resample to n = min(num_point, N) points by FPS started at the point farthest from the centroid
     (pose- and order-equivariant);
  2. kNN graph (k = knn) with W_ij = exp(-d_ij^2 / sigma^2), symmetrised by max(W, W^T);
  3. L = D - W, smallest num_eig + 1 eigenpairs, the constant mode dropped;
  4. descriptor = (lambda_1..K, quantiles of the normalised HKS h_t(x) at t = c / lambda_K).

d_spec(X, Y) = alpha * mean_k (l_X,k - l_Y,k)^2 + beta * mean_q (sx_q - sy_q)^2, with
l_k = log(lambda_k + f) - mean_j log(lambda_j + f) (log eigenvalue *ratios*).
Each graph's sigma is its own mean kNN distance (unless reward.sigma fixes one), so the Laplacian
depends only on d / sigma: a scaled copy, or the same piece sampled at another density, has the same
spectrum up to one common factor, which the mean-centred logs remove.  d_spec is a *shape* distance,
free of size and point count; the size of a piece is measured by topocut.reward.size (docs/reward.md).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla
from scipy.spatial import cKDTree

from topocut.metrics.sampling import fps
from topocut.reward.config import RewardConfig


def _cfg(cfg: RewardConfig | None) -> RewardConfig:
    return (cfg or RewardConfig()).validate()


def _points(x, name: str = "points") -> np.ndarray:
    if type(x).__module__.split(".")[0] == "torch":
        x = x.detach().cpu().numpy()
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"{name} must be an (n,3) point array, got shape {x.shape}")
    if not np.isfinite(x).all():
        bad = int((~np.isfinite(x)).any(1).sum())
        raise ValueError(f"{name} has {bad} point(s) with NaN or inf coordinates (of {len(x)})")
    return x


def resample(points, cfg: RewardConfig | None = None) -> np.ndarray:
    """FPS subset (min(num_point, N), 3) of an (N,3) cloud."""
    cfg = cfg or RewardConfig()
    p = _points(points)
    return p if len(p) <= cfg.num_point else p[fps(p, cfg.num_point)]


def resample_groups(clouds, cfg: RewardConfig | None = None):
    """``resample`` of many clouds on cfg.device, grouped by resampled size: [(indices, (b,n,3) float64 tensor)].

    clouds: list of (N_i,3) float64 arrays (already checked by ``_points``).  Every cloud with more than
    num_point points goes through one padded, masked ``fps_torch`` call, so its FPS runs for all clouds at
    once on the device instead of one numpy loop per cloud; clouds with at most num_point points are used
    whole, as ``resample`` does.  In float64 the picks equal ``resample``'s (same start rule and arithmetic).
    Groups come out sorted by n; the indices say which clouds (in input order) each group's rows are.
    """
    import torch

    from topocut.metrics.sampling import fps_torch

    cfg = cfg or RewardConfig()
    dev, m = torch.device(cfg.device), int(cfg.num_point)
    sizes = [len(c) for c in clouds]
    groups: dict[int, tuple[list, list]] = {}
    for s in sorted(set(sizes)):
        if s <= m:  # used whole: one host stack and one transfer per size
            ids = [i for i, t in enumerate(sizes) if t == s]
            groups[s] = (ids, [torch.from_numpy(np.stack([clouds[i] for i in ids])).to(dev)])
    big = [i for i, t in enumerate(sizes) if t > m]
    if big:
        # ship only the real points (one concatenated transfer) and pad on the device: fragment sizes
        # vary a lot (the uncut stock vs small pieces), and B x N_max of padding would be mostly zeros
        count = torch.tensor([sizes[i] for i in big], device=dev)  # B,
        flat = torch.from_numpy(np.concatenate([clouds[i] for i in big])).to(dev)  # sum N_i,3
        B, N = len(big), max(sizes[i] for i in big)
        row = torch.repeat_interleave(torch.arange(B, device=dev), count)  # sum N_i,
        col = torch.arange(len(flat), device=dev) - torch.repeat_interleave(count.cumsum(0) - count, count)
        pts = flat.new_zeros(B, N, 3)
        pts[row, col] = flat
        mask = torch.zeros(B, N, dtype=torch.bool, device=dev)
        mask[row, col] = True
        idx = fps_torch(pts, m, mask)  # B,m
        ids, parts = groups.setdefault(m, ([], []))
        ids.extend(big)
        parts.append(pts[torch.arange(B, device=dev)[:, None], idx])  # B,m,3
    return [(ids, parts[0] if len(parts) == 1 else torch.cat(parts)) for _, (ids, parts) in sorted(groups.items())]


def mean_knn_distance(points, k: int) -> float:
    """Mean distance from each point to its k nearest neighbours (points already resampled)."""
    p = _points(points)
    k = min(k, len(p) - 1)
    return float(cKDTree(p).query(p, k + 1)[0][:, 1:].mean())


def own_sigma(points, cfg: RewardConfig | None = None) -> float:
    """The graph width of one (resampled) cloud: reward.sigma if set, else sigma_scale x its mean kNN distance."""
    cfg = _cfg(cfg)
    if cfg.sigma is not None:
        return float(cfg.sigma)
    s = cfg.sigma_scale * mean_knn_distance(points, cfg.knn)
    if not s > 0:
        raise ValueError(f"a cloud's mean kNN distance is {s}; pieces need distinct points (or set reward.sigma)")
    return s


def reference_sigma(goals, cfg: RewardConfig | None = None) -> float:
    """The mean graph width of ``goals`` (list of (m,3) clouds); kept for callers that fix one sigma."""
    cfg = _cfg(cfg)
    if cfg.sigma is not None:
        return float(cfg.sigma)
    sigma = cfg.sigma_scale * float(np.mean([mean_knn_distance(resample(g, cfg), cfg.knn) for g in goals]))
    if not sigma > 0:  # every goal piece collapsed onto one point: no graph width to compare shapes with
        raise ValueError(f"reference_sigma: the goal pieces' mean kNN distance is {sigma}; goal pieces need "
                         "distinct points (or set reward.sigma)")
    return sigma


def laplacian(points: np.ndarray, sigma: float, knn: int) -> sp.csr_matrix:
    """Sparse combinatorial Laplacian L = D - W (n,n) of the symmetrised Gaussian kNN graph."""
    n = len(points)
    k = min(knn, n - 1)
    d, j = cKDTree(points).query(points, k + 1)  # n,k+1 (self first)
    d, j = d[:, 1:], j[:, 1:]
    W = sp.csr_matrix((np.exp(-(d / sigma) ** 2).ravel(), (np.repeat(np.arange(n), k), j.ravel())), shape=(n, n))
    W = W.maximum(W.T)  # i~j if either is among the other's k nearest
    return (sp.diags(np.asarray(W.sum(1)).ravel()) - W).tocsr()


def smallest_eigenpairs(L, m: int, method: str = "eigsh"):
    """The m smallest eigenpairs (values (m,), vectors (n,m)) of a symmetric PSD matrix.

    method="eigsh": ARPACK shift-invert just below 0 (fast for sparse L);
    method="eigh": dense LAPACK with subset_by_index (the reference).
    """
    n = L.shape[0]
    if method == "eigsh" and m < n - 1:
        try:
            # a fixed start vector: ARPACK's default is random per process, which moved R in its last bits
            # between identical runs (not np.ones: that is L's null vector)
            v0 = np.random.default_rng(0).uniform(-1, 1, n)
            w, v = sla.eigsh(L.tocsc(), k=m, sigma=-1e-3, which="LM", v0=v0)
        except (sla.ArpackNoConvergence, RuntimeError):
            w = None  # shift-invert failed (e.g. a singular factorisation): use the dense solver below
        if w is not None:
            order = np.argsort(w)
            return w[order], v[:, order]
    elif method not in ("eigsh", "eigh"):
        raise ValueError(f"unknown eigen method {method!r}; valid: eigsh, eigh")
    import scipy.linalg

    dense = L.toarray() if sp.issparse(L) else np.asarray(L)
    return scipy.linalg.eigh(dense, subset_by_index=[0, min(m, n) - 1])


def smallest_eigenpairs_batch(L: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """The m smallest eigenpairs of each symmetric matrix of L (B,n,n): values (B,m), vectors (B,n,m), by
    LAPACK's subset driver (evx): finding m << n pairs is ~4x cheaper than the whole spectrum.  One matrix
    after another: scipy's call holds the GIL, so threads gain nothing (measured on the H100's host)."""
    import scipy.linalg

    m = min(m, L.shape[-1])
    pairs = [scipy.linalg.eigh(A, subset_by_index=[0, m - 1], driver="evx", check_finite=False) for A in L]
    return np.stack([w for w, _ in pairs]), np.stack([v for _, v in pairs])


def hks_signature(evals: np.ndarray, evecs: np.ndarray, cfg: RewardConfig) -> np.ndarray:
    """Quantiles of the normalised heat kernel signature at times t = c / lambda_K.

    h_t(x) = sum_k exp(-lambda_k t) phi_k(x)^2 over the K kept non-constant modes,
    divided by its mean over x (= sum_k exp(-lambda_k t) / n), so values are O(1) for any n.
    phi_k^2 is blind to the sign of phi_k and the HKS to the basis chosen inside a
    (fully kept) eigenspace; quantiles forget the point order.  Times scaled by the
    largest kept eigenvalue damp the last modes by exp(-c): an eigenspace split by the
    truncation at K has little weight, which keeps the signature stable under resampling;
    scaling also makes it size-free (absolute size is carried by the eigenvalue term).
    evals (..., K), evecs (..., n, K) -> (..., len(hks_times) * num_quantiles).
    """
    lamK = np.maximum(evals[..., -1:], cfg.eig_floor)  # ...,1
    q = (np.arange(cfg.num_quantiles) + 0.5) / cfg.num_quantiles
    sigs = []
    for c in cfg.hks_times:
        h = (np.exp(-evals * (c / lamK))[..., None, :] * evecs ** 2).sum(-1)  # ...,n
        h = h / h.mean(-1, keepdims=True)
        sigs.append(np.moveaxis(np.quantile(h, q, axis=-1), 0, -1))  # ...,Q
    return np.concatenate(sigs, -1)


def descriptor(points, sigma: float | None = None, cfg: RewardConfig | None = None, method: str = "eigsh"):
    """(eigvals (K,), signature (S,)) of one cloud (N,3) with graph width sigma (None: its own; scipy path)."""
    cfg = _cfg(cfg)
    p = resample(points, cfg)
    if len(p) < cfg.min_points:
        raise ValueError(f"a fragment needs at least reward.min_points={cfg.min_points} points, got {len(p)}")
    sigma = own_sigma(p, cfg) if sigma is None else float(sigma)
    w, v = smallest_eigenpairs(laplacian(p, sigma, cfg.knn), cfg.num_eig + 1, method)
    w, v = np.maximum(w[1:], 0.0), v[:, 1:]  # drop the constant mode (lambda_0 = 0)
    return w, hks_signature(w, v, cfg)


def descriptor_distance(eig_x, sig_x, eig_y, sig_y, cfg: RewardConfig | None = None):
    """d_spec from two descriptors; broadcasts over leading axes."""
    cfg = cfg or RewardConfig()
    f = cfg.eig_floor
    lx, ly = np.log(eig_x + f), np.log(eig_y + f)
    lx, ly = lx - lx.mean(-1, keepdims=True), ly - ly.mean(-1, keepdims=True)  # ratios: no common scale
    d_eig = ((lx - ly) ** 2).mean(-1)
    d_vec = ((sig_x - sig_y) ** 2).mean(-1)
    return cfg.alpha * d_eig + cfg.beta * d_vec


def spectral_distance(x, y, cfg: RewardConfig | None = None, sigma: float | None = None) -> float:
    """d_spec(x, y) for clouds (n,3), (m,3): the scale-free shape distance (each graph its own sigma unless
    ``sigma`` or reward.sigma fixes one).  Symmetric.  Returns inf when either cloud has fewer than
    cfg.min_points points.  The reward's distance adds the size terms: topocut.reward.piece_distance.
    """
    cfg = _cfg(cfg)
    x, y = resample(_points(x, "x"), cfg), resample(_points(y, "y"), cfg)  # once; resample is then a no-op
    if min(len(x), len(y)) < cfg.min_points:
        return float("inf")
    return float(descriptor_distance(*descriptor(x, sigma, cfg), *descriptor(y, sigma, cfg), cfg))


def spectral_descriptors(batch, cfg: RewardConfig | None = None, sigma=None):
    """Batched torch path: batch (B,n,3) -> (eigvals (B,K), signature (B,S)) torch tensors.

    The clouds are used as given (resample beforehand, e.g. with fps_torch).  sigma: float,
    (B,) tensor, or None for each cloud's own mean kNN distance x sigma_scale.  Dense
    (B,n,n) Laplacians in float64 on the batch's device; their eigenpairs per ``reward.eig_solver`` (host LAPACK
    subset solver, returning CPU tensors; batched subspace iteration or torch.linalg.eigh on the device).
    """
    return spectral_descriptors_groups([batch], cfg, sigma)[0]


def spectral_descriptors_groups(batches, cfg: RewardConfig | None = None, sigma=None):
    """``spectral_descriptors`` of several batches [(B_i,n_i,3)] (clouds of different sizes): [(eigvals, signature)].

    With the subspace solver every batch's Laplacian goes into one eigen call: each (n_i,n_i) Laplacian is padded to
    the largest n with isolated nodes of degree c above every eigenvalue (c = 2 x the largest degree + 1 > lambda_max
    by Gershgorin), so its K + 1 smallest pairs are the unpadded matrix's, with vectors zero on the padding.  One call
    instead of one per size: the solver's cost is its launches, not its matrices (docs/reward.md).
    """
    import torch

    from topocut.reward.eigen import smallest_eigenpairs_subspace

    cfg = _cfg(cfg)
    Ls = [_laplacians(b, cfg, sigma) for b in batches]  # [(B_i,n_i,n_i)]
    if not Ls:
        return []
    dev = Ls[0].device
    host = cfg.eig_solver == "host" or (cfg.eig_solver == "auto" and dev.type == "cpu")
    out = []
    if host:  # the K + 1 smallest pairs by LAPACK's subset solver (RewardConfig.eig_solver)
        for L in Ls:
            w, v = smallest_eigenpairs_batch(L.cpu().numpy(), cfg.num_eig + 1)  # B,K+1 / B,n,K+1
            w, v = np.maximum(w[:, 1:], 0.0), v[:, :, 1:]
            out.append((torch.as_tensor(w), torch.as_tensor(hks_signature(w, v, cfg))))
        return out
    if cfg.eig_solver == "device":  # the whole spectrum of each matrix (the reference)
        pairs = [torch.linalg.eigh(L) for L in Ls]  # ascending
    else:  # subspace, or auto on CUDA: only the K + 1 smallest pairs, every matrix at once (topocut.reward.eigen)
        n = max(L.shape[-1] for L in Ls)
        c = 2.0 * max(float(L.diagonal(dim1=1, dim2=2).max()) for L in Ls) + 1.0
        padded = torch.cat([_pad_laplacian(L, n, c) for L in Ls])  # sum B_i,n,n
        w, v = smallest_eigenpairs_subspace(padded, cfg.num_eig + 1)
        sizes = [len(L) for L in Ls]
        pairs = [(wi, vi[:, :L.shape[-1]]) for wi, vi, L in zip(w.split(sizes), v.split(sizes), Ls)]
    for w, v in pairs:
        w, v = w[:, 1:cfg.num_eig + 1].clamp_min(0.0), v[:, :, 1:cfg.num_eig + 1]
        out.append((w, _signature(w, v, cfg)))
    return out


def _laplacians(batch, cfg: RewardConfig, sigma):
    """Dense float64 Laplacians (B,n,n) of the symmetrised Gaussian kNN graphs of batch (B,n,3)."""
    import torch

    x = torch.as_tensor(batch).to(torch.float64)  # B,n,3
    if x.dim() != 3 or x.shape[-1] != 3:
        raise ValueError(f"spectral_descriptors expects (B,n,3), got {tuple(x.shape)}")
    B, n, _ = x.shape
    k = min(cfg.knn, n - 1)
    d = torch.cdist(x, x)  # B,n,n
    dk, jk = d.topk(k + 1, dim=-1, largest=False)  # B,n,k+1 (self first)
    dk, jk = dk[..., 1:], jk[..., 1:]
    if sigma is None:
        s = cfg.sigma if cfg.sigma is not None else cfg.sigma_scale * dk.mean((1, 2))
    else:
        s = sigma
    s = torch.as_tensor(s, dtype=torch.float64, device=x.device).reshape(-1, 1, 1).expand(B, 1, 1)
    W = torch.zeros_like(d).scatter_(-1, jk, torch.exp(-(dk / s) ** 2))
    W = torch.maximum(W, W.transpose(1, 2))
    return torch.diag_embed(W.sum(-1)) - W


def _pad_laplacian(L, n: int, c: float):
    """L (B,m,m) as (B,n,n): the extra n - m nodes isolated with diagonal c (eigenvalue c, vectors on them only)."""
    import torch

    B, m, _ = L.shape
    if m == n:
        return L
    P = torch.diag_embed(L.new_full((B, n), c))
    P[:, :m, :m] = L
    return P


def _signature(w, v, cfg: RewardConfig):
    """hks_signature in torch: w (B,K), v (B,n,K) -> (B, len(hks_times) * num_quantiles)."""
    import torch

    lamK = w[:, -1:].clamp_min(cfg.eig_floor)  # B,1
    q = (torch.arange(cfg.num_quantiles, dtype=torch.float64, device=w.device) + 0.5) / cfg.num_quantiles
    sigs = []
    for c in cfg.hks_times:
        h = (torch.exp(-w * (c / lamK))[:, None, :] * v ** 2).sum(-1)  # B,n
        sigs.append(torch.quantile(h / h.mean(-1, keepdim=True), q, dim=-1).T)  # B,Q
    return torch.cat(sigs, -1)

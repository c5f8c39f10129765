"""Every fragment's size descriptor at once, on the reward's device (``reward.size_solver``; issue #49 item 3).

``topocut.reward.distance._fragment_size`` measures one fragment on the host: its particle spacing (a KD-tree of its
particles, 4 nearest neighbours of up to 8,192 of them), its extents (3 x 3 covariance), then, where its extents and
fill leave R > 0 against some goal piece, its body (``topocut.reward.strays``: neighbours within 1.6 spacings) and its
thickness profile.  An MPPI cut has ~50-100 fragments (16 rollout scenes x their pieces): one at a time in host threads
that was ~0.3 s a cut at 64^3, the largest part of the reward there, and one thread a process under ``make paper``'s
16 processes (OMP_NUM_THREADS=1).

Here the same quantities are found for every fragment in a few batched passes, the fragments' particles shipped to
the device once (flat, with their fragment's index):

  spacing      4 nearest neighbours of each query particle (the host's fixed-seed sample of a large piece) among its
               fragment's particles, by cell lists (``near``: cells of twice the mean particle distance, the 27 around
               a query); a query whose 4th neighbour lies past its cell side, against every particle of its fragment
  extents      per-fragment mean and covariance (index_add), batched 3 x 3 eigh
  (host)       the extents-and-fill bound against each fragment's goal pieces: which fragments go on
  body         neighbour counts within LINK spacings (cells of that side: the core), then whether each non-core
               particle has a core particle within it
  profile      columns of 2 s on the two wider principal axes (one unique over (fragment, column) keys), their
               second moments by index_add, the thickness quantiles by one sort of (fragment, value)

A few host syncs a call, none per fragment.  The numbers are the host's up to rounding (sums run in another order;
tests/test_reward_size_batch.py compares every field and the kept particles); fragments of fewer than ``HOST_BELOW``
particles, or with no spacing (coincident particles), take the host path.  On one H200 the reward of a 64^3
demonstration cut went from 0.59 to 0.38 s, at 128^3 from 0.87 to 0.61 s (docs/benchmarks.md).
"""
from __future__ import annotations

import numpy as np

from topocut.reward.size import NN_K, NN_RATIO, PROFILE_QUANTILES, SPACING_QUERIES
from topocut.reward.strays import CORE_NEIGHBOURS, LINK

HOST_BELOW = 2 * CORE_NEIGHBOURS + 4  # fewer particles: the host path (its small-piece rules; rare, tiny)
CELL_BUDGET = 1 << 23  # distances held at once (by ``near`` with their candidates' coordinates: ~300 MiB)


def _brute_nearest(X, q, ref, k: int, budget: int = CELL_BUDGET):
    """The k smallest distances (Q, k) from each of the rows q of X to the rows ref of X, ascending: every pair, in
    chunks of at most ``budget`` distances (the fallback of ``_spacings`` for the few queries cell lists cannot
    settle)."""
    import torch

    rows = max(1, budget // max(len(ref), 1))
    R = X[ref][None]  # 1,n,3
    # exact differences, not |x|^2 - 2 x.y + |y|^2 (its cancellation moves neighbour distances of 1e-3 by 1e-9)
    return torch.cat([torch.cdist(X[q[a:a + rows]][None], R, compute_mode="donot_use_mm_for_euclid_dist")[0]
                      .topk(k, dim=-1, largest=False).values for a in range(0, len(q), rows)])


def near(X, q, qseg, ref, rseg, h, F: int, mode: str, k: int = 1, radius=None, budget: int = CELL_BUDGET,
         method: str = "kernel"):
    """Each query's reduction over the references of its own fragment within the 27 cells of side h[fragment] around
    it: mode "knn" the k smallest distances ascending (Q, k), "count" how many lie within radius[fragment] less one
    (Q, 1; the query is among its references), "min" the smallest distance (Q, 1).  Other references count as inf.

    Cell lists on the device: the references sorted by (fragment, cell), each query's 27 neighbour cells read at once.
    A reference within h of a query is always among its candidates, so a count within a radius <= h, or a nearest
    distance <= h, is exact.  q, ref: rows of X (long, on X's device); qseg, rseg: their fragments; h (F,): each
    fragment's cell side.  method "kernel": one Warp thread a query walks its cells (topocut.reward.near_kernel);
    "tensor": the candidates gathered into blocks padded to the fullest cell (27 x its count) and reduced by tensor
    operations, in chunks of ``budget`` distances: the same numbers to rounding, the reference."""
    import torch

    if method not in ("kernel", "tensor"):
        raise ValueError(f"near: method={method!r}; valid: kernel, tensor")
    if mode not in ("knn", "count", "min"):
        raise ValueError(f"near: mode={mode!r}; valid: knn, count, min")
    width = k if mode == "knn" else 1
    dev, Q = X.device, len(q)
    if Q == 0 or len(ref) == 0:
        return torch.full((Q, width), -1.0 if mode == "count" else float("inf"), dtype=X.dtype, device=dev)
    big = torch.iinfo(torch.int64).max
    cr = torch.floor(X[ref] / h[rseg, None]).long()  # n,3
    idx3 = rseg[:, None].expand(-1, 3)
    lo = torch.full((F, 3), big, device=dev).scatter_reduce(0, idx3, cr, "amin")
    hi = torch.full((F, 3), -big, device=dev).scatter_reduce(0, idx3, cr, "amax")
    has = (torch.bincount(rseg, minlength=F) > 0)[:, None]
    lo, hi = torch.where(has, lo, 0), torch.where(has, hi, -1)
    dims = hi - lo + 5  # F,3: two empty cells of padding on each side
    size = dims.prod(1)
    base = torch.cumsum(size, 0) - size
    stride = torch.stack([dims[:, 1] * dims[:, 2], dims[:, 2], torch.ones_like(dims[:, 2])], 1)  # F,3
    key = base[rseg] + ((cr - lo[rseg] + 2) * stride[rseg]).sum(1)
    key, order = torch.sort(key)
    ref = ref[order]
    count = torch.bincount(key, minlength=int(size.sum()))  # cells,
    start = torch.cumsum(count, 0) - count
    cq = torch.floor(X[q] / h[qseg, None]).long() - lo[qseg] + 2  # Q,3
    inside = ((cq >= 1) & (cq <= dims[qseg] - 2)).all(1)  # else more than a cell from every reference
    cq = torch.where(inside[:, None], cq, 2)
    if method == "kernel" and X.dtype == torch.float64:
        from topocut.reward.near_kernel import walk_cells

        return walk_cells(mode, k, X, q, qseg, cq, inside, base, stride, start, count, ref, radius)
    if mode == "knn":
        def reduce(d, _):
            return d.topk(k, dim=-1, largest=False).values
    elif mode == "count":
        def reduce(d, t):
            return (d <= radius[t][:, None]).sum(-1, keepdim=True).to(d.dtype) - 1
    else:
        def reduce(d, _):
            return d.amin(-1, keepdim=True)
    off = torch.stack(torch.meshgrid(*[torch.arange(-1, 2, device=dev)] * 3, indexing="ij"), -1).reshape(27, 3)
    nb = (base[qseg] + (cq * stride[qseg]).sum(1))[:, None] + (off[None] * stride[qseg][:, None, :]).sum(-1)  # Q,27
    ncount = count[nb] * inside[:, None]  # Q,27
    C = max(1, int(ncount.max()))
    ar = torch.arange(C, device=dev)
    rows = max(1, budget // (27 * C))
    out = X.new_empty(Q, width)
    for a in range(0, Q, rows):
        sl = slice(a, a + rows)
        valid = ar < ncount[sl][..., None]  # r,27,C
        cand = ref[(start[nb[sl]][..., None] + ar).clamp(max=len(ref) - 1)]  # r,27,C
        d = torch.sqrt(((X[cand] - X[q[sl]][:, None, None, :]) ** 2).sum(-1))
        out[sl] = reduce(torch.where(valid, d, float("inf")).reshape(len(cand), 27 * C), qseg[sl])
    return out


def _segment_sorted(values, seg, F: int):
    """values (M,) sorted within each segment (seg (M,) the fragment of each), and each segment's start and count."""
    import torch

    v, order = torch.sort(values)
    s, order2 = torch.sort(seg[order], stable=True)
    count = torch.bincount(seg, minlength=F)
    start = torch.cumsum(count, 0) - count
    return v[order2], start, count


def _quantiles(values, seg, F: int, levels):
    """numpy.quantile(..., method='linear') of each segment at ``levels`` (L,): (F, L); numpy's own index and lerp."""
    import torch

    v, start, count = _segment_sorted(values, seg, F)
    q = torch.as_tensor(levels, dtype=values.dtype, device=values.device)[None]  # 1,L
    virtual = (count.to(values.dtype)[:, None] - 1) * q  # F,L: numpy's virtual index for 'linear'
    last = (count - 1)[:, None]  # F,1
    lo = torch.floor(virtual)
    gamma = virtual - lo
    lo = torch.where(virtual >= last, last, lo.long())  # numpy: at or past the last index, the last value
    hi = torch.minimum(lo + 1, last)
    a, b = v[start[:, None] + lo], v[start[:, None] + hi]
    d = b - a
    return torch.where(gamma >= 0.5, b - d * (1 - gamma), a + d * gamma)  # numpy's _lerp


def _medians(values, seg, F: int):
    """numpy.median of each segment of values (M,): the mean of the two middle values of an even count."""
    v, start, count = _segment_sorted(values, seg, F)
    return (v[start + (count - 1) // 2] + v[start + count // 2]) / 2.0


def _moments(X, seg, F: int):
    """Per-segment (count (F,), mean (F,3), biased covariance (F,3,3)) of X (M,3) (numpy.cov(bias=True): centred)."""
    import torch

    n = torch.bincount(seg, minlength=F).to(X.dtype)
    mean = X.new_zeros(F, 3).index_add_(0, seg, X) / n[:, None]
    c = X - mean[seg]
    cov = X.new_zeros(F, 3, 3).index_add_(0, seg, c[:, :, None] * c[:, None, :]) / n[:, None, None]
    return n, mean, cov


def _descriptors(X, seg, F: int, s, profile: bool):
    """size_descriptor of each segment: (F, 5 + PROFILE_QUANTILES) on the device; s (F,) the spacings."""
    import torch

    n, mean, cov = _moments(X, seg, F)
    c, vec = torch.linalg.eigh(cov)  # F,3 ascending / F,3,3: vec[..., 0] the thinnest axis
    e = torch.sqrt(torch.clamp(12.0 * c, min=0.0) + s[:, None] ** 2)
    out = [e, (n * s ** 3)[:, None]]
    if profile:
        local = torch.einsum("mi,mij->mj", X - mean[seg], vec[seg])  # M,3
        cell = (2.0 * s)[seg, None]
        ij = torch.floor(local[:, 1:] / cell).long()  # M,2
        ij = ij - torch.full((F, 2), torch.iinfo(torch.int64).max, device=X.device).scatter_reduce(
            0, seg[:, None].expand(-1, 2), ij, "amin")[seg]
        width = torch.zeros(F, dtype=torch.long, device=X.device).scatter_reduce(0, seg, ij[:, 1], "amax") + 1
        col = ij[:, 0] * width[seg] + ij[:, 1]
        M = int(col.max()) + 1
        key, inv, cnt = torch.unique(seg * M + col, return_inverse=True, return_counts=True)  # (fragment, column)
        cnt = cnt.to(X.dtype)
        m1 = X.new_zeros(len(cnt)).index_add_(0, inv, local[:, 0]) / cnt
        m2 = X.new_zeros(len(cnt)).index_add_(0, inv, local[:, 0] ** 2) / cnt
        thick = torch.sqrt(torch.clamp(12.0 * (m2 - m1 ** 2), min=0.0) + s[key // M] ** 2)[inv]  # each its column's
        keep = cnt[inv] >= 3  # a column of one or two particles says nothing ...
        none = torch.bincount(seg, weights=keep.to(X.dtype), minlength=F) == 0
        keep = keep | none[seg]  # ... unless no column has three: then every particle (as the host)
        levels = 0.1 + 0.8 * (np.arange(PROFILE_QUANTILES) + 0.5) / PROFILE_QUANTILES
        out.append(_quantiles(thick[keep], seg[keep], F, levels))
    else:
        out.append(X.new_full((F, PROFILE_QUANTILES), float("nan")))
    out.append(s[:, None])
    return torch.cat(out, 1)


def fragment_sizes(items, cfg, spacing: float | None = None, budget: int = CELL_BUDGET, near_method: str = "kernel") -> list:
    """(size descriptor, the points described) of each (fragment (N,3), its set's goal sizes (G, 5+Q)) in ``items``:
    ``topocut.reward.distance._fragment_size`` of every fragment, batched on ``cfg.device``.  near_method: ``near``'s
    (the tensor path, with ``budget`` distances a block, is the reference)."""
    import torch

    from topocut.reward.distance import _fragment_size, past_zero_by_size

    out: list = [None] * len(items)
    dev = torch.device(cfg.device)
    big = [i for i, (p, _) in enumerate(items) if len(p) >= HOST_BELOW]
    if big:
        pts = [np.asarray(items[i][0], np.float64) for i in big]
        F = len(big)
        count = np.array([len(p) for p in pts], np.int64)
        start = np.concatenate([[0], np.cumsum(count)[:-1]])
        X = torch.from_numpy(np.concatenate(pts)).to(dev)  # P,3
        seg_np = np.repeat(np.arange(F), count)
        seg = torch.from_numpy(seg_np).to(dev)  # P,
        if spacing is None:
            s = _spacings(X, seg, start, count, budget, near_method)
        else:
            s = X.new_full((F,), float(spacing))
        base = _descriptors(X, seg, F, s, profile=False).cpu().numpy()  # host sync 1
        # the host's rules for a piece with no spacing (coincident particles): its own path
        host = {f for f in range(F) if not base[f, -1] > 0}
        on = []  # fragments whose extents and fill leave R > 0 for some goal piece: their body and profile
        for f, i in enumerate(big):
            if f in host:
                continue
            if past_zero_by_size(base[f], items[i][1], cfg):
                out[i] = (base[f], pts[f])
                continue
            on.append(f)
        if on:
            keep = _bodies(X, start, count, s, on, cfg.stray_share, budget, near_method)  # host masks, one per fragment in on
            kept = [start[f] + np.flatnonzero(k) for f, k in zip(on, keep)]
            rows = torch.from_numpy(np.concatenate(kept)).to(dev)
            kseg = torch.from_numpy(np.repeat(np.arange(len(on)), [len(k) for k in kept])).to(dev)
            desc = _descriptors(X[rows], kseg, len(on), s[torch.as_tensor(on, device=dev)], profile=True)
            desc = desc.cpu().numpy()  # host sync 4
            for j, (f, k) in enumerate(zip(on, keep)):
                out[big[f]] = (desc[j], pts[f] if k.all() else pts[f][k])
        for f in host:
            out[big[f]] = _fragment_size(pts[f], items[big[f]][1], cfg, spacing)
    for i, (p, goals) in enumerate(items):
        if out[i] is None:
            out[i] = _fragment_size(np.asarray(p, np.float64), goals, cfg, spacing)
    return out


def _spacings(X, seg, start, count, budget: int, method: str = "kernel"):
    """topocut.reward.size.particle_spacing of each fragment (F,): the median distance of its query particles (all, or
    the host's fixed-seed sample of SPACING_QUERIES) to their NN_K nearest neighbours, / NN_RATIO.  Neighbours by cell
    lists of side twice the fragment's mean particle distance (from its principal extents); a query whose NN_K-th
    neighbour lies past that side (a sparse corner, strays) is measured against every particle of its fragment."""
    import torch

    dev, F = X.device, len(count)
    rows = [start[f] + (np.arange(count[f]) if count[f] <= SPACING_QUERIES else
                        np.sort(np.random.default_rng(0).choice(count[f], SPACING_QUERIES, replace=False)))
            for f in range(F)]
    q = torch.from_numpy(np.concatenate(rows)).to(dev)
    qseg = torch.from_numpy(np.repeat(np.arange(F), [len(r) for r in rows])).to(dev)
    n, _, cov = _moments(X, seg, F)
    box = torch.sqrt(12.0 * torch.linalg.eigvalsh(cov).clamp_min(0.0)).prod(1)  # F: the principal box's volume
    idx3 = seg[:, None].expand(-1, 3)
    extent = (X.new_full((F, 3), -np.inf).scatter_reduce(0, idx3, X, "amax")
              - X.new_full((F, 3), np.inf).scatter_reduce(0, idx3, X, "amin")).amax(1)  # F: the widest side
    h = torch.maximum(2.0 * (box / n) ** (1.0 / 3.0), extent / 64.0 + 1e-12)  # at most 64 cells a side (memory)
    every = torch.arange(len(X), device=dev)
    nn = near(X, q, qseg, every, seg, h, F, "knn", NN_K + 1, budget=budget, method=method)  # Q,K+1: itself first, as query(k + 1)
    unsure = nn[:, -1] > h[qseg]  # Q,
    for f in torch.unique(qseg[unsure]).tolist():  # against every particle of the fragment (rare: strays, sheets)
        u = (unsure & (qseg == f)).nonzero().reshape(-1)
        nn[u] = _brute_nearest(X, q[u], every[start[f]:start[f] + count[f]], NN_K + 1, budget)
    return _medians(nn[:, 1:].reshape(-1), qseg.repeat_interleave(NN_K), F) / NN_RATIO


def _bodies(X, start, count, s, on: list, max_share: float, budget: int, method: str = "kernel") -> list:
    """topocut.reward.strays.body's kept mask (N_f,) of each fragment f in ``on``; s (F,) their spacings."""
    import torch

    if not max_share > 0:
        return [np.ones(count[f], bool) for f in on]
    dev = X.device
    r = LINK * s[torch.as_tensor(on, device=dev)]  # J,: the link radius of each fragment in on
    rows = torch.from_numpy(np.concatenate([start[f] + np.arange(count[f]) for f in on])).to(dev)
    jseg = torch.from_numpy(np.repeat(np.arange(len(on)), [count[f] for f in on])).to(dev)
    near_n = near(X, rows, jseg, rows, jseg, r, len(on), "count", radius=r, budget=budget, method=method)
    core = near_n.reshape(-1) >= CORE_NEIGHBOURS  # itself not counted
    # the non-core particles within one link of the core
    dmin = near(X, rows[~core], jseg[~core], rows[core], jseg[core], r, len(on), "min", budget=budget,
                method=method).reshape(-1)
    keep = core.clone()
    keep[~core] = dmin <= r[jseg[~core]]
    keep, core = keep.cpu().numpy(), core.cpu().numpy()  # host sync 2
    offset = np.concatenate([[0], np.cumsum([count[f] for f in on])])
    out = []
    for j, f in enumerate(on):
        c, k = core[offset[j]:offset[j + 1]], keep[offset[j]:offset[j + 1]]
        # all of it where the core is everything or nothing, or more would be left out than max_share
        out.append(k if c.any() and not c.all() and (~k).sum() <= max_share * count[f] else np.ones(count[f], bool))
    return out

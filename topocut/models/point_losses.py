"""Point-set losses batched on the tensor's device: Chamfer, Hausdorff and an ε-accurate EMD (auction).

Same definitions as ``topocut.metrics`` (unsquared Euclidean distances, docs/reward.md):

    nn(a -> b) = mean_i min_j |a_i - b_j|,   chamfer = (nn(a -> b) + nn(b -> a)) / 2
    hausdorff  = max(max_i min_j |a_i - b_j|, max_j min_i |b_j - a_i|)
    emd        = min over bijections s of mean_i |a_i - b_s(i)|

Inputs are (B,N,3) and (B,M,3) tensors with an optional ``valid`` (B,N) bool mask of the rows that count (the
same mask for both sets: TransitionDataset pads pred and target with the same indices).  Everything, the EMD
assignment included, runs on the inputs' device with no host round trip but the auction's termination test.

EMD by the auction algorithm (Bertsekas 1988; Jacobi form: every unassigned row bids at once, each column
goes to its highest bidder) with ε-scaling.  On termination the assignment satisfies ε-complementary
slackness, hence its summed cost is within N·ε of the optimum: the returned mean matched distance d obeys

    emd <= d <= emd + ε,   ε = max(tol · max(nn(a -> b), nn(b -> a)), floor)

and since nn(a -> b) <= emd (every matched distance is at least the nearest one), d <= (1 + tol) · emd unless
the floor (``EPS_FLOOR`` times the largest distance, against float rounding of the prices) is larger.  d is the
cost of a true bijection, so it is never below the exact value.  As in the exact path, the assignment is found
without gradient and the mean matched distance is differentiated (exact almost everywhere).  The auction's
starting prices come from log-domain Sinkhorn potentials (``warm_iters``), which cuts its rounds ~10x without
touching the bound; on CUDA the Sinkhorn steps and the rounds are replayed as CUDA graphs (``USE_CUDA_GRAPHS``).
Speed and measured error: docs/perception.md "Losses on the device", benchmarks/losses.py.
"""
from __future__ import annotations

import math

import torch

EPS_FLOOR = {torch.float64: 1e-9, torch.float32: 1e-5}  # smallest ε, as a fraction of the item's largest distance
EMD_METHODS = ("auto", "exact", "auction")


def _check(a: torch.Tensor, b: torch.Tensor, valid: torch.Tensor | None, equal: bool = False):
    if a.dim() != 3 or b.dim() != 3 or a.shape[0] != b.shape[0]:
        raise ValueError(f"inputs must be (B,N,D) and (B,M,D) with equal B, got {tuple(a.shape)}, {tuple(b.shape)}")
    if (equal or valid is not None) and a.shape[1] != b.shape[1]:
        raise ValueError(f"point sets must have equal sizes here, got {a.shape[1]} and {b.shape[1]}")
    if valid is not None and tuple(valid.shape) != tuple(a.shape[:2]):
        raise ValueError(f"valid must be (B,N)={tuple(a.shape[:2])}, got {tuple(valid.shape)}")


def _nn(a: torch.Tensor, b: torch.Tensor, valid: torch.Tensor | None):
    """Distances (B,N,M) and nearest distances a -> b (B,N), b -> a (B,M); +inf on invalid rows/columns."""
    d = torch.cdist(a, b)
    if valid is None:
        return d, d.min(2).values, d.min(1).values
    v = valid.bool()
    inf = float("inf")  # a Python scalar: torch.tensor(inf, device=cuda) would be a blocking host -> device copy
    ab = d.masked_fill(~v[:, None, :], inf).min(2).values
    ba = d.masked_fill(~v[:, :, None], inf).min(1).values
    return d, ab.masked_fill(~v, inf), ba.masked_fill(~v, inf)


def _mean(x: torch.Tensor, valid: torch.Tensor | None) -> torch.Tensor:
    if valid is None:
        return x.mean(1)
    v = valid.bool()
    return torch.where(v, x, torch.zeros_like(x)).sum(1) / v.sum(1).clamp(min=1)


def chamfer(a: torch.Tensor, b: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
    """Symmetric mean nearest-neighbour distance (B,) over the ``valid`` rows of both sets."""
    _check(a, b, valid)
    _, ab, ba = _nn(a, b, valid)
    return 0.5 * (_mean(ab, valid) + _mean(ba, valid))


def hausdorff(a: torch.Tensor, b: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
    """Symmetric Hausdorff distance (B,) over the ``valid`` rows of both sets."""
    _check(a, b, valid)
    _, ab, ba = _nn(a, b, valid)
    if valid is not None:
        v = valid.bool()
        ab, ba = torch.where(v, ab, torch.zeros_like(ab)), torch.where(v, ba, torch.zeros_like(ba))
    return torch.maximum(ab.amax(1), ba.amax(1))


USE_CUDA_GRAPHS = True  # replay the auction's rounds and the Sinkhorn steps as CUDA graphs (launch-bound otherwise)
_GRAPHS: dict = {}


def _graphed(key, state: dict, step, n: int):
    """(graph, static): ``step(static)`` (in place on the tensors of ``static``) n times as one CUDA graph,
    captured once per ``key``; ``static`` holds copies of ``state``'s tensors: copy inputs in, replay, read."""
    entry = _GRAPHS.get(key)
    if entry is None:
        static = {k: t.clone() for k, t in state.items()}
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            step(static)  # warm-up outside the capture (allocator, kernels)
        torch.cuda.current_stream().wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            for _ in range(n):
                step(static)
        entry = _GRAPHS[key] = (graph, static)
    graph, static = entry
    for k, t in state.items():
        static[k].copy_(t)
    return graph, static


def _auction_round(s: dict):
    """One Jacobi round on state s (benefit, price, assign, valid, e, rows), in place."""
    benefit, price, assign, v, e, rows = s["benefit"], s["price"], s["assign"], s["valid"], s["e"], s["rows"]
    bidders = (assign < 0) & v
    val = benefit - price[:, None, :]
    k2 = min(2, val.shape[2])
    top, j = val.topk(k2, dim=2)
    j1 = j[..., 0]
    gap = top[..., 0] - top[..., 1] if k2 == 2 else torch.zeros_like(top[..., 0])
    gap = torch.where(torch.isfinite(gap), gap, torch.zeros_like(gap))  # a single valid column
    bid = torch.where(bidders, price.gather(1, j1) + gap + e, -math.inf)
    best = torch.full_like(price, -math.inf).scatter_reduce(1, j1, bid, "amax")
    got = best > -math.inf  # columns that received a bid
    cand = bidders & (bid == best.gather(1, j1))
    winner = torch.full_like(assign, -1).scatter_reduce(1, j1, torch.where(cand, rows, -1), "amax")
    lost = (assign >= 0) & got.gather(1, assign.clamp(min=0))
    won = cand & (winner.gather(1, j1) == rows)
    assign.copy_(torch.where(won, j1, torch.where(lost, -1, assign)))
    price.copy_(torch.where(got, best, price))


def auction_phases(ratio: float, factor: float = 8.0) -> int:
    """ε-scaling phases from eps0 down to eps = eps0 / ratio, dividing by ``factor`` per phase."""
    return 1 + max(0, math.ceil(math.log(max(ratio, 1.0)) / math.log(factor)))


WARM_EPS0 = 3.0  # after the Sinkhorn warm start the auction's ε-scaling starts at this multiple of the final ε


@torch.no_grad()
def auction_assignment(cost: torch.Tensor, eps: torch.Tensor, valid: torch.Tensor | None = None,
                       phases: int | None = None, factor: float = 8.0, check_every: int = 4,
                       max_rounds: int = 100_000, price0: torch.Tensor | None = None,
                       eps0: torch.Tensor | None = None, budget: int | None = None) -> torch.Tensor:
    """Column (B,N) assigned to each row of the (B,N,N) ``cost``, minimising the summed cost within N·eps.

    eps (B,) is the final ε of each item; ε-scaling starts at ``eps0`` (default a quarter of the item's largest
    cost) and divides by ``factor`` per phase (prices carried over, assignment restarted; each item moves on when
    it alone is complete).  Rows/columns outside ``valid`` take no part and get -1.  Jacobi auction: each round, every unassigned row bids for its best column
    (value = -cost - price) raising the price by (best - second best) + ε; each column goes to its highest bid.
    Termination is tested every ``check_every`` rounds (a round with every row assigned changes nothing).
    ``budget``: stop after that many rounds instead; an item not fully assigned in the final phase by then comes
    back all -1 (emd_auction solves those exactly).  Without it, ``max_rounds`` rounds raise RuntimeError.
    """
    B, N, _ = cost.shape
    dev, dt = cost.device, cost.dtype
    v = torch.ones(B, N, dtype=torch.bool, device=dev) if valid is None else valid.bool()
    benefit = torch.where(v[:, None, :], -cost, -math.inf)  # invalid columns are never bid for
    big = torch.where(v[:, :, None] & v[:, None, :], cost, torch.zeros_like(cost)).amax((1, 2))
    eps = eps.to(dt)
    eps0 = torch.maximum(big / 4 if eps0 is None else eps0.to(dt), eps)
    if phases is None:
        ratio = float((eps0 / eps).max())  # a host sync: callers that know the ratio pass ``phases``
        phases = auction_phases(ratio, factor)
    price = torch.zeros(B, N, dtype=dt, device=dev) if price0 is None else price0.to(dt).clone()
    state = {"benefit": benefit, "price": price, "assign": torch.full((B, N), -1, dtype=torch.long, device=dev),
             "valid": v, "e": eps[:, None].clone(), "rows": torch.arange(N, device=dev).expand(B, N).contiguous()}
    graph = None
    if USE_CUDA_GRAPHS and cost.is_cuda:
        graph, state = _graphed(("auction", B, N, dt, dev, check_every), state, _auction_round, check_every)
    # ε of each item's phases, B,phases; every item moves to its next phase (prices kept, assignment restarted) as
    # soon as it is complete, not when the whole batch is: an item's rounds are those it takes alone
    E = torch.stack([eps if phases == 1 else torch.maximum(eps0 * (eps / eps0) ** (k / (phases - 1)), eps)
                     for k in range(phases)], 1)
    phase = torch.zeros(B, dtype=torch.long, device=dev)
    state["e"].copy_(E[:, :1])
    state["assign"].fill_(-1)
    rounds = 0
    while True:
        complete = ~((state["assign"] < 0) & state["valid"]).any(1)
        step_up = complete & (phase < phases - 1)
        phase += step_up.long()
        state["assign"].masked_fill_(step_up[:, None], -1)
        state["e"].copy_(E.gather(1, phase[:, None]))
        done = complete & ~step_up  # complete in its final phase
        if bool(done.all()) or (budget is not None and rounds >= budget):
            break
        if rounds >= max_rounds:
            raise RuntimeError(f"auction did not terminate in {max_rounds} rounds")
        rounds += check_every
        if graph is not None:
            graph.replay()
        else:
            for _ in range(check_every):
                _auction_round(state)
    auction_assignment.last_rounds = rounds
    # the graph's static buffer is reused by the next call; an item out of budget comes back all -1
    cols = torch.where(done[:, None], state["assign"], torch.full_like(state["assign"], -1))
    return cols


def exact_rows(cost: torch.Tensor, cols: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
    """``cols`` with every item that has an unassigned valid row solved exactly by scipy on the host (those items
    only: one transfer of their (N,N) costs each way)."""
    from topocut.models.losses import _match  # scipy's assignment, row -> column

    v = torch.ones_like(cols, dtype=torch.bool) if valid is None else valid.bool()
    left = ((cols < 0) & v).any(1)
    items = left.nonzero().flatten().tolist()
    exact_rows.last_items = len(items)
    if not items:
        return cols
    c, m = cost[items].detach().cpu().double().numpy(), v[items].cpu().numpy()
    fill = torch.full((len(items), cols.shape[1]), -1, dtype=cols.dtype)
    for k in range(len(items)):
        idx = m[k].nonzero()[0]
        fill[k, torch.as_tensor(idx)] = torch.as_tensor(idx[_match(c[k][idx][:, idx])])
    out = cols.clone()
    out[items] = fill.to(cols.device)
    return out


def _sinkhorn_step(s: dict):
    """One Sinkhorn iteration in scaled potentials u = f/ε, v = g/ε, then ε <- max(scaling·ε, eps), in place."""
    c, logw, e, u, v = s["c"], s["logw"], s["e"], s["u"], s["v"]
    k = -c / e[..., None]
    u.copy_(-torch.logsumexp(k + (v + logw)[:, None, :], 2))
    v.copy_(-torch.logsumexp(k + (u + logw)[:, :, None], 1))
    e_new = torch.maximum(e * s["scaling"], s["eps"])
    u.mul_(e / e_new)
    v.mul_(e / e_new)
    e.copy_(e_new)


@torch.no_grad()
def sinkhorn_potentials(cost: torch.Tensor, eps: torch.Tensor, iters: int, valid: torch.Tensor | None = None,
                        scaling: float = 0.7) -> torch.Tensor:
    """Column potentials g (B,N) of log-domain Sinkhorn (uniform weights over the ``valid`` rows), ε annealed by
    ``scaling`` per iteration from the largest cost down to eps (B,); used as the auction's starting prices (-g)."""
    B, N, _ = cost.shape
    dt, dev = cost.dtype, cost.device
    m = torch.ones(B, N, dtype=torch.bool, device=dev) if valid is None else valid.bool()
    logw = torch.where(m, -torch.log(m.sum(1, keepdim=True).clamp(min=1).to(dt)), -math.inf)  # B,N
    c = torch.where(m[:, :, None] & m[:, None, :], cost, torch.zeros_like(cost))
    eps = eps.to(dt)[:, None]
    s = {"c": c, "logw": logw, "eps": eps, "e": torch.maximum(c.amax((1, 2))[:, None], eps),
         "u": torch.zeros(B, N, dtype=dt, device=dev), "v": torch.zeros(B, N, dtype=dt, device=dev),
         "scaling": torch.full_like(eps, scaling)}
    if USE_CUDA_GRAPHS and cost.is_cuda and iters > 0:
        graph, s = _graphed(("sinkhorn", B, N, dt, dev, iters), s, _sinkhorn_step, iters)
        graph.replay()
    else:
        for _ in range(iters):
            _sinkhorn_step(s)
    g = s["v"] * s["e"]
    return torch.where(torch.isfinite(g), g, torch.zeros_like(g))


def emd_auction(a: torch.Tensor, b: torch.Tensor, valid: torch.Tensor | None = None, tol: float = 0.01,
                return_assignment: bool = False, warm_iters: int = 30, rounds: int = 0):
    """Earth Mover's distance (B,) of equal-size sets by the auction: emd <= result <= (1 + tol)·emd (module doc).

    ``warm_iters`` Sinkhorn iterations (ε down to 30 tol-ε) give the auction near-optimal starting prices, which
    cuts its rounds several-fold; they change its speed, not its bound (0: plain ε-scaling from zero prices).
    30, not more: on an H100 at B=256, N=256 the auction took 8 rounds after 30, 60 or 150 iterations and 20
    from zero prices, for 26.8 / 43.9 / 96.2 / 21.5 ms (the same assignment every time).
    With ``return_assignment`` also the (B,N) column of b matched to each row of a (-1 outside ``valid``).
    ``rounds`` > 0: the auction's budget; the items it leaves unfinished are solved exactly on the host
    (``exact_rows``), so the bound holds for every item.  On real point clouds a few rows of an item can take
    hundreds of rounds (docs/perception.md, "The auction's rounds on real data").
    """
    _check(a, b, valid, equal=True)
    with torch.no_grad():
        d, ab, ba = _nn(a.detach(), b.detach(), valid)
        lb = torch.maximum(_mean(torch.where(torch.isfinite(ab), ab, 0), valid),
                           _mean(torch.where(torch.isfinite(ba), ba, 0), valid))  # <= emd
        dm = d if valid is None else torch.where(valid[:, :, None] & valid[:, None, :], d, torch.zeros_like(d))
        floor = EPS_FLOOR.get(d.dtype, 1e-5) * dm.amax((1, 2)).clamp(min=torch.finfo(d.dtype).tiny)
        eps = torch.maximum(tol * lb, floor)
        if warm_iters > 0:
            g = sinkhorn_potentials(d, 30 * eps, warm_iters, valid)
            # eps0 / eps is WARM_EPS0 for every item (eps > 0): the phase count is known without a host sync
            cols = auction_assignment(d, eps, valid, price0=-g, eps0=WARM_EPS0 * eps,
                                      phases=auction_phases(WARM_EPS0), budget=rounds or None)
        else:
            cols = auction_assignment(d, eps, valid, budget=rounds or None)
        exact_rows.last_items = 0
        if rounds:
            cols = exact_rows(d, cols, valid)
    ar = torch.arange(a.shape[0], device=a.device)[:, None]
    dist = (a - b[ar, cols.clamp(min=0)]).norm(dim=-1)
    out = _mean(dist, valid)
    return (out, cols) if return_assignment else out


def emd(a: torch.Tensor, b: torch.Tensor, valid: torch.Tensor | None = None, method: str = "auto",
        tol: float = 0.01, rounds: int = 0) -> torch.Tensor:
    """EMD (B,): ``exact`` = scipy's Hungarian assignment on the host (topocut.metrics.emd, per sample),
    ``auction`` = on the device within (1 + tol) of exact, ``auto`` = auction on CUDA, exact elsewhere."""
    if method not in EMD_METHODS:
        raise ValueError(f"emd method {method!r} is not one of {', '.join(EMD_METHODS)}")
    if method == "auto":
        method = "auction" if a.is_cuda else "exact"
    if method == "auction":
        return emd_auction(a, b, valid, tol, rounds=rounds)
    from topocut.metrics import emd as exact

    _check(a, b, valid)
    if valid is None or bool(valid.all()):
        return exact(a, b)
    v = valid.bool()
    return torch.cat([exact(a[i][v[i]][None], b[i][v[i]][None]) for i in range(a.shape[0])])

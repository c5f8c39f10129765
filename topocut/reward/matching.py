"""Fragment-to-goal assignment and the multi-fragment reward (docs/reward.md#several-fragments).

Distance of a fragment X to a goal piece Y (``piece_distance``):

    d(X, Y) = d_spec(X, Y) + d_size(X, Y)

d_spec the scale-free spectral shape distance (topocut.reward.spectral), d_size the pose-invariant size
distance (principal extents and fill, topocut.reward.size).  R(d) is the paper's piecewise-linear map:

    R(d) = R_max - gamma d                          for d <= tau
    R(d) = R_max - gamma tau - delta (d - tau)      for d >  tau        (delta > gamma)

clipped below at 0 (the main text's max(0, .)).

Every fragment is accounted for.  Each fragment f takes exactly one role, chosen by the Hungarian algorithm
to maximise the summed value:

* goal piece g (one fragment per goal piece):   R(d_fg) - c_mis (R_max - R(d_fg)) w_f
* the stock (at most one fragment: the uncut rest of the object):   0
* waste (material cut from the wrong place):   - c_waste R_max w_f

with w_f = min(1, V_f / mean_g V_g) the fragment's material in goal pieces (capped at one).  A goal piece
left without a fragment earns 0.  The goal's planned offcuts (``Goal.offcuts``: a die's rims, a stick's edge
band, what its own steps make besides the goal pieces and the rest) are not waste: waste up to their summed
weight (plus offcut_slack of a goal piece) is forgiven, the smallest fragments first (``forgive_offcuts``).
total = kappa * sum of values (kappa = 1 / G by default), clipped to
[0, R_max] (``RewardResult.unclipped`` keeps the sum).  N_C counts the fragments assigned to a goal piece
with d <= success_distance.

A fragment whose size terms alone put R at 0 for every goal piece (d >= d_size: the uncut stock) is not described
spectrally; its d is reported as d_size, a lower bound, and every value and role is as with the full d.
"""
from __future__ import annotations

import hashlib
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from topocut.reward.config import RewardConfig
from topocut.reward.size import size_descriptor, size_descriptors, size_distance
from topocut.reward.spectral import _points, descriptor, descriptor_distance, resample, resample_groups


def piecewise_reward(d, cfg: RewardConfig | None = None):
    """R(d) elementwise (float or array); inf -> 0."""
    cfg = cfg or RewardConfig()
    d = np.asarray(d, dtype=np.float64)
    r = np.where(d <= cfg.tau, cfg.r_max - cfg.gamma * d, cfg.r_max - cfg.gamma * cfg.tau - cfg.delta * (d - cfg.tau))
    r = np.clip(np.nan_to_num(r, neginf=0.0), 0.0, cfg.r_max)
    return float(r) if r.ndim == 0 else r


def match(distances, cfg: RewardConfig | None = None) -> list[tuple[int, int]]:
    """One-to-one (fragment, goal) pairs of an (F,G) distance matrix with the largest summed R(d); among
    assignments of equal reward (e.g. fragments all past R's zero) the smallest summed distance.
    Pairs at inf are left out."""
    D = np.asarray(distances, dtype=np.float64)
    if D.size == 0:
        return []
    finite = np.isfinite(D)
    if not finite.any():
        return []
    Df = np.where(finite, D, 0.0)
    # tie-break: all distance terms together stay below 1e-9, far below any reward difference that matters
    eps = 1e-9 / (Df.max() * D.size + 1e-300)
    # an inf pair is worth what no pair is (0: it is dropped), a hair worse than any finite pair of reward 0
    cost = np.where(finite, -piecewise_reward(Df, cfg) + eps * Df, 1e-9)
    rows, cols = linear_sum_assignment(cost)
    return sorted((int(r), int(c)) for r, c in zip(rows, cols) if finite[r, c])


def fragment_weights(volumes, goal_volumes) -> np.ndarray:
    """w_f = min(1, V_f / mean goal-piece volume): a fragment's material counted in goal pieces."""
    v = np.asarray(volumes, np.float64).reshape(-1)
    gv = float(np.mean(goal_volumes)) if len(goal_volumes) else 0.0
    if not gv > 0:
        return np.ones_like(v)
    return np.minimum(1.0, v / gv)


def assign(distances, cfg: RewardConfig | None = None, weights=None, volumes=None):
    """Roles of the fragments of an (F,G) distance matrix: (pairs [(f, g)], stock f or None, waste [f],
    values (F,)).  Maximises the summed value (module docstring); the summed distance of the pairs breaks
    ties.  A fragment at d = inf to every goal piece (below min_points) can only be stock or waste.
    ``volumes`` (F,), uncapped: among equal choices the largest fragment is the stock (the weights are capped at
    one, so a die and the whole rest of the object would tie)."""
    cfg = cfg or RewardConfig()
    D = np.asarray(distances, dtype=np.float64).reshape(len(distances), -1) if len(distances) else np.zeros((0, 0))
    F, G = D.shape if D.ndim == 2 else (0, 0)
    if F == 0:
        return [], None, [], np.zeros(0)
    w = np.ones(F) if weights is None else np.asarray(weights, np.float64)
    finite = np.isfinite(D)
    R = piecewise_reward(np.where(finite, D, np.inf), cfg) if G else np.zeros((F, 0))
    R = np.atleast_2d(R).reshape(F, G)
    pair_val = R - cfg.mismatch_cost * (cfg.r_max - R) * w[:, None]
    waste_val = -cfg.waste_cost * cfg.r_max * w
    Df = np.where(finite, D, 0.0)
    eps = 1e-9 / (Df.max(initial=0.0) * max(D.size, 1) + 1e-300)
    big = 1e6
    cost = np.full((F, G + 1 + F), big)
    cost[:, :G] = np.where(finite, -pair_val + eps * Df, big)
    size = w if volumes is None else np.asarray(volumes, np.float64) / max(float(np.max(volumes)), 1e-300)
    cost[:, G] = 0.0 - 1e-12 * size  # the stock: a hair better for the larger fragment among equal choices
    cost[np.arange(F), G + 1 + np.arange(F)] = -waste_val
    rows, cols = linear_sum_assignment(cost)
    pairs, stock, waste = [], None, []
    values = np.zeros(F)
    for r, c in zip(rows, cols):
        if c < G:
            pairs.append((int(r), int(c)))
            values[r] = pair_val[r, c]
        elif c == G:
            stock = int(r)
        else:
            waste.append(int(r))
            values[r] = waste_val[r]
    return sorted(pairs), stock, sorted(waste), values


@dataclass
class RewardResult:
    total: float  # kappa * sum of the fragments' values, clipped to [0, r_max]
    per_goal: np.ndarray  # G, R(d) of the fragment assigned to each goal piece (0 if none)
    matching: list = field(default_factory=list)  # [(fragment index, goal index)]
    cut_count: int = 0  # fragments assigned to a goal piece with d <= success distance (N_C)
    distances: np.ndarray = None  # F,G distances d_spec + d_size (inf: fragment too small)
    unclipped: float = 0.0  # kappa * sum of the fragments' values (may be < 0)
    stock: int | None = None  # the fragment taken as the uncut rest (value 0)
    waste: list = field(default_factory=list)  # fragments costing -c_waste w_f
    values: np.ndarray = None  # F, each fragment's value
    weights: np.ndarray = None  # F, w_f
    # [(fragment, share forgiven)]: waste fragments counted (in full, or the last in part) as the offcuts the goal's
    # own steps make (forgive_offcuts); ``waste`` still lists them
    offcuts: list = field(default_factory=list)


_CACHE: OrderedDict[tuple, object] = OrderedDict()  # goal resamplings / descriptors reused across MPPI rollouts
_CACHE_SIZE = 256


def _cached(key: tuple, make):
    if key in _CACHE:
        _CACHE.move_to_end(key)
        return _CACHE[key]
    val = _CACHE[key] = make()
    while len(_CACHE) > _CACHE_SIZE:
        _CACHE.popitem(last=False)
    return val


def _hash(points: np.ndarray) -> str:
    return hashlib.blake2b(np.ascontiguousarray(points).tobytes(), digest_size=16).hexdigest()


def _descriptors(clouds: list[np.ndarray], sigma, cfg: RewardConfig) -> list:
    """Descriptor per (resampled) cloud, None for clouds below min_points."""
    out: list = [None] * len(clouds)
    todo = [i for i, c in enumerate(clouds) if len(c) >= cfg.min_points]
    if cfg.backend == "torch" and todo:
        import torch

        groups = []
        for size in sorted({len(clouds[i]) for i in todo}):  # equal-size batches
            idx = [i for i in todo if len(clouds[i]) == size]
            groups.append((idx, torch.as_tensor(np.stack([clouds[i] for i in idx]), device=cfg.device)))
        _describe_groups(groups, sigma, cfg, out)
    else:
        for i in todo:
            out[i] = descriptor(clouds[i], sigma, cfg)
    return out


def _describe_groups(groups, sigma, cfg: RewardConfig, out: list) -> None:
    """Fill out[i] with (eigvals, signature) numpy arrays from [(indices, (b,n,3) tensor)] (torch backend)."""
    from topocut.reward.spectral import spectral_descriptors_groups

    described = spectral_descriptors_groups([batch for _, batch in groups], cfg, sigma=sigma)  # one eigen call
    for (idx, _), (w, s) in zip(groups, described):
        w, s = w.cpu().numpy(), s.cpu().numpy()  # one copy per group, not one sync per fragment
        for j, i in enumerate(idx):
            out[i] = (w[j], s[j])


def _raw_descriptors(clouds: list[np.ndarray], sigma, cfg: RewardConfig) -> list:
    """Descriptor per raw (not yet resampled) cloud, None below min_points.  The torch backend resamples
    every cloud in one batched FPS on cfg.device (``resample_groups``) and never brings points back."""
    if cfg.backend != "torch":
        return _descriptors([resample(c, cfg) for c in clouds], sigma, cfg)
    out: list = [None] * len(clouds)
    todo = [i for i, c in enumerate(clouds) if min(len(c), cfg.num_point) >= cfg.min_points]
    if todo:
        groups = resample_groups([clouds[i] for i in todo], cfg)
        _describe_groups([([todo[j] for j in ids], batch) for ids, batch in groups], sigma, cfg, out)
    return out


def piece_distance(x, y, cfg: RewardConfig | None = None) -> float:
    """d(x, y) = d_spec + d_size of one fragment x (n,3) to one goal piece y (m,3); inf below min_points."""
    return float(distance_matrix([x], [y], cfg)[0, 0])


def distance_matrix(fragments, goal_fragments, cfg: RewardConfig | None = None) -> np.ndarray:
    """(F,G) distances d_spec + d_size.

    Goal resamplings and descriptors are cached (keyed by the goal's bytes and the config),
    so repeated calls with the same goal, as in MPPI, only pay for the fragments.
    """
    return distance_matrices([fragments], goal_fragments, cfg, names=("fragments",))[0]


def distance_matrices(fragment_sets, goal_fragments, cfg: RewardConfig | None = None,
                      names=None) -> list[np.ndarray]:
    """One (F_s,G) matrix per set of fragments (e.g. the K scenes of an MPPI batch) against one goal."""
    return _score_sets(fragment_sets, goal_fragments, cfg, names)[0]


def distances_and_volumes(fragment_sets, goal_fragments, cfg: RewardConfig | None = None, names=None):
    """(one (F_s,G) distance matrix per set, fragment volumes per set, goal volumes): what
    ``reward_from_distances(D, G, cfg, volumes, goal_volumes)`` needs to score each set."""
    return _score_sets(fragment_sets, goal_fragments, cfg, names)


def _score_sets(fragment_sets, goal_fragments, cfg: RewardConfig | None = None, names=None, per_set=False):
    """(distance matrices, fragment volumes per set, goal volumes).

    goal_fragments: one list of goal clouds for every set, or (per_set=True) one list per set; the goal
    volumes are then one array per set.  All sets' fragments go through one descriptor call, so the torch
    backend resamples and decomposes every scene's fragments in one batch instead of one scene at a time.
    Goals are hashed once per distinct cloud; their resamplings and descriptors are cached across calls.
    """
    cfg = (cfg or RewardConfig()).validate()
    names = names or [f"fragment_sets[{s}]" for s in range(len(fragment_sets))]
    raw = [[_points(f, f"{name}[{i}]") for i, f in enumerate(fs)] for name, fs in zip(names, fragment_sets)]
    flat = iter(size_descriptors([f for fs in raw for f in fs]))  # every scene's pieces in one thread pool
    sizes = [[next(flat) for _ in fs] for fs in raw]
    goal_sets = goal_fragments if per_set else [goal_fragments]
    if per_set and len(goal_sets) != len(raw):
        raise ValueError(f"per-set goals: got {len(goal_sets)} goal lists for {len(raw)} fragment sets")
    ckey = repr(cfg)
    keys, ugoals, gidx = {}, [], []  # content hash -> distinct goal index; distinct (hash, cloud); per goal list
    for s, gs in enumerate(goal_sets):
        row = []
        for i, g in enumerate(gs):
            g = _points(g, f"goal_fragments[{s}][{i}]" if per_set else f"goal_fragments[{i}]")
            k = _hash(g)
            if k not in keys:
                keys[k] = len(ugoals)
                ugoals.append((k, g))
            row.append(keys[k])
        gidx.append(row)
    gsizes = [_cached(("size", k), lambda g=g: size_descriptor(g)) for k, g in ugoals]
    gres = [_cached(("resample", k, ckey), lambda g=g: resample(g, cfg)) for k, g in ugoals]
    uvols = np.array([sz[3] for sz in gsizes])
    set_goals = gidx if per_set else gidx * len(raw)  # each set's goal indices into ugoals
    Ds = [np.full((len(fs), len(row)), np.inf) for fs, row in zip(raw, set_goals)]
    vols = [np.array([sz[3] for sz in fs]) for fs in sizes]
    gvols = [uvols[row] for row in gidx] if per_set else uvols[gidx[0]]
    flat = [f for fs in raw for f in fs]
    if not flat or not any(len(g) >= cfg.min_points for g in gres):
        return Ds, vols, gvols
    d_size = [size_distance(np.asarray(fs)[:, None], np.asarray(gsizes)[row][None], cfg.size_weight,
                            cfg.fill_weight, cfg.profile_weight) if len(fs) and len(row) else np.zeros((len(fs), len(row)))
              for fs, row in zip(sizes, set_goals)]  # F_s,G_s
    # d = d_spec + d_size >= d_size: a fragment whose size alone puts it past R's zero for every goal piece (the
    # uncut stock, ~10^5 particles at 128^3) scores R = 0 whatever its shape, so it is not described spectrally
    # (its FPS was most of the reward's device time) and its d is reported as d_size, a lower bound
    needed = np.concatenate([(piecewise_reward(np.atleast_2d(d), cfg) > 0).any(1) if d.size else np.ones(len(d), bool)
                             for d in d_size])  # sum F_s,
    sigma = cfg.sigma  # None: each cloud its own graph width (scale-free spectra)
    described = _raw_descriptors([f for f, k in zip(flat, needed) if k], sigma, cfg)
    fd = iter(described)
    gd = _goal_descriptors([k for k, _ in ugoals], gres, sigma, cfg)
    need = iter(needed)
    for D, fs, ds, row in zip(Ds, raw, d_size, set_goals):
        for i in range(D.shape[0]):
            if next(need):
                a = next(fd)
                spec = [descriptor_distance(*a, *gd[u], cfg) if a is not None and gd[u] is not None else np.inf
                        for u in row]
            else:  # below min_points stays inf, as a described fragment would
                spec = [0.0 if min(len(fs[i]), cfg.num_point) >= cfg.min_points and gd[u] is not None else np.inf
                        for u in row]
            D[i] = np.asarray(spec) + ds[i]
    return Ds, vols, gvols


def _goal_descriptors(keys: list, clouds: list, sigma, cfg: RewardConfig) -> list:
    """Cached descriptor per distinct goal (resampled) cloud; the misses go through one batched call."""
    ckey = repr(cfg)
    missing = [j for j, k in enumerate(keys) if ("desc", k, ckey) not in _CACHE]
    fresh = dict(zip(missing, _descriptors([clouds[j] for j in missing], sigma, cfg)))
    # fresh.get: an entry evicted since the check above (more distinct goals than _CACHE_SIZE) is recomputed
    return [_cached(("desc", k, ckey), lambda j=j: fresh[j] if j in fresh else _descriptors([clouds[j]], sigma, cfg)[0])
            for j, k in enumerate(keys)]


def forgive_offcuts(values, weights, waste, offcut_weight: float, cfg: RewardConfig):
    """The waste the goal's own steps make, forgiven: (new values (F,), [(fragment, share forgiven)]).

    The goal plans offcuts besides its goal pieces and the rest (a die's rims, a stick's edge band:
    ``Goal.offcuts``), ``offcut_weight`` = their summed weight min(1, V_o / mean goal V) in the units of w_f.
    Of the fragments the assignment calls waste, the smallest are forgiven first, in full, until that budget
    plus reward.offcut_slack (a fraction of one goal piece) is spent (the last one in part): the plan's by-products are
    not waste, however the physics broke or merged them, but material beyond them is
    (docs/reward.md#planned-offcuts)."""
    values = np.asarray(values, np.float64).copy()
    budget = float(offcut_weight) + cfg.offcut_slack
    forgiven = []
    for f in sorted(waste, key=lambda f: (weights[f], f)):
        if budget <= 0:
            break
        share = min(1.0, budget / weights[f]) if weights[f] > 0 else 1.0
        budget -= share * weights[f]
        values[f] *= 1.0 - share
        forgiven.append((int(f), float(share)))
    return values, forgiven


def reward_from_distances(D: np.ndarray, G: int, cfg: RewardConfig, volumes=None,
                          goal_volumes=None, offcut_volumes=None) -> RewardResult:
    """Roles, values, total and N_C from an (F,G) distance matrix (spectral_reward's last step).

    volumes (F,) and goal_volumes (G,) give the fragments' weights w_f; without them every fragment weighs 1.
    offcut_volumes (O,): the goal's planned offcuts (docs/reward.md#planned-offcuts; ``forgive_offcuts``).
    """
    D = np.asarray(D, np.float64).reshape(-1, G)
    w = (fragment_weights(volumes, goal_volumes) if volumes is not None and goal_volumes is not None
         else np.ones(len(D)))
    pairs, stock, waste, values = assign(D, cfg, w, volumes)
    forgiven = []
    if offcut_volumes is not None and len(offcut_volumes) and goal_volumes is not None and waste:
        budget = float(fragment_weights(offcut_volumes, goal_volumes).sum())
        values, forgiven = forgive_offcuts(values, w, waste, budget, cfg)
    per_goal = np.zeros(G)
    success = cfg.tau if cfg.success_distance is None else cfg.success_distance
    cut_count = 0
    for f, g in pairs:
        per_goal[g] = piecewise_reward(D[f, g], cfg)
        cut_count += int(D[f, g] <= success)
    kappa = 1.0 / G if cfg.kappa is None else cfg.kappa
    unclipped = float(kappa * values.sum())
    total = float(np.clip(unclipped, 0.0, cfg.r_max)) if cfg.clip_total else unclipped
    return RewardResult(total, per_goal, pairs, cut_count, D, unclipped, stock, waste, values, w, forgiven)


def _is_per_set(goal_fragments) -> bool:
    """True when goal_fragments is one list of goal clouds per set (its first entry holds 2-D clouds),
    False for one shared list of clouds (its first entry is itself a cloud: rows of 3 coordinates)."""
    if len(goal_fragments) == 0:
        return False
    first = goal_fragments[0]
    return len(first) > 0 and np.ndim(first[0]) == 2


def spectral_rewards(fragment_sets, goal_fragments, cfg: RewardConfig | None = None, offcuts=None) -> list[RewardResult]:
    """spectral_reward of each set of fragments, descriptors batched across sets.

    goal_fragments is either one list of goal clouds (m,3) that every set is scored against, or one such
    list per set (``spectral_rewards_per_goal``), told apart by ``_is_per_set``: per set when its first
    entry is a list of clouds rather than a cloud.  ``offcuts``: the goal's planned offcuts, shaped like
    goal_fragments (one list, or one list per set).  Result s equals spectral_reward(fragment_sets[s], its goals).
    """
    if _is_per_set(goal_fragments):
        return spectral_rewards_per_goal(fragment_sets, goal_fragments, cfg, offcuts)
    if not len(goal_fragments):
        raise ValueError("spectral_rewards needs at least one goal fragment")
    cfg = (cfg or RewardConfig()).validate()
    Ds, vols, gvols = _score_sets(fragment_sets, goal_fragments, cfg)  # the shared goal hashed once
    ov = _offcut_volumes(offcuts)
    return [reward_from_distances(D, len(goal_fragments), cfg, v, gvols, ov) for D, v in zip(Ds, vols)]


def spectral_rewards_per_goal(fragment_sets, goal_sets, cfg: RewardConfig | None = None,
                              offcut_sets=None) -> list[RewardResult]:
    """spectral_reward(fragment_sets[s], goal_sets[s], cfg, offcut_sets[s]) for every s in one batched call:
    scenes that each have their own goal (goal_sets: one list of (m,3) goal clouds per set, same length as
    fragment_sets; offcut_sets: one list of planned offcuts per set, or None).  All fragments share one
    resampling / descriptor batch; each distinct goal cloud is described once and cached by content, so
    repeated goals (and repeated calls, as in MPPI) cost nothing more."""
    cfg = (cfg or RewardConfig()).validate()
    if len(goal_sets) != len(fragment_sets):
        raise ValueError(f"spectral_rewards_per_goal: {len(goal_sets)} goal lists for {len(fragment_sets)} "
                         "fragment sets (one list per set)")
    for s, gs in enumerate(goal_sets):
        if not len(gs):
            raise ValueError(f"spectral_rewards_per_goal: goal_sets[{s}] has no goal fragment")
    offcut_sets = [[] for _ in goal_sets] if offcut_sets is None else [list(o or []) for o in offcut_sets]
    if len(offcut_sets) != len(goal_sets):
        raise ValueError(f"spectral_rewards_per_goal: {len(offcut_sets)} offcut lists for {len(goal_sets)} sets")
    Ds, vols, gvols = _score_sets(fragment_sets, goal_sets, cfg, per_set=True)
    ovols = [_offcut_volumes(off) for off in offcut_sets]
    return [reward_from_distances(D, len(gs), cfg, v, gv, ov)
            for D, v, gv, ov, gs in zip(Ds, vols, gvols, ovols, goal_sets)]


def _offcut_volumes(offcuts) -> np.ndarray:
    """(O,) volumes of a goal's planned offcuts (cached by content, as the goal pieces' descriptors are)."""
    clouds = [_points(o, f"offcuts[{i}]") for i, o in enumerate(offcuts or [])]
    return np.array([_cached(("size", _hash(o)), lambda o=o: size_descriptor(o))[3] for o in clouds])


def spectral_reward(fragments, goal_fragments, cfg: RewardConfig | None = None, offcuts=None) -> RewardResult:
    """Reward of the current pieces (list of (n,3)) against the goal pieces (list of (m,3)) and the goal's
    planned offcuts (list of (k,3), docs/reward.md#planned-offcuts; None: the goal plans none)."""
    cfg = (cfg or RewardConfig()).validate()
    G = len(goal_fragments)
    if G == 0:
        raise ValueError("spectral_reward needs at least one goal fragment")
    Ds, vols, gvols = _score_sets([fragments], goal_fragments, cfg, names=("fragments",))
    return reward_from_distances(Ds[0], G, cfg, vols[0], gvols, _offcut_volumes(offcuts))

"""Fragment-to-goal matching and the multi-fragment spectral reward.

R(d) is the paper's piecewise-linear map (appendix, "Pose-Invariant Shape Evaluation"):

    R(d) = R_max - gamma d                          for d <= tau
    R(d) = R_max - gamma tau - delta (d - tau)      for d >  tau        (delta > gamma)

clipped below at 0 (the main text's max(0, .)), so 0 <= R <= R_max.  Fragments are
assigned to goal pieces one-to-one by the Hungarian algorithm maximising the summed reward
(the distance only breaks ties: minimising summed distance instead lets a far-off extra
fragment, which earns 0 anyway, pull a perfect fragment off its goal piece); goal pieces
left without a fragment score 0.  total = kappa * sum_g R(d_g), with
kappa = 1 / G by default so that 0 <= total <= R_max whatever the number G of goal pieces.
"""
from __future__ import annotations

import hashlib
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from topocut.reward.config import RewardConfig
from topocut.reward.spectral import _points, descriptor, descriptor_distance, reference_sigma, resample


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


@dataclass
class RewardResult:
    total: float  # kappa * sum of per-goal rewards
    per_goal: np.ndarray  # G, R(d) of the fragment matched to each goal piece (0 if none)
    matching: list = field(default_factory=list)  # [(fragment index, goal index)]
    cut_count: int = 0  # matched pieces with d <= success distance (N_C)
    distances: np.ndarray = None  # F,G spectral distances (inf: fragment too small)


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


def _descriptors(clouds: list[np.ndarray], sigma: float, cfg: RewardConfig) -> list:
    """Descriptor per (resampled) cloud, None for clouds below min_points."""
    out: list = [None] * len(clouds)
    todo = [i for i, c in enumerate(clouds) if len(c) >= cfg.min_points]
    if cfg.backend == "torch" and todo:
        import torch

        from topocut.reward.spectral import spectral_descriptors

        for size in sorted({len(clouds[i]) for i in todo}):  # equal-size batches
            idx = [i for i in todo if len(clouds[i]) == size]
            batch = torch.as_tensor(np.stack([clouds[i] for i in idx]), device=cfg.device)
            w, s = spectral_descriptors(batch, cfg, sigma=sigma)
            for j, i in enumerate(idx):
                out[i] = (w[j].cpu().numpy(), s[j].cpu().numpy())
    else:
        for i in todo:
            out[i] = descriptor(clouds[i], sigma, cfg)
    return out


def distance_matrix(fragments, goal_fragments, cfg: RewardConfig | None = None) -> np.ndarray:
    """(F,G) spectral distances; sigma is set once from the goal pieces (reference_sigma).

    Goal resamplings and descriptors are cached (keyed by the goal's bytes and the config),
    so repeated calls with the same goal, as in MPPI, only pay for the fragments.
    """
    return distance_matrices([fragments], goal_fragments, cfg, names=("fragments",))[0]


def distance_matrices(fragment_sets, goal_fragments, cfg: RewardConfig | None = None,
                      names=None) -> list[np.ndarray]:
    """One (F_s,G) matrix per set of fragments (e.g. the K scenes of an MPPI batch) against one goal.

    All sets' fragments go through one descriptor call, so the torch backend
    decomposes every scene's fragments in one batch instead of one scene at a time.
    """
    cfg = (cfg or RewardConfig()).validate()
    names = names or [f"fragment_sets[{s}]" for s in range(len(fragment_sets))]
    sets = [[resample(_points(f, f"{name}[{i}]"), cfg) for i, f in enumerate(fs)]
            for name, fs in zip(names, fragment_sets)]
    goals = [_points(g, f"goal_fragments[{i}]") for i, g in enumerate(goal_fragments)]
    ckey = repr(cfg)
    gkeys = [_hash(g) for g in goals]
    goals = [_cached(("resample", k, ckey), lambda g=g: resample(g, cfg)) for k, g in zip(gkeys, goals)]
    Ds = [np.full((len(fs), len(goals)), np.inf) for fs in sets]
    valid = [g for g in goals if len(g) >= cfg.min_points]
    flat = [f for fs in sets for f in fs]
    if not flat or not valid:
        return Ds
    sigma = reference_sigma(valid, cfg)
    fd = iter(_descriptors(flat, sigma, cfg))
    gd = [_cached(("desc", k, sigma, ckey), lambda g=g: _descriptors([g], sigma, cfg)[0]) for k, g in zip(gkeys, goals)]
    for D in Ds:
        for i in range(D.shape[0]):
            a = next(fd)
            for j, b in enumerate(gd):
                if a is not None and b is not None:
                    D[i, j] = descriptor_distance(*a, *b, cfg)
    return Ds


def reward_from_distances(D: np.ndarray, G: int, cfg: RewardConfig) -> RewardResult:
    """Matching, R(d) per goal piece, total and N_C from an (F,G) distance matrix (spectral_reward's last step)."""
    pairs = match(D, cfg)
    per_goal = np.zeros(G)
    success = cfg.tau if cfg.success_distance is None else cfg.success_distance
    cut_count = 0
    for f, g in pairs:
        per_goal[g] = piecewise_reward(D[f, g], cfg)
        cut_count += int(D[f, g] <= success)
    kappa = 1.0 / G if cfg.kappa is None else cfg.kappa
    return RewardResult(float(kappa * per_goal.sum()), per_goal, pairs, cut_count, D)


def spectral_rewards(fragment_sets, goal_fragments, cfg: RewardConfig | None = None) -> list[RewardResult]:
    """spectral_reward of each set of fragments against the same goal, descriptors batched across sets."""
    cfg = (cfg or RewardConfig()).validate()
    if not goal_fragments:
        raise ValueError("spectral_rewards needs at least one goal fragment")
    return [reward_from_distances(D, len(goal_fragments), cfg) for D in distance_matrices(fragment_sets, goal_fragments, cfg)]


def spectral_reward(fragments, goal_fragments, cfg: RewardConfig | None = None) -> RewardResult:
    """Reward of the current pieces (list of (n,3)) against the goal pieces (list of (m,3))."""
    cfg = (cfg or RewardConfig()).validate()
    G = len(goal_fragments)
    if G == 0:
        raise ValueError("spectral_reward needs at least one goal fragment")
    return reward_from_distances(distance_matrix(fragments, goal_fragments, cfg), G, cfg)

"""Fragment-to-goal assignment and the multi-fragment reward (docs/reward.md#several-fragments); the distances
themselves are topocut.reward.distance's.

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

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from topocut.reward.config import RewardConfig
from topocut.reward.distance import _offcut_volumes, _score_sets, piecewise_reward


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
    ov = _offcut_volumes(offcuts, goal_fragments, gvols)
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
    ovols = [_offcut_volumes(off, gs, gv) for off, gs, gv in zip(offcut_sets, goal_sets, gvols)]
    return [reward_from_distances(D, len(gs), cfg, v, gv, ov)
            for D, v, gv, ov, gs in zip(Ds, vols, gvols, ovols, goal_sets)]


def spectral_reward(fragments, goal_fragments, cfg: RewardConfig | None = None, offcuts=None) -> RewardResult:
    """Reward of the current pieces (list of (n,3)) against the goal pieces (list of (m,3)) and the goal's
    planned offcuts (list of (k,3), docs/reward.md#planned-offcuts; None: the goal plans none)."""
    cfg = (cfg or RewardConfig()).validate()
    G = len(goal_fragments)
    if G == 0:
        raise ValueError("spectral_reward needs at least one goal fragment")
    Ds, vols, gvols = _score_sets([fragments], goal_fragments, cfg, names=("fragments",))
    return reward_from_distances(Ds[0], G, cfg, vols[0], gvols, _offcut_volumes(offcuts, goal_fragments, gvols))

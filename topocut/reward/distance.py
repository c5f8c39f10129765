"""What R sees, for every fragment and goal piece at once (docs/reward.md#the-distance-r-sees).

d(X, Y) = d_spec(X, Y) + d_size(X, Y) (topocut.reward.spectral, topocut.reward.size) as (F,G) matrices, one per
set of fragments (the K scenes of an MPPI batch) against one goal or each set's own, every set's fragments through
one descriptor call; goal resamplings and descriptors cached by content across calls.  And the paper's
piecewise map R(d) (``piecewise_reward``).  Roles, values and totals: topocut.reward.matching.
"""
from __future__ import annotations

import hashlib
from collections import OrderedDict

import numpy as np

from topocut.reward.config import RewardConfig
from topocut.reward.size import (
    PROFILE_QUANTILES,
    material_volumes,
    particle_spacing,
    set_spacing,
    size_descriptor,
    size_descriptors,
    size_distance,
)
from topocut.reward.spectral import _points, descriptor, descriptor_distance, resample, resample_groups
from topocut.reward.strays import body


def piecewise_reward(d, cfg: RewardConfig | None = None):
    """R(d) elementwise (float or array); inf -> 0."""
    cfg = cfg or RewardConfig()
    d = np.asarray(d, dtype=np.float64)
    r = np.where(d <= cfg.tau, cfg.r_max - cfg.gamma * d, cfg.r_max - cfg.gamma * cfg.tau - cfg.delta * (d - cfg.tau))
    r = np.clip(np.nan_to_num(r, neginf=0.0), 0.0, cfg.r_max)
    return float(r) if r.ndim == 0 else r


_CACHE: OrderedDict[tuple, object] = OrderedDict()  # goal resamplings / descriptors reused across MPPI rollouts
# and across the evaluation's runs of one batch of episodes (a learned policy's training seeds, one after another:
# topocut.eval.runner): 16 dice goals of 27 pieces are ~1,300 entries
_CACHE_SIZE = 4096


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


def piece_distance(x, y, cfg: RewardConfig | None = None, spacing: float | None = None) -> float:
    """d(x, y) = d_spec + d_size of one fragment x (n,3) to one goal piece y (m,3); inf below min_points.
    ``spacing``: as for distance_matrix."""
    return float(distance_matrix([x], [y], cfg, spacing=spacing)[0, 0])


def distance_matrix(fragments, goal_fragments, cfg: RewardConfig | None = None,
                    spacing: float | None = None) -> np.ndarray:
    """(F,G) distances d_spec + d_size.

    ``spacing``: the particle spacing every fragment and goal piece was made at, where the caller knows that they
    share it (the pen's and the spoon's scenes: every particle stands for spacing^3 of material, MPMSolver.vol);
    the size terms then take it instead of estimating it from each cloud's neighbour distances
    (topocut.reward.size.particle_spacing).  None (the knife tasks): the estimate.

    Goal resamplings and descriptors are cached (keyed by the goal's bytes and the config),
    so repeated calls with the same goal, as in MPPI, only pay for the fragments.
    """
    return distance_matrices([fragments], goal_fragments, cfg, names=("fragments",), spacing=spacing)[0]


def distance_matrices(fragment_sets, goal_fragments, cfg: RewardConfig | None = None,
                      names=None, spacing: float | None = None) -> list[np.ndarray]:
    """One (F_s,G) matrix per set of fragments (e.g. the K scenes of an MPPI batch) against one goal."""
    return _score_sets(fragment_sets, goal_fragments, cfg, names, spacing=spacing)[0]


def distances_and_volumes(fragment_sets, goal_fragments, cfg: RewardConfig | None = None, names=None,
                          spacing: float | None = None):
    """(one (F_s,G) distance matrix per set, fragment volumes per set, goal volumes): what
    ``reward_from_distances(D, G, cfg, volumes, goal_volumes)`` needs to score each set.  The volumes are the pieces'
    material (``material_volumes``: particles x the goal's lattice cell, ``_fragment_material``), what w_f counts."""
    return _score_sets(fragment_sets, goal_fragments, cfg, names, spacing=spacing)


def _score_sets(fragment_sets, goal_fragments, cfg: RewardConfig | None = None, names=None, per_set=False,
                spacing: float | None = None):
    """(distance matrices, fragment volumes per set, goal volumes): the volumes are material (particle counts x the
    goal's lattice cell, ``set_spacing``; a set sampled at another spacing its own: ``_fragment_material``), what the
    weights w_f count.

    goal_fragments: one list of goal clouds for every set, or (per_set=True) one list per set; the goal
    volumes are then one array per set.  All sets' fragments go through one descriptor call, so the torch
    backend resamples and decomposes every scene's fragments in one batch instead of one scene at a time.
    Goals are hashed once per distinct cloud; their resamplings and descriptors are cached across calls.

    d = d_spec + d_size >= d_size >= its extent and fill terms: a fragment whose size alone puts it past R's zero
    for every goal piece of its set (the uncut stock, ~10^5 particles at 128^3) scores R = 0 whatever its shape, so
    it is not described spectrally (its FPS was most of the reward's device time) nor, where its extents and fill
    already say so, profiled; its d is reported as the size terms it was measured with, a lower bound.

    spacing: the particle spacing shared by every fragment and goal piece (distance_matrix); None: each cloud's own
    estimate.
    """
    cfg = (cfg or RewardConfig()).validate()
    if spacing is not None and not spacing > 0:
        raise ValueError(f"spacing={spacing} must be > 0 (the particle spacing) or None (estimated per cloud)")
    skey = () if spacing is None else (float(spacing),)  # the estimate keeps its cache keys
    names = names or [f"fragment_sets[{s}]" for s in range(len(fragment_sets))]
    raw = [[_points(f, f"{name}[{i}]") for i, f in enumerate(fs)] for name, fs in zip(names, fragment_sets)]
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
    ucounts = [len(g) for _, g in ugoals]  # the goal pieces' material, in particles (strays and all)
    # goal pieces by their bodies as the fragments (ideal pieces have no strays: the same points), and their sizes
    pieces = [_cached(("goal piece", k, *skey, cfg.stray_share), lambda g=g: _goal_piece(g, spacing, cfg))
              for k, g in ugoals]
    ugoals = [(k, b) for (k, _), (b, _) in zip(ugoals, pieces)]
    gsizes = np.array([size for _, size in pieces])  # U,5+Q
    gres = [_cached(("resample", k, ckey), lambda g=g: resample(g, cfg)) for k, g in ugoals]
    set_goals = gidx if per_set else gidx * len(raw)  # each set's goal indices into ugoals
    # every scene's pieces at once (on the device, or in one host thread pool: reward.size_solver), each profiled only
    # where its extents and fill leave R > 0, each described by its body (its strays left out) where that matters
    counts = [[len(f) for f in fs] for fs in raw]  # each fragment's material, in particles (strays and all)
    todo = [(f, gsizes[row]) for fs, row in zip(raw, set_goals) for f in fs]
    flat_sizes = iter(_fragment_sizes(todo, cfg, spacing))
    sized = [[next(flat_sizes) for _ in fs] for fs in raw]
    sizes = [[sz for sz, _ in fs] for fs in sized]
    raw = [[b for _, b in fs] for fs in sized]
    Ds = [np.full((len(fs), len(row)), np.inf) for fs, row in zip(raw, set_goals)]
    # the weights count material, not the size descriptor's V (the body's particles x the piece's own spacing
    # estimate, which a chip or a torn sheet inflates): docs/reward.md#weights
    gcells = [set_spacing(gsizes[row, -1] if len(row) else [], [ucounts[u] for u in row]) for row in gidx]
    gvols = [material_volumes([ucounts[u] for u in row], c) for row, c in zip(gidx, gcells)]
    set_cells = gcells if per_set else gcells * len(raw)
    vols = [_fragment_material(n, [sz[-1] for sz in fs], c) for fs, n, c in zip(sizes, counts, set_cells)]
    gvols = gvols if per_set else gvols[0]
    flat = [f for fs in raw for f in fs]
    if not flat or not any(len(g) >= cfg.min_points for g in gres):
        return Ds, vols, gvols
    d_size = [_size_matrix(np.asarray(fs), gsizes[row], cfg) if len(fs) and len(row) else np.zeros((len(fs), len(row)))
              for fs, row in zip(sizes, set_goals)]  # F_s,G_s
    needed = np.concatenate([(piecewise_reward(np.atleast_2d(d), cfg) > 0).any(1) if d.size else np.ones(len(d), bool)
                             for d in d_size])  # sum F_s,
    sigma = cfg.sigma  # None: each cloud its own graph width (scale-free spectra)
    fd = iter(_raw_descriptors([f for f, k in zip(flat, needed) if k], sigma, cfg))
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


def _goal_piece(points: np.ndarray, spacing: float | None, cfg: RewardConfig) -> tuple[np.ndarray, np.ndarray]:
    """(body, size_descriptor of the body) of a goal piece (N,3).  Its spacing is estimated once where the body
    kept every point (an ideal piece has no strays): the body's own estimate would read the same points in the
    same order, so it is the same number, and it is one KD-tree of the piece less (a goal piece is new every
    evaluation episode: its pose is the episode's)."""
    s = particle_spacing(points) if spacing is None else float(spacing)
    kept = body(points, s, cfg.stray_share)
    return kept, size_descriptor(kept, s if spacing is not None or len(kept) == len(points) else None)


def _fragment_sizes(items: list, cfg: RewardConfig, spacing: float | None = None) -> list:
    """``_fragment_size`` of each (fragment, its set's goal sizes) in ``items``, where ``reward.size_solver`` says: every
    fragment at once on the reward's device (topocut.reward.size_batch) or one at a time in host threads."""
    if cfg.backend == "torch" and (cfg.size_solver == "device" or (cfg.size_solver == "auto"
                                                                   and not str(cfg.device).startswith("cpu"))):
        from topocut.reward.size_batch import fragment_sizes

        return fragment_sizes(items, cfg, spacing)
    return size_descriptors(items, fn=lambda t: _fragment_size(t[0], t[1], cfg, spacing))


def _fragment_size(points: np.ndarray, goal_sizes: np.ndarray, cfg: RewardConfig,
                   spacing: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(size_descriptor, the points described) of a fragment (N,3) against its set's goal pieces (G,5+Q).  Its
    thickness profile is left NaN, and its strays in, when its extent and fill terms alone already put R at 0 for
    every goal piece (the profile term only adds; a few strays cannot bring an uncut stock near a goal piece);
    otherwise it is described by its body (topocut.reward.strays.body).  spacing: the known particle spacing (None: estimated)."""
    s = particle_spacing(points) if spacing is None else float(spacing)
    base = size_descriptor(points, s, profile=False)
    if past_zero_by_size(base, goal_sizes, cfg):
        return base, points
    kept = body(points, s, cfg.stray_share)  # the points themselves where stray_share is 0
    return size_descriptor(kept, s), kept


def past_zero_by_size(base: np.ndarray, goal_sizes: np.ndarray, cfg: RewardConfig) -> bool:
    """Whether a fragment's extents and fill alone (its size descriptor without the profile, (5+Q,)) put R at 0 for
    every goal piece (G, 5+Q) of its set: then it is neither profiled nor described (False without goal pieces)."""
    if not len(goal_sizes):
        return False
    bound = size_distance(base, goal_sizes, cfg.size_weight, cfg.fill_weight, 0.0, cfg.size_tolerance)  # G,
    return not (piecewise_reward(np.atleast_1d(bound), cfg) > 0).any()


def _size_matrix(sizes: np.ndarray, goal_sizes: np.ndarray, cfg: RewardConfig) -> np.ndarray:
    """(F,G) d_size; a fragment left unprofiled (``_fragment_size``) gets its extent and fill terms alone."""
    full = size_distance(sizes[:, None], goal_sizes[None], cfg.size_weight, cfg.fill_weight, cfg.profile_weight,
                         cfg.size_tolerance)
    part = size_distance(sizes[:, None], goal_sizes[None], cfg.size_weight, cfg.fill_weight, 0.0, cfg.size_tolerance)
    return np.where(np.isnan(sizes[:, 4:4 + PROFILE_QUANTILES]).any(1)[:, None], part, full)  # the profile's NaN


def _goal_descriptors(keys: list, clouds: list, sigma, cfg: RewardConfig) -> list:
    """Cached descriptor per distinct goal (resampled) cloud; the misses go through one batched call."""
    ckey = repr(cfg)
    missing = [j for j, k in enumerate(keys) if ("desc", k, ckey) not in _CACHE]
    fresh = dict(zip(missing, _descriptors([clouds[j] for j in missing], sigma, cfg)))
    # fresh.get: an entry evicted since the check above (more distinct goals than _CACHE_SIZE) is recomputed
    return [_cached(("desc", k, ckey), lambda j=j: fresh[j] if j in fresh else _descriptors([clouds[j]], sigma, cfg)[0])
            for j, k in enumerate(keys)]


SAME_LATTICE = 0.25  # fragments whose spacing is within this share of their goal's were sampled on its lattice


def _fragment_material(counts, spacings, goal_cell: float) -> np.ndarray:
    """A set's fragments' material (F,) in its goal's unit: their particles x the goal's lattice cell where the set
    was sampled on the goal's lattice (its spacing, set_spacing, within SAME_LATTICE of the goal's: every goal the
    project makes is what its steps make on the scene's own particles), so a fragment weighs its particle count over
    a goal piece's; another set (a goal sampled apart, at another spacing) its own cell."""
    own = set_spacing(spacings, counts)
    same = goal_cell > 0 and own > 0 and abs(own / goal_cell - 1.0) <= SAME_LATTICE
    return material_volumes(counts, goal_cell if same else own)


def _offcut_volumes(offcuts, goal_fragments, goal_volumes) -> np.ndarray:
    """(O,) material of a goal's planned offcuts in its goal pieces' unit: their particles x the goal's lattice cell
    (goal_volumes over the goal pieces' particles: a goal's pieces and offcuts are one sampling)."""
    counts = np.array([len(_points(o, f"offcuts[{i}]")) for i, o in enumerate(offcuts or [])], np.float64)
    n_goal = sum(len(g) for g in goal_fragments)
    return counts * (float(np.sum(goal_volumes)) / n_goal if n_goal else 0.0)

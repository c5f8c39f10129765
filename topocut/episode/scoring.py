"""How a state is labelled and scored: topology discovery (cluster ids carried over from the previous labels),
the pieces (``fragments``), the spectral reward of the pieces against the goal's, the task's success.

``make_scoring`` is the one builder of the engine's ``Scoring`` (every scene of a step against its own goal, in
one reward call), whether from the task registry and the configs (evaluation, the gym env), with parts
replaced (tests run the protocol without the simulator that way), or from a one-goal ``Scorer``
(demonstrations, teleop: ``scorer=``).  ``Scorer`` is that one-goal view, which MPPI's rollouts also score
with (``labels_batch``, ``rewards``: K rollouts against one goal in one call); its discovery and its pieces
are the builder's.
"""
from __future__ import annotations

import inspect
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from topocut.episode.records import Score
from topocut.episode.scene import env_board_z, topology_device


@dataclass
class Scoring:
    """How a state is labelled and scored; each part replaceable (test doubles, other backends)."""
    goal_fn: Callable  # (task_cfg, object, pose, spacing, seed) -> Goal: seed, the scene's particle sampling
    discover_fn: Callable  # (x (N,3), damage (N,), sweeps, previous_labels[, start_positions=]) -> labels (N,)
    score_fn: Callable  # (xs, labels, goals, task_cfgs) -> [Score]: all scenes of a step in one call


def fragments(x, labels, min_points: int) -> list[np.ndarray]:
    """The pieces (n_i,3) of labelled particles; -1 (unassigned) is no piece, pieces below min_points dropped."""
    x, labels = np.asarray(x), np.asarray(labels).reshape(-1)
    key = labels
    if len(labels) and labels.dtype.kind == "i" and -2 ** 15 <= labels.min() and labels.max() < 2 ** 15:
        key = labels.astype(np.int16)  # 16-bit keys: numpy's stable sort is a radix sort, ~5x faster, same order
    order = np.argsort(key, kind="stable")  # one sort, not a mask per label: each piece keeps its particles' order
    ordered = labels[order]
    # np.unique(ordered, return_index=True) without its second sort: the labels are sorted, so each id starts where
    # its predecessor differs
    start = np.flatnonzero(ordered[1:] != ordered[:-1]) + 1
    ids = ordered[np.concatenate([[0], start])] if len(ordered) else ordered
    pieces = np.split(x[order], start)
    return [f for c, f in zip(ids, pieces) if c >= 0 and len(f) >= min_points]


_GOALS: OrderedDict = OrderedDict()  # task_goal's: the goals of the last GOALS_KEPT episodes of this process
GOALS_KEPT = 32


def task_goal(task_cfg, obj, pose, spacing: float, board_z: float, seed: int = 0):
    """``get_task(task_cfg.name).make_goal(...)``, kept for the process's last GOALS_KEPT (task config, object, pose,
    spacing, board, seed): the evaluation runs each batch of episodes once per policy run (a learned policy's
    training seeds one after another), and a 128³ goal costs ~1 s of host time (its ideal execution, its sampling).
    make_goal is deterministic in these; each caller gets its own copy (a policy may keep what it is given)."""
    import copy

    from topocut.tasks import get_task

    key = (repr(task_cfg), str(obj), repr(pose), float(spacing), float(board_z), int(seed))
    if key in _GOALS:
        _GOALS.move_to_end(key)
    else:
        _GOALS[key] = get_task(task_cfg.name).make_goal(task_cfg, obj, pose, spacing, board_z=board_z, seed=seed)
        while len(_GOALS) > GOALS_KEPT:
            _GOALS.popitem(last=False)
    return copy.deepcopy(_GOALS[key])


def discover_labels(x, damage, sweeps, previous, topo_cfg=None, device: str = "cpu",
                    start_positions=None) -> np.ndarray:  # N,
    """Topology discovery (topocut.topology.discover on ``device``) with the previous labels' cluster ids;
    ``start_positions``: the particles where the cut's blade started (a kerf particle keeps its side there)."""
    from topocut.topology import discover

    res = discover(np.asarray(x), np.asarray(damage, bool), sweeps, previous_labels=previous, cfg=topo_cfg,
                   device=device, start_positions=start_positions)
    return np.asarray(res.labels, np.int32)


def make_scoring(reward_cfg=None, topo_cfg=None, device: str = "cpu", board_z: float = 0.05,
                 min_fragment_points: int = 4, *, env=None, goal_fn: Callable | None = None,
                 discover_fn: Callable | None = None, reward_fn: Callable | None = None, scorer=None) -> Scoring:
    """The engine's Scoring: the task registry's goal (on the board at ``board_z``) and success, topology
    discovery on ``device``, the spectral reward of every scene against its own goal in one call (descriptors
    batched across scenes).  ``env``: ``device`` and ``board_z`` are the simulator's (discovery where it runs).

    Replacements: ``goal_fn(task_cfg, obj, pose, spacing, seed)``, ``discover_fn(x, damage, sweeps, previous,
    topo_cfg)`` and ``reward_fn(fragments, goal_fragments, reward_cfg)`` (told no planned offcuts; one scene a
    call).  ``scorer``: a one-goal scorer (``Scorer`` or a double with ``labels(x, damage, sweeps, previous)``
    and ``reward(x, labels) -> (total, success)``) labels and scores every scene instead (the episode's goal
    given, not built)."""
    if scorer is not None:
        return _scorer_scoring(scorer)
    if env is not None:
        device, board_z = topology_device(env), env_board_z(env)
    from topocut.tasks import get_task

    def default_goal(task_cfg, obj, pose, spacing, seed=0):  # the scene's own particles (its sampling seed), ideally cut
        return task_goal(task_cfg, obj, pose, spacing, board_z, seed)

    if discover_fn is None:
        def discover(x, damage, sweeps, previous, start_positions=None):
            return discover_labels(x, damage, sweeps, previous, topo_cfg, device, start_positions)
    else:
        def discover(x, damage, sweeps, previous):
            return discover_fn(x, np.asarray(damage, bool), sweeps, previous, topo_cfg)

    if reward_fn is None:
        def rewards_fn(sets, goal_sets, offcut_sets=None):
            from topocut.reward import spectral_rewards

            return spectral_rewards(sets, goal_sets, reward_cfg, offcut_sets)
    else:  # a replacement reward_fn(fragments, goal_fragments, reward_cfg) is told no planned offcuts
        def rewards_fn(sets, goal_sets, offcut_sets=None):
            return [reward_fn(f, g, reward_cfg) for f, g in zip(sets, goal_sets)]

    def score_fn(xs, labels, goals, task_cfgs):
        sets = [fragments(x, lab, min_fragment_points) for x, lab in zip(xs, labels)]
        res = rewards_fn(sets, [[np.asarray(f) for f in g.fragments] for g in goals],
                         [[np.asarray(f) for f in getattr(g, "offcuts", None) or []] for g in goals]) if sets else []
        return [Score(float(r.total), int(r.cut_count), bool(get_task(t.name).success(r, t)), len(f))
                for r, t, f in zip(res, task_cfgs, sets)]

    return Scoring(goal_fn or default_goal, discover, score_fn)


def _scorer_scoring(scorer) -> Scoring:
    """The Scoring of a one-goal scorer: its labels and its reward/success (N_C not counted: 0)."""

    def score_fn(xs, labels, goals, task_cfgs):
        out = []
        for x, lab in zip(xs, labels):
            total, ok = scorer.reward(x, lab)
            out.append(Score(float(total), 0, bool(ok), int(len([c for c in np.unique(lab) if c >= 0]))))
        return out

    return Scoring(goal_fn=None, discover_fn=scorer.labels, score_fn=score_fn)


class Scorer:
    """Labels (topology discovery) and reward/success of a particle state against one goal."""

    def __init__(self, goal, reward_cfg=None, topo_cfg=None, success_threshold: float | None = None,
                 min_fragment_points: int = 4, device: str = "cpu", success_fn=None):
        """``success_fn(RewardResult) -> bool`` (the task's ``success``, e.g. ``lambda r: task.success(r, cfg)``)
        decides success; without it, the total at ``success_threshold`` (None: never)."""
        self.goal, self.reward_cfg, self.topo_cfg = goal, reward_cfg, topo_cfg
        self.success_threshold, self.min_fragment_points, self.device = success_threshold, min_fragment_points, device
        self.success_fn = success_fn

    def labels(self, x, damage, sweeps, previous=None, start_positions=None) -> np.ndarray:  # N,
        return discover_labels(x, damage, sweeps, previous, self.topo_cfg, self.device, start_positions)

    def labels_batch(self, xs, damages, sweeps, previous, start_positions=None) -> list[np.ndarray]:  # B x (N_b,)
        """``labels`` of several scenes in one discovery (topology.batch.discover_batch: one grid, one pass)."""
        from topocut.topology.batch import discover_batch

        res = discover_batch([np.asarray(x) for x in xs], [np.asarray(d, bool) for d in damages], list(sweeps),
                             list(previous), cfg=self.topo_cfg, device=self.device, start_positions=start_positions)
        return [np.asarray(r.labels, np.int32) for r in res]

    def fragments(self, x, labels) -> list[np.ndarray]:
        return fragments(x, labels, self.min_fragment_points)  # the engine's rule: -1 is no piece

    def reward(self, x, labels) -> tuple[float, bool]:
        from topocut.reward import spectral_reward

        res = spectral_reward(self.fragments(x, labels), list(self.goal.fragments), self.reward_cfg,
                              offcuts=list(getattr(self.goal, "offcuts", None) or []))
        return float(res.total), self.success(res)

    def success(self, result) -> bool:
        """A RewardResult's success: ``success_fn``'s, else the total at ``success_threshold`` (None: never)."""
        if self.success_fn is not None:
            return bool(self.success_fn(result))
        return bool(self.success_threshold is not None and float(result.total) >= self.success_threshold)

    def results(self, xs, labels) -> list:  # K RewardResults of K scenes in one batched reward call
        from topocut.reward import spectral_rewards

        sets = [self.fragments(x, lab) for x, lab in zip(xs, labels)]
        off = list(getattr(self.goal, "offcuts", None) or [])
        return spectral_rewards(sets, list(self.goal.fragments), self.reward_cfg, off)

    def rewards(self, xs, labels) -> np.ndarray:  # K, the rewards of K scenes in one batched reward call
        return np.array([r.total for r in self.results(xs, labels)])


def takes_start_positions(fn) -> bool:
    """Whether a discovery callable takes ``start_positions=`` (the built-in ones do; a replacement may not)."""
    try:
        return "start_positions" in inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False


def piece_agreement(labels, piece, min_points: int = 4) -> tuple[int, float]:
    """(the simulator's pieces of >= min_points particles, the lowest IoU of a discovered piece (label >= 0, >=
    min_points particles) with the simulator piece it overlaps most): does discovery see what the simulator
    separated?"""
    labels, piece = np.asarray(labels, np.int64), np.asarray(piece, np.int64)
    n_sim = int((np.bincount(piece) >= min_points).sum()) if len(piece) else 0
    ok = labels >= 0
    if not ok.any():
        return n_sim, float("nan")
    # the overlap of every (label, piece) pair: one bincount table over label * P + piece (np.unique over the stacked
    # pairs, axis=1, sorted them as structured rows: ~40 ms a 128^3 cut); only sizes and overlaps matter, so sparse
    # cluster ids are numbered 0.. first (in their order: ties still go to the lowest piece)
    lab, P = labels[ok], int(piece.max()) + 1
    if (int(lab.max()) + 1) * P > 1 << 22:
        lab = np.unique(lab, return_inverse=True)[1].reshape(-1)
    inter = np.bincount(lab * P + piece[ok], minlength=(int(lab.max()) + 1) * P).reshape(-1, P)  # labels, P
    size_l, size_p, worst = inter.sum(1), np.bincount(piece), 1.0
    for i in np.flatnonzero(size_l >= min_points):
        j = int(np.argmax(inter[i]))  # the piece it overlaps most (the lowest of equals)
        worst = min(worst, float(inter[i, j] / (size_l[i] + size_p[j] - inter[i, j])))
    return n_sim, worst

"""The one episode loop: demonstrations, evaluation, teleop replay and renders all run ``run_episodes``.

An episode resets a scene (object, pose, sampling seed), builds its task's goal, then repeats up to
``max_cuts`` times: observe (``observe_fn``), ask the policy for a cut, execute it (``executed_action``: one
rule for every caller), push if the task pushes, re-discover the pieces with the previous labels (cluster ids
carried over), score them against the goal (spectral reward, the task's success), and perform the goal's
scripted turn after the k-th cut where the task has one (``Goal.steps``: stick, dice).  It ends after
``max_cuts`` cuts, when the policy returns None, on success (``stop_on_success``), or when its scene diverges
(status ``failed``) or its policy / scoring raises (status ``error``); the steps before stay recorded.

Batching.  B = env.batch_size episodes advance together, scene b holding episode b with its own object, pose,
goal and policy state (``CuttingEnv.reset_scenes`` pads scenes to the largest particle count with particles
no phase visits), so a cut of all B is one launch sequence and its scores one reward call.  Scene b evolves as
it would alone (tests/test_sim_mixed_batch.py); a scene whose episode has ended is frozen (a None action); one
that diverges is frozen and its episode marked failed while the others go on (``CuttingEnv.freeze_diverged``).
Each episode gets its own copy of the policy (torch modules shared), reset with the episode's seed, so an
episode's actions do not depend on its batch-mates.  A policy that plans with the simulator itself
(``uses_simulator``: MPPI, whose rollouts are the batch's scenes) runs its episodes one at a time, the episode
in every scene and the rollouts restoring them (``obs["sim_state"]``).  An env of batch size 1 or one without
``reset_scenes`` (test doubles) runs one episode at a time the same way.
"""
from __future__ import annotations

import copy
import time
import warnings
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from topocut.policies.base import reset_policy
from topocut.sim.action import POSE_FEATURE_DIM, executed_action
from topocut.tasks.base import turns_after

HISTORY_LEN = 3


@dataclass
class Episode:
    """What one episode needs: the scene and the task (its ``TaskConfig``: goal, success, push).
    ``object`` None: the env already holds the episode's scene (a caller that reset it), so it is not reset."""
    object: str | None
    pose: object  # topocut.sim.objects.ObjectPose
    seed: int | None  # particle sampling, the observation noise, the policy's sampler (None: no re-seeding)
    task: object  # TaskConfig (name, push, ...)
    key: str = ""
    goal: object = None  # built by the goal function when None


@dataclass
class EpisodeLog:
    """What happened in one episode (evaluation's EpisodeResult and the demonstrations' records come from it)."""
    status: str = "ok"  # ok | failed (simulation diverged, turn refused) | error (policy or scoring raised)
    error: str | None = None
    initial_reward: float = 0.0
    rewards: list[float] = field(default_factory=list)  # after each executed cut
    cut_counts: list[int] = field(default_factory=list)
    successes: list[bool] = field(default_factory=list)
    turns: list[int] = field(default_factory=list)  # the cuts after which the goal's turn was performed
    num_pieces: list[int] = field(default_factory=list)
    # after each cut: the simulator's own pieces (its bond components, CuttingEnv.piece, >= 4 particles) and the
    # worst IoU of a discovered piece with its best simulator piece (piece_agreement); empty for an env without
    sim_pieces: list[int] = field(default_factory=list)
    piece_iou: list[float] = field(default_factory=list)
    actions: list[list[float]] = field(default_factory=list)  # executed [x, y, yaw, tilt]
    act_time_s: list[float] = field(default_factory=list)
    time_s: float = 0.0
    steps: list[dict] = field(default_factory=list)  # dataset records (record=True)
    labels: np.ndarray | None = None  # the final particle labels
    # (x, labels, what, knife) after reset, each cut, each turn (frames=True); knife: the cut's executed KnifeAction
    frames: list = field(default_factory=list)
    # per entry of ``frames``: the topocut.sim.cut_frames.CutFrames during the cut that led to it (cut_frames=F > 0: F of
    # them; [] after reset and turns, and for every frame with cut_frames=0)
    motion: list = field(default_factory=list)
    goal: object = None


@dataclass
class Score:
    total: float  # the reward
    cut_count: int  # N_C
    success: bool  # the task's success
    pieces: int  # fragments scored


@dataclass
class Scoring:
    """How a state is labelled and scored; each part replaceable (test doubles, other backends)."""
    goal_fn: Callable  # (task_cfg, object, pose, spacing, seed) -> Goal: seed, the scene's particle sampling
    discover_fn: Callable  # (x (N,3), damage (N,), sweeps, previous_labels) -> labels (N,)
    score_fn: Callable  # (xs, labels, goals, task_cfgs) -> [Score]: all scenes of a step in one call


def fragment_scoring(goal_fn: Callable, discover_fn: Callable, rewards_fn: Callable, success_fn: Callable,
                     min_fragment_points: int = 4) -> Scoring:
    """Scoring from pieces: ``rewards_fn(fragment sets, goal fragment sets, planned offcut sets) -> results``
    (.total, .cut_count) of every scene in one call, ``success_fn(result, task_cfg) -> bool``."""

    def score_fn(xs, labels, goals, task_cfgs):
        sets = [fragments(x, lab, min_fragment_points) for x, lab in zip(xs, labels)]
        res = rewards_fn(sets, [[np.asarray(f) for f in g.fragments] for g in goals],
                         [[np.asarray(f) for f in getattr(g, "offcuts", None) or []] for g in goals]) if sets else []
        return [Score(float(r.total), int(r.cut_count), bool(success_fn(r, t)), len(f))
                for r, t, f in zip(res, task_cfgs, sets)]

    return Scoring(goal_fn, discover_fn, score_fn)


def default_scoring(reward_cfg=None, topo_cfg=None, device: str = "cpu", board_z: float = 0.05,
                    min_fragment_points: int = 4) -> Scoring:
    """Topology discovery (topocut.topology.discover on ``device``), the spectral reward of every scene against
    its own goal in one call (descriptors batched across scenes), the task registry's goal and success."""
    from topocut.reward import spectral_rewards
    from topocut.tasks import get_task
    from topocut.topology import discover

    def goal_fn(task_cfg, obj, pose, spacing, seed=0):  # the scene's own particles (its sampling seed), ideally cut
        return get_task(task_cfg.name).make_goal(task_cfg, obj, pose, spacing, board_z=board_z, seed=seed)

    def discover_fn(x, damage, sweeps, previous):
        return np.asarray(discover(x, np.asarray(damage, bool), sweeps, previous_labels=previous, cfg=topo_cfg,
                                   device=device).labels, np.int32)

    def rewards_fn(sets, goal_sets, offcut_sets=None):
        return spectral_rewards(sets, goal_sets, reward_cfg, offcut_sets)

    def success_fn(res, task_cfg):
        return bool(get_task(task_cfg.name).success(res, task_cfg))

    return fragment_scoring(goal_fn, discover_fn, rewards_fn, success_fn, min_fragment_points)


def fragments(x, labels, min_points: int) -> list[np.ndarray]:
    """The pieces (n_i,3) of labelled particles; -1 (unassigned) is no piece, pieces below min_points dropped."""
    x, labels = np.asarray(x), np.asarray(labels)
    ids = [c for c in np.unique(labels) if c >= 0]
    return [f for f in (x[labels == c] for c in ids) if len(f) >= min_points]


def piece_agreement(labels, piece, min_points: int = 4) -> tuple[int, float]:
    """(the simulator's pieces of >= min_points particles, the lowest IoU of a discovered piece (label >= 0, >=
    min_points particles) with the simulator piece it overlaps most): does discovery see what the simulator
    separated?"""
    labels, piece = np.asarray(labels, np.int64), np.asarray(piece, np.int64)
    n_sim = int((np.bincount(piece) >= min_points).sum()) if len(piece) else 0
    ok = labels >= 0
    if not ok.any():
        return n_sim, float("nan")
    pairs, inter = np.unique(np.stack([labels[ok], piece[ok]]), axis=1, return_counts=True)
    size_l = np.bincount(labels[ok])
    size_p = np.bincount(piece)
    worst = 1.0
    for lab in np.unique(pairs[0]):
        if size_l[lab] < min_points:
            continue
        m = pairs[0] == lab
        j = np.argmax(inter[m])
        i = inter[m][j]
        worst = min(worst, float(i / (size_l[lab] + size_p[pairs[1][m][j]] - i)))
    return n_sim, worst


def new_history() -> deque:
    """The pose features (3,7) of the last cuts, oldest first: zeros before the first cut."""
    return deque([np.zeros(POSE_FEATURE_DIM, np.float32)] * HISTORY_LEN, maxlen=HISTORY_LEN)


def step_seed(episode_seed: int, cut: int) -> int:
    """Seed of the observation before cut ``cut`` (0-based) of an episode."""
    return (int(episode_seed) * 7919 + int(cut) + 1) % (2**31 - 1)


def make_record(x_t, f_t, x_t1, f_t1, action, history, reward: float, success: bool, board_z: float) -> dict:
    """One dataset record (EpisodeWriter input); ``action`` as executed, history the 3 previous pose features."""
    action = executed_action(action)
    return {"x_t": np.asarray(x_t, np.float32).copy(), "f_t": np.asarray(f_t, np.int32).copy(),
            "x_t1": np.asarray(x_t1, np.float32).copy(), "f_t1": np.asarray(f_t1, np.int32).copy(),
            "action": action.to_vector(), "pose": action.to_matrix(board_z).astype(np.float32),
            "history": np.stack(list(history)).astype(np.float32), "reward": float(reward),
            "success": bool(success)}


def _slot_policy(policy):
    """A copy of ``policy`` for one slot of a batch: its own episode state, the torch modules shared."""
    try:
        import torch

        memo = {}

        def share(obj, depth):
            if isinstance(obj, torch.nn.Module):
                memo[id(obj)] = obj
            elif depth < 3 and hasattr(obj, "__dict__"):
                for v in vars(obj).values():
                    share(v, depth + 1)

        share(policy, 0)
        return copy.deepcopy(policy, memo)
    except Exception:  # noqa: BLE001 - an uncopyable attribute (a generator, a handle): a shallow copy
        return copy.copy(policy)


def env_board_z(env, default: float = 0.05) -> float:
    """The board's top face of ``env`` (its cfg.board_z; ``default`` for a test double without one)."""
    return float(getattr(getattr(env, "cfg", None), "board_z", default))


def _spacing(env) -> float:
    cfg = getattr(env, "cfg", None)
    for name in ("spacing", "particle_spacing"):
        if hasattr(cfg, name):
            return float(getattr(cfg, name))
    raise ValueError("run_episodes: env.cfg has no particle spacing (spacing/particle_spacing); pass spacing=")


def diverged_type() -> type:
    """topocut.sim.SimulationDiverged (imported late: this module stays free of Taichi)."""
    from topocut.planning.rollout import simulation_diverged_error

    return simulation_diverged_error()


def _scene(st, b):
    if hasattr(st, "scene"):
        return st.scene(b)
    return np.asarray(st.x[b]), np.asarray(st.damage[b])


class EpisodeBatch:
    """Up to B episodes in the B scenes of one simulator batch, advanced one cut at a time: the engine's state
    (what ``run_episodes`` and the gymnasium vector env, topocut.envs, both drive).

    ``start(episodes)`` loads them (scene b holds episode b; ``alone``: one episode in every scene), builds the
    goals, labels and scores the uncut scenes; ``observations(observe_fn, sim_state)`` gives each live episode
    its policy observation; ``step(actions)`` executes one cut per scene (None: an ended episode's scene idles),
    the push where the episode's task pushes, discovery, the batched score, and the goals' turns.  ``logs[b]``
    holds what episode b did; ``live[b]`` whether it goes on.
    """

    def __init__(self, env, scoring: Scoring, max_cuts: int = 5, turns: bool = True, spacing: float | None = None,
                 record: bool = False, frames: bool = False, stop_on_success: bool = False,
                 progress: Callable | None = None, cut_frames: int = 0):
        self.env, self.sc, self.max_cuts, self.turns = env, scoring, int(max_cuts), bool(turns)
        self.spacing, self.record, self.frames, self.stop_on_success = spacing, record, frames, stop_on_success
        self.progress = progress
        # frames during each cut: CuttingEnv.cut's snapshots (a host sync each), so only for renders (frames=True)
        self.cut_frames = int(cut_frames) if frames else 0
        self.B = int(getattr(env, "batch_size", 1) or 1)
        self.board_z = env_board_z(env)
        self.Diverged = diverged_type()

    # -- episode bookkeeping ---------------------------------------------------------------------------
    def _keep(self, b: int, what: str, knife=None, motion=()) -> None:
        if self.frames:
            self.logs[b].frames.append((self.xs[b].copy(), np.asarray(self.labels[b]).copy(), what, knife))
            self.logs[b].motion.append(list(motion))

    def end(self, b: int, status: str, error: str) -> None:
        self.live[b] = False
        self.logs[b].status, self.logs[b].error = status, error
        if "scoring" in error or "labelling" in error:  # our side failed, not the policy: say so at once
            warnings.warn(f"{self.eps[b].key or self.eps[b].object}: {error}", stacklevel=3)

    def start(self, episodes: list[Episode], alone: bool = False, initial_reward: bool = True) -> list[EpisodeLog]:
        env, sc, B, n = self.env, self.sc, self.B, len(episodes)
        if not alone and n > B:
            raise ValueError(f"EpisodeBatch.start: {n} episodes for batch_size={B}")
        self.t0, self.eps, self.alone, self.n, self.k = time.perf_counter(), list(episodes), alone, n, 0
        self.logs = [EpisodeLog() for _ in episodes]
        if alone:  # the episode in every scene (a planner's rollouts restore them from obs["sim_state"])
            if episodes[0].object is not None:
                env.reset(episodes[0].object, episodes[0].pose, seed=episodes[0].seed)
        else:  # scene b holds episode b; the scenes past them repeat the last episode and stay frozen
            pad = self.eps + [self.eps[-1]] * (B - n)
            env.reset_scenes([e.object for e in pad], [e.pose for e in pad], [e.seed for e in pad])
            env.freeze_diverged = True
        spacing = self.spacing
        if spacing is None and any(e.goal is None for e in episodes):
            spacing = _spacing(env)
        self.goals = [e.goal if e.goal is not None else sc.goal_fn(e.task, e.object, e.pose, spacing, e.seed or 0)
                      for e in episodes]
        self.tasks = [e.task for e in episodes]
        st = env.state()
        self.xs = [np.asarray(_scene(st, b)[0]) for b in range(n)]
        self.labels = [sc.discover_fn(self.xs[b], _scene(st, b)[1], None, None) for b in range(n)]
        init = (sc.score_fn(self.xs, self.labels, self.goals, self.tasks) if initial_reward
                else [Score(float("nan"), 0, False, 0)] * n)
        self.live = [True] * n
        self.hist = [new_history() for _ in episodes]
        for b in range(n):
            self.logs[b].initial_reward, self.logs[b].goal = float(init[b].total), self.goals[b]
            self._keep(b, "reset")
        self.initial = init
        return self.logs

    def observation(self, b: int, observe_fn: Callable | None = None) -> dict:
        """Episode b's policy observation (topocut.policies.base.OBS_KEYS, + particle_labels, cuts_done)."""
        observe_fn = observe_fn or (lambda x, labels, seed: (np.asarray(x, np.float32), np.asarray(labels, np.int32)))
        points, obs_labels = observe_fn(self.xs[b], self.labels[b], step_seed(self.eps[b].seed or 0, self.k))
        return {"points": points, "labels": obs_labels, "history": np.stack(list(self.hist[b])),  # 3,7 oldest first
                "goal": np.asarray(self.goals[b].points, np.float32),
                "goal_labels": np.asarray(self.goals[b].labels, np.int32),
                "particle_labels": self.labels[b], "cuts_done": self.k}

    # -- one cut of every live episode -----------------------------------------------------------------
    def step(self, actions: list) -> list[Score | None]:
        """Execute ``actions`` (per episode: a KnifeAction, run through ``executed_action``, or None: no cut) and
        score them; returns each episode's Score (None where it did not cut or failed)."""
        env, B, n, k = self.env, self.B, self.n, self.k
        acts = [None if a is None or not self.live[b] else executed_action(a) for b, a in enumerate(actions)]
        moving = [b for b in range(n) if acts[b] is not None]
        out: list[Score | None] = [None] * n
        if not moving:
            return out
        record = {}  # CuttingEnv.cut's snapshot interval, only when the frames during the cut are kept
        if self.cut_frames:
            from topocut.sim.cut_frames import record_interval

            record = {"record_every": record_interval(env, [self.xs[b][:, 2].max() for b in moving],
                                                      [acts[b] for b in moving], self.cut_frames)}
            st0 = env.state()
            damage_before = [_scene(st0, b)[1].copy() for b in range(n)]
        try:
            if self.alone:
                info = env.cut([acts[0]] * B if B > 1 else acts[0], **record)
                if getattr(self.tasks[0], "push", False):
                    env.push()
            else:
                info = env.cut(acts + [None] * (B - n), **record)
                pushed = np.array([acts[b] is not None and bool(getattr(self.tasks[b], "push", False))
                                   for b in range(n)] + [False] * (B - n))
                if pushed.any():
                    env.push(scenes=pushed)
        except self.Diverged as e:  # one episode (alone) or a batch not freezing its diverged scenes
            for b in moving:
                self.end(b, "failed", f"cut {k + 1}: {type(e).__name__}: {e}")
            self.k += 1
            return out
        dead = np.asarray(getattr(env, "dead", np.zeros(B, bool)))
        st = env.state()
        scored = []
        for b in moving:
            if dead[b]:
                self.end(b, "failed", f"cut {k + 1}: SimulationDiverged: scene {b} diverged (a NaN/Inf position "
                                      f"or J = det F out of bounds); the other scenes went on")
                continue
            x1, d1 = _scene(st, b)
            try:
                lab1 = self.sc.discover_fn(np.asarray(x1), d1, st.sweeps[b], self.labels[b])
            except Exception as e:  # noqa: BLE001 - recorded in the episode's log
                self.end(b, "error", f"scoring cut {k + 1}: {type(e).__name__}: {e}")
                continue
            scored.append((b, np.asarray(x1), lab1))
        try:
            results = self.sc.score_fn([x for _, x, _ in scored], [lab for _, _, lab in scored],
                                       [self.goals[b] for b, _, _ in scored],
                                       [self.tasks[b] for b, _, _ in scored]) if scored else []
        except Exception as e:  # noqa: BLE001 - recorded in the episodes' logs
            for b, _, _ in scored:
                self.end(b, "error", f"scoring cut {k + 1}: {type(e).__name__}: {e}")
            scored, results = [], []
        for (b, x1, lab1), res in zip(scored, results):
            log, a = self.logs[b], acts[b]
            if self.record:
                log.steps.append(make_record(self.xs[b], self.labels[b], x1, lab1, a, self.hist[b], res.total,
                                             res.success, self.board_z))
            log.rewards.append(res.total)
            log.cut_counts.append(res.cut_count)
            log.successes.append(res.success)
            log.num_pieces.append(res.pieces)
            sim_piece = getattr(env, "piece", None)
            if isinstance(sim_piece, np.ndarray) and sim_piece.ndim == 2 and sim_piece.shape[1] >= len(lab1):
                n_sim, iou = piece_agreement(lab1, sim_piece[0 if self.alone else b, :len(lab1)])
                log.sim_pieces.append(n_sim)
                log.piece_iou.append(iou)
            log.actions.append([float(v) for v in a.to_vector()])
            self.hist[b].append(a.pose_feature(self.board_z))
            motion = []
            if record:
                from topocut.sim.cut_frames import pick_cut_frames

                scene = 0 if self.alone else b
                budget = (info.substeps if info.substeps_per_scene is None
                          else int(info.substeps_per_scene[scene]))
                motion = pick_cut_frames(info.snapshots, scene, len(self.xs[b]), damage_before[b], budget,
                                         self.cut_frames, env.dt)
            self.xs[b], self.labels[b] = x1, lab1
            self._keep(b, f"cut {k + 1}: R={res.total:.2f}", knife=a, motion=motion)
            out[b] = res
            if self.progress is not None:
                name = self.eps[b].key or self.eps[b].object or getattr(self.goals[b], "object", "") or f"episode {b}"
                self.progress(1, info=f"{name} cut {k + 1}: reward {res.total:.3f}")  # (MPPI's episodes: no key)
            if self.stop_on_success and res.success:
                self.live[b] = False
        self.k += 1
        for b in range(n):  # an episode that did not cut this step (its policy stopped) is over
            if acts[b] is None:
                self.live[b] = False
        if self.turns and self.k < self.max_cuts:
            todo = {b: turns_after(self.goals[b], self.k) for b in range(n) if self.live[b]}
            todo = {b: t for b, t in todo.items() if t}
            if todo:
                self._turn(todo)
        if self.k >= self.max_cuts:
            self.live = [False] * n
        return out

    def _turn(self, todo: dict) -> None:
        """The goals' turns after cut k in the scenes of ``todo`` ({scene: [Turn, ...]}), then discovery with the
        previous labels and no sweep (CuttingEnv.turn clears them), so the cluster ids are kept."""
        from topocut.sim.primitives import TurnRefused

        env, B, k = self.env, self.B, self.k
        depth = max(len(t) for t in todo.values())
        refused = [None] * B  # per scene, why a turn of its was refused (a batch's scenes are refused one by one)
        try:
            for i in range(depth):
                if self.alone:
                    env.turn(todo[0][i])
                else:
                    env.turn([todo[b][i] if b in todo and i < len(todo[b]) and not refused[b] else None
                              for b in range(B)])
                    refused = [r or t for r, t in zip(refused, env.turn_refused)]
        except (self.Diverged, TurnRefused) as e:
            for b in todo:
                self.end(b, "failed", f"turn after cut {k}: {type(e).__name__}: {e}")
            return
        dead = np.asarray(getattr(env, "dead", np.zeros(B, bool)))
        st = env.state()
        for b in todo:
            if dead[b] or refused[b]:
                self.end(b, "failed", f"turn after cut {k}: " + (f"TurnRefused: {refused[b]}" if refused[b]
                                                                 else f"scene {b} diverged"))
                continue
            self.logs[b].turns.append(k)
            x1, d1 = _scene(st, b)
            try:
                self.labels[b] = self.sc.discover_fn(np.asarray(x1), d1, st.sweeps[b], self.labels[b])
            except Exception as e:  # noqa: BLE001
                self.end(b, "error", f"labelling after turn {len(self.logs[b].turns)}: {type(e).__name__}: {e}")
                continue
            self.xs[b] = np.asarray(x1)
            self._keep(b, f"turn after cut {k}")

    def finish(self) -> list[EpisodeLog]:
        for b in range(self.n):
            self.logs[b].labels = self.labels[b]
            self.logs[b].time_s = time.perf_counter() - self.t0
        return self.logs


def run_episodes(env, episodes: list[Episode], policy, scoring: Scoring, max_cuts: int = 5,
                 observe_fn: Callable | None = None, stop_on_success: bool = False, record: bool = False,
                 turns: bool = True, spacing: float | None = None, on_done: Callable | None = None,
                 progress: Callable | None = None, initial_reward: bool = True,
                 batch: bool = True, frames: bool = False, cut_frames: int = 0) -> list[EpisodeLog]:
    """Run ``episodes`` with ``policy`` (the Policy protocol), env.batch_size at a time (module docstring).

    ``observe_fn(x, labels, seed) -> (points, labels)`` is what the policy sees (default: the particles).
    ``record``: keep dataset records (topocut.data) in ``EpisodeLog.steps``.  ``on_done(i, log)`` is called
    as episode i finishes (evaluation writes its JSON there, so a killed run resumes); ``progress(n, info)``
    after every executed cut of every episode; ``initial_reward``: score the uncut scene too; ``batch`` False:
    one episode at a time (in every scene); ``frames``: keep (x, labels, what, knife) of every state (renders),
    and with ``cut_frames`` F > 0 also F frames during each cut (``EpisodeLog.motion``, topocut.sim.cut_frames: the env's
    ``cut(..., record_every=k)`` snapshots, asked for only then).  Returns one EpisodeLog per episode, in order.
    """
    B = int(getattr(env, "batch_size", 1) or 1)
    uses_sim = bool(getattr(policy, "uses_simulator", False))
    alone = (not batch or B == 1 or uses_sim or not hasattr(env, "reset_scenes")
             or any(e.object is None for e in episodes))
    size = 1 if alone else B
    engine = EpisodeBatch(env, scoring, max_cuts, turns, spacing, record, frames, stop_on_success, progress,
                          cut_frames)
    logs: list[EpisodeLog] = []
    for c0 in range(0, len(episodes), size):
        chunk = episodes[c0:c0 + size]
        pols = [policy] if alone else [_slot_policy(policy) for _ in chunk]
        engine.start(chunk, alone, initial_reward)
        for b, e in enumerate(chunk):
            reset_policy(pols[b], engine.goals[b], seed=e.seed)
        batched = not alone and callable(getattr(type(policy), "act_batch", None))
        while any(engine.live):
            live = [b for b in range(len(chunk)) if engine.live[b]]
            obs = {b: engine.observation(b, observe_fn) for b in live}
            if getattr(policy, "privileged", False):  # the oracle reads the scene itself (planning/oracle.py)
                for b in live:
                    obs[b]["particles"] = engine.xs[b]  # N,3
            saved = None
            if alone and hasattr(env, "get_state"):  # one episode in every scene: a planner (MPPI) may roll
                obs[0]["sim_state"] = env.get_state(0)  # out from its state (batched episodes: no planner)
                saved = env.save_scene(0, "episode") if hasattr(env, "save_scene") else None
                if saved is not None:  # the same state kept on the device: rollouts in this env start from it
                    obs[0]["sim_saved"] = saved
            acts = _act(pols, obs, batched, engine)
            if "sim_state" in obs.get(0, {}) and hasattr(env, "set_state"):  # the rollouts moved the scenes:
                if saved is None or not env.restore_scene(saved):  # restore them (on the device where kept)
                    env.set_state(obs[0]["sim_state"], b=None)
            if not any(a is not None for a in acts):
                break
            engine.step(acts)
        for j, log in enumerate(engine.finish()):
            logs.append(log)
            if on_done is not None:
                on_done(c0 + j, log)
    return logs


def _act(pols: list, obs: dict, batched: bool, engine: EpisodeBatch) -> list:
    """Each live episode's action: one ``act_batch`` call for all of them where the policy class has one (the
    network runs once on the stacked batch; each episode draws from its own generator), else ``act`` each.
    A failing call fails only its episode: a batched call that raises is retried one episode at a time."""
    acts = [None] * len(pols)
    if batched and len(obs) > 1:
        live = list(obs)
        ta = time.perf_counter()
        try:
            out = type(pols[live[0]]).act_batch([pols[b] for b in live], [obs[b] for b in live])
        except Exception:  # noqa: BLE001 - find the episode that fails below
            out = None
        if out is not None:
            dt = (time.perf_counter() - ta) / len(live)  # the batch's time, shared
            for b, a in zip(live, out):
                acts[b] = a
                engine.logs[b].act_time_s.append(dt)
            return acts
    for b, o in obs.items():
        ta = time.perf_counter()
        try:
            acts[b] = pols[b].act(o)
        except Exception as e:  # noqa: BLE001 - a broken policy fails its episode, not the run
            engine.end(b, "error", f"{type(e).__name__}: {e}")
            continue
        engine.logs[b].act_time_s.append(time.perf_counter() - ta)
    return acts

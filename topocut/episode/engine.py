"""The episode engine: ``EpisodeBatch``, up to B episodes advanced together one cut at a time.

An episode resets a scene (object, pose, sampling seed), builds its task's goal, then repeats up to
``max_cuts`` times: observe (``observe_fn``), ask the policy for a cut, execute it (``executed_action``: one
rule for every caller), re-discover the pieces with the previous labels (cluster ids carried over) where the
blade left them, push if the task pushes (the labels ride on the particles), score them against the goal (spectral reward, the task's success), and perform the goal's
scripted turn after the k-th cut where the task has one (``Goal.steps``: stick, dice).  It ends after
``max_cuts`` cuts, when the policy returns None, on success (``stop_on_success``), or when its scene diverges
(status ``failed``) or its policy / scoring raises (status ``error``); the steps before stay recorded.

Batching.  B = env.batch_size episodes advance together, scene b holding episode b with its own object, pose,
goal and policy state (``CuttingEnv.reset_scenes`` pads scenes to the largest particle count with particles
no phase visits), so a cut of all B is one launch sequence and its scores one reward call.  Scene b evolves as
it would alone (tests/test_sim_mixed_batch.py); a scene whose episode has ended is frozen (a None action); one
that diverges is frozen and its episode marked failed while the others go on (``CuttingEnv.freeze_diverged``).
"""
from __future__ import annotations

import inspect
import time
import warnings
from collections.abc import Callable
from types import SimpleNamespace

import numpy as np

from topocut.episode.records import HISTORY_LEN, Episode, EpisodeLog, Score, make_record, new_history
from topocut.episode.scene import env_board_z, env_spacing, scene_of, simulation_diverged_error
from topocut.episode.scoring import Scoring, piece_agreement, takes_start_positions
from topocut.episode.seeds import step_seed
from topocut.sim.action import executed_action
from topocut.tasks.base import turns_after


def reset_policy(policy, goal, seed: int | None = None) -> None:
    """``policy.reset(goal, seed=seed)``; policies written against the older ``reset(goal)`` get the goal only."""
    try:
        takes_seed = "seed" in inspect.signature(policy.reset).parameters
    except (TypeError, ValueError):  # a builtin or C-implemented reset
        takes_seed = False
    if takes_seed:
        policy.reset(goal, seed=seed)
    else:
        policy.reset(goal)


class EpisodeBatch:
    """Up to B episodes in the B scenes of one simulator batch, advanced one cut at a time: the engine's state
    (what ``run_episodes`` and the gymnasium vector env, topocut.envs, both drive).

    ``start(episodes)`` loads them (scene b holds episode b; ``alone``: one episode in every scene), builds the
    goals, labels and scores the uncut scenes; ``observations(live, observe_fn, points)`` gives each live episode
    its policy observation; ``step(actions)`` executes one cut per scene (None: an ended episode's scene idles),
    discovery, the push where the episode's task pushes, the batched score, and the goals' turns.  ``logs[b]``
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
        self.Diverged = simulation_diverged_error()
        self.starts = takes_start_positions(scoring.discover_fn)  # a replacement discovery may not take them

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

    def start(self, episodes: list[Episode], alone: bool = False, initial_reward: bool = True,
              history_len: int = HISTORY_LEN) -> list[EpisodeLog]:
        """Load ``episodes``; each policy observation holds the pose features of the last ``history_len`` cuts."""
        env, sc, B, n = self.env, self.sc, self.B, len(episodes)
        if not alone and n > B:
            raise ValueError(f"EpisodeBatch.start: {n} episodes for batch_size={B}")
        self.t0, self.eps, self.alone, self.n, self.k = time.perf_counter(), list(episodes), alone, n, 0
        self.logs = [EpisodeLog() for _ in episodes]
        if alone:  # the episode in every scene; it moves on in scene 0 (a planner's rollouts restore the rest)
            if episodes[0].object is not None:
                env.reset(episodes[0].object, episodes[0].pose, seed=episodes[0].seed)
        else:  # scene b holds episode b; the scenes past them repeat the last episode and stay frozen
            pad = self.eps + [self.eps[-1]] * (B - n)
            env.reset_scenes([e.object for e in pad], [e.pose for e in pad], [e.seed for e in pad])
            env.freeze_diverged = True
        spacing = self.spacing
        if spacing is None and any(e.goal is None for e in episodes):
            spacing = env_spacing(env)
        self.goals = [e.goal if e.goal is not None else sc.goal_fn(e.task, e.object, e.pose, spacing, e.seed or 0)
                      for e in episodes]
        self.tasks = [e.task for e in episodes]
        st = env.state()
        self.xs = [np.asarray(scene_of(st, b)[0]) for b in range(n)]
        self.labels = [sc.discover_fn(self.xs[b], scene_of(st, b)[1], None, None) for b in range(n)]
        init = (sc.score_fn(self.xs, self.labels, self.goals, self.tasks) if initial_reward
                else [Score(float("nan"), 0, False, 0)] * n)
        self.live = [True] * n
        self.hist = [new_history(history_len) for _ in episodes]
        for b in range(n):
            self.logs[b].initial_reward, self.logs[b].goal = float(init[b].total), self.goals[b]
            self._keep(b, "reset")
        self.initial = init
        return self.logs

    def observation(self, b: int, observe_fn: Callable | None = None, points: bool = True) -> dict:
        """Episode b's policy observation (topocut.policies.base.OBS_KEYS, + particle_labels, cuts_done);
        ``points`` False leaves out the observed ``points`` and ``labels`` (records.reads_points: a policy that
        declares it does not read them), whose FPS would cost more than the policy's act."""
        obs = {"history": np.stack(list(self.hist[b])),  # h,7 oldest first
               "goal": np.asarray(self.goals[b].points, np.float32),
               "goal_labels": np.asarray(self.goals[b].labels, np.int32),
               "particle_labels": self.labels[b], "cuts_done": self.k}
        if points:
            observe_fn = observe_fn or (lambda x, labels, seed: (np.asarray(x, np.float32),
                                                                 np.asarray(labels, np.int32)))
            obs["points"], obs["labels"] = observe_fn(self.xs[b], self.labels[b],
                                                      step_seed(self.eps[b].seed or 0, self.k))
        return obs

    def observations(self, live: list, observe_fn: Callable | None = None, points: bool = True) -> dict:
        """{b: observation(b)} of the live episodes; an ``observe_fn`` with a ``batch(xs, labels, seeds)`` method
        (the evaluation's: topocut.eval.protocol.make_observe_fn) observes them in one call, the same points."""
        batch = getattr(observe_fn, "batch", None) if points else None
        if batch is None or len(live) < 2:
            return {b: self.observation(b, observe_fn, points) for b in live}
        seen = batch([self.xs[b] for b in live], [self.labels[b] for b in live],
                     [step_seed(self.eps[b].seed or 0, self.k) for b in live])
        out = {}
        for b, (pts, lab) in zip(live, seen):
            out[b] = self.observation(b, points=False)
            out[b]["points"], out[b]["labels"] = pts, lab
        return out

    # -- one cut of every live episode -----------------------------------------------------------------
    def simulated(self, cut, actions: list):
        """``cut`` (a SimulatedCut: the state a planner's rollout made with episode 0's action) where ``step``
        may take it as that action's cut: one episode alone, its action the cut's to the bit, not pushed unless
        its task pushes (one not pushed yet is pushed by ``step``), no frames of the cut asked for; else None."""
        if cut is None or not self.alone or self.n != 1 or self.cut_frames or not self.live[0]:
            return None
        a = actions[0]
        if a is None or not cut.is_of(executed_action(a)) or cut.pushed and not getattr(self.tasks[0], "push", False):
            return None
        return cut

    def step(self, actions: list, simulated=None) -> list[Score | None]:
        """Execute ``actions`` (per episode: a KnifeAction, run through ``executed_action``, or None: no cut) and
        score them; returns each episode's Score (None where it did not cut or failed).  ``simulated``: the
        env already holds episode 0's cut (``simulated(...)``'s SimulatedCut, restored): it is not cut again."""
        acts = [None if a is None or not self.live[b] else executed_action(a) for b, a in enumerate(actions)]
        moving = [b for b in range(self.n) if acts[b] is not None]
        out: list[Score | None] = [None] * self.n
        if not moving:
            return out
        if simulated is not None:  # the env holds the state after the cut (and its push, or the push is to come)
            record, damage_before, info = {}, None, None
            before = None if simulated.before_push is None else SimpleNamespace(
                x=[simulated.before_push[0]], damage=[simulated.before_push[1]], sweeps=[simulated.before_push[2]])
            scored = self._push(acts, self._discover(moving, before), done=simulated.pushed)
        else:
            record, damage_before = self._record_args(acts, moving)
            done, info = self._cut(acts, moving, record)
            if not done:
                return out
            # discovery where the blade left the pieces (its sweep is where the kerf is), then the push moves them
            # and the labels ride on the particles (docs/topology.md#discovery-before-the-push)
            scored = self._push(acts, self._discover(moving))
        for (b, x1, lab1), res in zip(scored, self._score(scored)):
            self._log_cut(b, acts[b], x1, lab1, res, info, record, damage_before)
            out[b] = res
        self._after_cut(acts)
        return out

    def _record_args(self, acts: list, moving: list) -> tuple[dict, list | None]:
        """CuttingEnv.cut's snapshot interval (only when the frames during the cut are kept), the damage before."""
        if not self.cut_frames:
            return {}, None
        from topocut.sim.cut_frames import record_interval

        env = self.env
        record = {"record_every": record_interval(env, [self.xs[b][:, 2].max() for b in moving],
                                                  [acts[b] for b in moving], self.cut_frames)}
        st0 = env.state()
        return record, [scene_of(st0, b)[1].copy() for b in range(self.n)]

    def _cut(self, acts: list, moving: list, record: dict) -> tuple[bool, object]:
        """(whether the cut ran, CuttingEnv.cut's info); a divergence raised (one episode alone, or a batch not
        freezing its diverged scenes) fails the moving episodes."""
        env, B, n = self.env, self.B, self.n
        try:
            # scenes past the episodes idle (frozen: no phase touches them).  One episode alone (a planner's) runs
            # in scene 0 only: the other scenes are its planner's scratch, restored before its rollouts cut, so
            # cutting them too (as before 2026-11-30) cost a whole batch's cut for nothing
            info = env.cut(acts + [None] * (B - n) if B > 1 else acts[0], **record)  # B = 1: the action itself
        except self.Diverged as e:
            for b in moving:
                self.end(b, "failed", f"cut {self.k + 1}: {type(e).__name__}: {e}")
            self.k += 1
            return False, None
        return True, info

    def _push(self, acts: list, scored: list, done: bool = False) -> list[tuple]:
        """The pushes of the scenes whose task pushes, after their cut's discovery: ``scored`` with each pushed
        scene's positions and labels after the push (discovery again, as after a turn: the cut's labels as the
        previous ones and no sweep, so what the push moved apart is found apart and the kerf's particles keep
        the side the cut's discovery gave them); a divergence fails the pushed episodes.  ``done``: the env
        has pushed already (a SimulatedCut's state)."""
        env, B, n = self.env, self.B, self.n
        pushes = [acts[b] is not None and bool(getattr(self.tasks[b], "push", False)) for b in range(n)]
        if not any(pushes) or not scored:
            return scored
        try:
            if done:  # a SimulatedCut's state: pushed in its rollout
                pass
            elif B == 1:
                env.push()
            else:  # scenes past the episodes (one episode alone: all but scene 0) idle, as in the cut
                env.push(scenes=np.array(pushes + [False] * (B - n)))
        except self.Diverged as e:
            for b, _, _ in scored:
                self.end(b, "failed", f"push after cut {self.k + 1}: {type(e).__name__}: {e}")
            return []
        dead, st, out = self._dead(), env.state(), []
        for b, x1, lab1 in scored:
            found = self._labelled(st, b, dead, [], lab1, f"push after cut {self.k + 1}") if pushes[b] else (x1, lab1)
            if found is not None:
                out.append((b, *found))
        return out

    def _discover(self, moving: list, st=None) -> list[tuple]:
        """(b, x after the cut, its labels) of each moving scene that neither diverged nor failed discovery;
        ``st``: the state after the cut where the env holds a later one (default: the env's)."""
        dead, st, scored = self._dead(), self.env.state() if st is None else st, []
        for b in moving:
            start = {"start_positions": self.xs[b]} if self.starts else {}  # where the blade started
            found = self._labelled(st, b, dead, st.sweeps[b], self.labels[b], f"cut {self.k + 1}", **start)
            if found is not None:
                scored.append((b, *found))
        return scored

    def _dead(self) -> np.ndarray:
        return np.asarray(getattr(self.env, "dead", np.zeros(self.B, bool)))  # B, scenes that diverged

    def _labelled(self, st, b: int, dead, sweeps, previous, when: str, **start) -> tuple | None:
        """(x, labels) of scene b in ``st``, discovered with ``sweeps`` and ``previous``; None where its scene
        diverged (the episode fails) or discovery raised (it errs), ``when`` naming the moment."""
        if dead[b]:
            self.end(b, "failed", f"{when}: SimulationDiverged: scene {b} diverged (a NaN/Inf position or J = det F "
                                  f"out of bounds); the other scenes went on")
            return None
        x, d = scene_of(st, b)
        try:
            return np.asarray(x), self.sc.discover_fn(np.asarray(x), d, sweeps, previous, **start)
        except Exception as e:  # noqa: BLE001 - recorded in the episode's log
            self.end(b, "error", f"scoring {when}: {type(e).__name__}: {e}")
            return None

    def _score(self, scored: list) -> list[Score]:
        """The scores of ``scored`` in one call; a failing call fails their episodes (no scores)."""
        try:
            return self.sc.score_fn([x for _, x, _ in scored], [lab for _, _, lab in scored],
                                    [self.goals[b] for b, _, _ in scored],
                                    [self.tasks[b] for b, _, _ in scored]) if scored else []
        except Exception as e:  # noqa: BLE001 - recorded in the episodes' logs
            for b, _, _ in scored:
                self.end(b, "error", f"scoring cut {self.k + 1}: {type(e).__name__}: {e}")
            return []

    def _log_cut(self, b: int, a, x1, lab1, res: Score, info, record: dict, damage_before) -> None:
        """Episode b's cut ``a`` scored ``res``: its log, history, record, frames, and its state moves on."""
        env, k, log = self.env, self.k, self.logs[b]
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
        if self.progress is not None:
            name = self.eps[b].key or self.eps[b].object or getattr(self.goals[b], "object", "") or f"episode {b}"
            self.progress(1, info=f"{name} cut {k + 1}: reward {res.total:.3f}")  # (MPPI's episodes: no key)
        if self.stop_on_success and res.success:
            self.live[b] = False

    def _after_cut(self, acts: list) -> None:
        """The cut is done: episodes that did not cut are over, the goals' turns after it, the cut budget."""
        n = self.n
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

    def _turn(self, todo: dict) -> None:
        """The goals' turns after cut k in the scenes of ``todo`` ({scene: [Turn, ...]}), then discovery with the
        previous labels and no sweep (CuttingEnv.turn clears them), so the cluster ids are kept."""
        from topocut.sim.primitives import TurnRefused

        env, B, k = self.env, self.B, self.k
        depth = max(len(t) for t in todo.values())
        refused = [None] * B  # per scene, why a turn of its was refused (a batch's scenes are refused one by one)
        try:
            for i in range(depth):
                if B == 1:
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
            x1, d1 = scene_of(st, b)
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


"""Running episodes: ``run_episodes`` (the one episode loop: demonstrations, evaluation, teleop replay and
renders all run it) and ``run_episode`` (one demonstration, its dataset records).

Each episode gets its own copy of the policy (torch modules shared), reset with the episode's seed, so an
episode's actions do not depend on its batch-mates.  A policy that plans with the simulator itself
(``uses_simulator``: MPPI, whose rollouts are the batch's scenes) runs its episodes one at a time, the episode
in every scene and the rollouts restoring them (``obs["sim_state"]``); where its best rollout made the cut it
executes, the episode restores that rollout's state instead of cutting again (topocut.episode.simulated).  An env
of batch size 1 or one without ``reset_scenes`` (test doubles) runs one episode at a time the same way.  The policy's observations hold the
pose features of its last ``history_len`` cuts (its own ``history_len`` where it declares one, else
HISTORY_LEN).
"""
from __future__ import annotations

import copy
import time
from collections.abc import Callable

import numpy as np

from topocut.episode.engine import EpisodeBatch, reset_policy
from topocut.episode.records import Episode, EpisodeLog, history_len_of, reads_points
from topocut.episode.scene import topology_device
from topocut.episode.scoring import Scorer, Scoring, make_scoring


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
    sees = reads_points(policy)  # the scripted policies read no observed points: no FPS of every scene for them
    for c0 in range(0, len(episodes), size):
        chunk = episodes[c0:c0 + size]
        pols = [policy] if alone else [_slot_policy(policy) for _ in chunk]
        engine.start(chunk, alone, initial_reward, history_len=history_len_of(policy))
        for b, e in enumerate(chunk):
            reset_policy(pols[b], engine.goals[b], seed=e.seed)
        batched = not alone and callable(getattr(type(policy), "act_batch", None))
        while any(engine.live):
            live = [b for b in range(len(chunk)) if engine.live[b]]
            obs = engine.observations(live, observe_fn, points=sees)
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
            simulated = None
            if "sim_state" in obs.get(0, {}) and hasattr(env, "set_state"):  # the rollouts moved the scenes:
                # the state the executed cut makes where a rollout made it already (MPPI's best), else the start
                simulated = engine.simulated(getattr(pols[0], "simulated_cut", None), acts)
                if simulated is None or not env.restore_scene(simulated.after):
                    simulated = None
                    if saved is None or not env.restore_scene(saved):  # on the device where kept
                        env.set_state(obs[0]["sim_state"], b=None)
            if not any(a is not None for a in acts):
                break
            engine.step(acts, simulated)
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


def run_episode(env, goal, planner, reward_cfg=None, topo_cfg=None, max_cuts: int = 5, push: bool = False,
                observe_fn=None, progress=None, success_threshold: float | None = None,
                scorer: Scorer | None = None, seed: int | None = None, success_fn=None) -> tuple[list[dict], dict]:
    """Execute ``planner`` (Policy) in ``env`` (already reset) until success or max_cuts cuts: one demonstration
    through ``run_episodes`` (its rules for turns, failures and the executed action), keeping the dataset records.

    ``seed`` (the episode's) re-seeds a stochastic planner at its reset (reset_policy).
    ``success_fn(RewardResult) -> bool``: the task's success (Scorer); default the total at success_threshold.
    ``observe_fn(x, labels) -> (points, labels)``: what the planner sees (default the particles).
    Returns the step records and a summary; a SimulationDiverged (or a refused turn) marks the
    episode ``failed`` and keeps the steps recorded before it.
    """
    from types import SimpleNamespace

    scorer = scorer or Scorer(goal, reward_cfg, topo_cfg, success_threshold, device=topology_device(env),
                              success_fn=success_fn)
    observe = None if observe_fn is None else (lambda x, labels, seed: observe_fn(x, labels))
    episode = Episode(None, None, seed, SimpleNamespace(push=bool(push)), goal=goal)
    [log] = run_episodes(env, [episode], planner, make_scoring(scorer=scorer), max_cuts=max_cuts,
                         observe_fn=observe, stop_on_success=True, record=True, progress=progress,
                         initial_reward=False, batch=False)
    steps = log.steps
    summary = {"status": log.status, "num_cuts": len(steps), "turns": log.turns,
               "final_reward": steps[-1]["reward"] if steps else float("nan"),
               "success": bool(steps and steps[-1]["success"]),
               "rewards": [st["reward"] for st in steps], "actions": [st["action"].tolist() for st in steps],
               "num_clusters": int(len([c for c in np.unique(log.labels) if c >= 0])), "time_s": log.time_s}
    if log.error:
        summary["error"] = log.error
    return steps, summary

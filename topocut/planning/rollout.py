"""Simulator rollouts for MPPI and the episode runner that turns a policy into dataset records.

Both share ``Scorer``: topology discovery after every cut (consistent cluster
ids carried from the previous labels) and the spectral reward of the
resulting fragments against the goal's pieces.
"""
from __future__ import annotations

import dataclasses
import time
from collections import deque
from collections.abc import Mapping

import numpy as np

from topocut.policies.base import reset_policy
from topocut.sim.action import POSE_FEATURE_DIM, KnifeAction, cut_mask

HISTORY_LEN = 3


class _NoSimulator(Exception):
    """Stands in for SimulationDiverged when topocut.sim.env cannot be imported (so nothing raises it)."""


def simulation_diverged_error() -> type:
    """topocut.sim.SimulationDiverged (imported late so that this module stays free of Taichi)."""
    try:
        from topocut.sim import SimulationDiverged
    except ImportError:
        try:
            from topocut.sim.env import SimulationDiverged
        except ImportError:
            return _NoSimulator
    return SimulationDiverged


class Scorer:
    """Labels (topology discovery) and reward/success of a particle state against one goal."""

    def __init__(self, goal, reward_cfg=None, topo_cfg=None, success_threshold: float | None = None,
                 min_fragment_points: int = 4, device: str = "cpu"):
        self.goal, self.reward_cfg, self.topo_cfg = goal, reward_cfg, topo_cfg
        self.success_threshold, self.min_fragment_points, self.device = success_threshold, min_fragment_points, device

    def labels(self, x, damage, sweeps, previous=None) -> np.ndarray:  # N,
        from topocut.topology import discover

        res = discover(np.asarray(x), np.asarray(damage, bool), sweeps, previous_labels=previous,
                       cfg=self.topo_cfg, device=self.device)
        return np.asarray(res.labels, np.int32)

    def fragments(self, x, labels) -> list[np.ndarray]:
        x, labels = np.asarray(x), np.asarray(labels)
        ids = [c for c in np.unique(labels) if c >= 0]  # -1: unassigned particles belong to no piece
        frags = [x[labels == c] for c in ids]
        return [f for f in frags if len(f) >= self.min_fragment_points]

    def reward(self, x, labels) -> tuple[float, bool]:
        from topocut.reward import spectral_reward

        res = spectral_reward(self.fragments(x, labels), list(self.goal.fragments), self.reward_cfg)
        total = float(res.total)
        ok = self.success_threshold is not None and total >= self.success_threshold
        return total, bool(ok)

    def rewards(self, xs, labels) -> np.ndarray:  # K, the rewards of K scenes in one batched reward call
        from topocut.reward import spectral_rewards

        sets = [self.fragments(x, lab) for x, lab in zip(xs, labels)]
        return np.array([r.total for r in spectral_rewards(sets, list(self.goal.fragments), self.reward_cfg)])


def topology_device(env) -> str:
    """Discovery runs where the simulator runs: its particles are already on that device's side."""
    return "cuda" if getattr(getattr(env, "cfg", None), "arch", "cpu") == "cuda" else "cpu"


def quantize_action(action: KnifeAction) -> KnifeAction:
    """The canonical action that its own float32 vector (``to_vector``: what MPPI's rollouts evaluate and a
    record stores) maps back to exactly, so that what runs, what is stored and its pose all agree.

    Rounding to float32 can move a yaw across the canonical range's end: float32(pi/2) > pi/2 wraps to
    about -pi/2 with the normal reversed (the cut mask inverted), so the vector is re-read until it is
    stable (at most twice).  z_start and depth, which the vector does not hold, are kept.
    """
    v = action.to_vector()
    for _ in range(4):
        quantized = KnifeAction.from_vector(v)
        w = quantized.to_vector()
        if np.array_equal(w, v):
            break
        v = w
    return dataclasses.replace(quantized, z_start=action.z_start, depth=action.depth)


def _as_actions(vectors: np.ndarray) -> list[KnifeAction]:
    return [quantize_action(KnifeAction.from_vector(v)) for v in vectors]


def make_sim_rollout(env, state_dict: dict, goal, reward_cfg=None, topo_cfg=None, board_z: float = 0.05,
                     labels=None, push: bool = False, scorer: Scorer | None = None):
    """A batched MPPI cost: sequences (K,H,4) -> -(spectral reward after executing them) (K,).

    Every chunk of env.batch_size sequences starts from ``state_dict`` (one
    scene, env.get_state(0)); a chunk that diverges costs +inf (weight 0).
    """
    scorer = scorer or Scorer(goal, reward_cfg, topo_cfg, device=topology_device(env))
    B = int(getattr(env, "batch_size", 1))
    Diverged = simulation_diverged_error()
    labels0 = None if labels is None else np.asarray(labels, np.int32)

    def rollout(seqs: np.ndarray) -> np.ndarray:
        seqs = np.asarray(seqs, np.float64)  # K,H,4
        K, H = seqs.shape[:2]
        costs = np.empty(K)
        for c0 in range(0, K, B):
            chunk = seqs[c0:c0 + B]
            n = len(chunk)
            if n < B:  # pad the last chunk by repeating its final sequence; padded scenes are ignored
                chunk = np.concatenate([chunk, np.repeat(chunk[-1:], B - n, axis=0)])
            env.set_state(state_dict, b=None)
            x0 = np.asarray(env.state().x[0])  # N,3 (the restored state; no assumption on the dict's keys)
            lab0 = np.zeros(len(x0), np.int32) if labels0 is None else labels0
            labs = [lab0.copy() for _ in range(n)]
            xs = [x0] * n
            try:
                for h in range(H):
                    acts = _as_actions(chunk[:, h])
                    env.cut(acts if B > 1 else acts[0])
                    if push:
                        env.push()
                    st = env.state()
                    for b in range(n):
                        # a plane that misses every particle cannot change the topology: skip discovery
                        m = cut_mask(xs[b], acts[b], board_z)
                        if 0 < m.sum() < len(m):
                            labs[b] = scorer.labels(st.x[b], st.damage[b], st.sweeps[b], labs[b])
                        xs[b] = np.asarray(st.x[b])
            except Diverged:
                costs[c0:c0 + n] = np.inf
                continue
            batched = getattr(scorer, "rewards", None)  # a scorer may offer only per-scene reward()
            costs[c0:c0 + n] = -(batched(xs, labs) if batched is not None
                                 else np.array([scorer.reward(x, lab)[0] for x, lab in zip(xs, labs)]))
        return costs

    return rollout


def sim_rollout_factory(env, reward_cfg=None, topo_cfg=None, board_z: float = 0.05,
                        push: bool | Mapping[str, bool] = False):
    """``factory(obs, goal) -> rollout`` for MPPIPolicy: plans from obs['sim_state'] / obs['particle_labels'].

    ``push``: whether a rollout pushes after its cuts; a mapping {task: push} follows the goal's task, so
    that the rollouts of an evaluation over several tasks do what the executed episode does.
    """

    def factory(obs: dict, goal):
        for k in ("sim_state", "particle_labels"):
            if k not in obs:
                raise KeyError(f"MPPI needs obs[{k!r}] (set by run_episode); obs has {', '.join(obs)}")
        if isinstance(push, Mapping):
            task = getattr(goal, "task", None)
            if task not in push:
                raise KeyError(f"sim_rollout_factory: no push setting for task {task!r}; known: {', '.join(push)}")
            do_push = bool(push[task])
        else:
            do_push = bool(push)
        return make_sim_rollout(env, obs["sim_state"], goal, reward_cfg, topo_cfg, board_z,
                                labels=obs["particle_labels"], push=do_push)

    return factory


def empty_history() -> deque:
    return deque([np.zeros(POSE_FEATURE_DIM, np.float32)] * HISTORY_LEN, maxlen=HISTORY_LEN)


def make_step(x_t, f_t, x_t1, f_t1, action: KnifeAction, history, reward: float, success: bool,
              board_z: float) -> dict:
    """One dataset record (EpisodeWriter input); history = the 3 previous pose features, oldest first.

    ``action`` should be the quantized one that was executed (quantize_action): the stored float32 vector and
    the pose are both of it, so the vector read back gives the executed plane exactly.
    """
    action = quantize_action(action)
    return {"x_t": np.asarray(x_t, np.float32).copy(), "f_t": np.asarray(f_t, np.int32).copy(),
            "x_t1": np.asarray(x_t1, np.float32).copy(), "f_t1": np.asarray(f_t1, np.int32).copy(),
            "action": action.to_vector(), "pose": action.to_matrix(board_z).astype(np.float32),
            "history": np.stack(list(history)).astype(np.float32), "reward": float(reward),
            "success": bool(success)}


def env_board_z(env, default: float = 0.05) -> float:
    return float(getattr(getattr(env, "cfg", None), "board_z", default))


def run_episode(env, goal, planner, reward_cfg=None, topo_cfg=None, max_cuts: int = 5, push: bool = False,
                observe_fn=None, progress=None, success_threshold: float | None = None,
                scorer: Scorer | None = None, seed: int | None = None) -> tuple[list[dict], dict]:
    """Execute ``planner`` (Policy) in ``env`` (already reset, scene 0) until success or max_cuts cuts.

    ``seed`` (the episode's) re-seeds a stochastic planner at its reset (topocut.policies.base.reset_policy).

    Returns the step records and a summary; a SimulationDiverged marks the
    episode ``failed`` and keeps the steps recorded before it.
    """
    t0 = time.perf_counter()
    scorer = scorer or Scorer(goal, reward_cfg, topo_cfg, success_threshold, device=topology_device(env))
    board_z = env_board_z(env)
    B = int(getattr(env, "batch_size", 1))
    Diverged = simulation_diverged_error()
    st = env.state()
    x = np.asarray(st.x[0])  # N,3
    labels = scorer.labels(x, st.damage[0], None, None)
    reset_policy(planner, goal, seed=seed)
    history = empty_history()
    steps, status, error = [], "ok", None
    for t in range(max_cuts):
        points, obs_labels = observe_fn(x, labels) if observe_fn is not None else (x, labels)
        obs = {"points": points, "labels": obs_labels, "history": np.stack(list(history)),
               "goal": goal.points, "goal_labels": goal.labels,
               "sim_state": env.get_state(0), "particle_labels": labels}
        action = quantize_action(planner.act(obs))  # executed, stored and its pose: one float32-exact plane
        env.set_state(obs["sim_state"], b=None)  # MPPI's rollouts moved the scenes: execute from the real state
        try:
            env.cut([action] * B if B > 1 else action)
            if push:
                env.push()
        except Diverged as e:  # the reason goes with the episode (its log and dataset entry), not only a NaN reward
            status, error = "failed", f"cut {t + 1}: {type(e).__name__}: {e}"
            break
        st = env.state()
        x1 = np.asarray(st.x[0])
        labels1 = scorer.labels(x1, st.damage[0], st.sweeps[0], labels)
        reward, success = scorer.reward(x1, labels1)
        steps.append(make_step(x, labels, x1, labels1, action, history, reward, success, board_z))
        history.append(action.pose_feature(board_z))
        x, labels = x1, labels1
        if progress is not None:
            progress(1, info=f"cut {t + 1}: reward {reward:.3f}")
        if success:
            break
    summary = {"status": status, "num_cuts": len(steps),
               "final_reward": steps[-1]["reward"] if steps else float("nan"),
               "success": bool(steps and steps[-1]["success"]),
               "rewards": [s["reward"] for s in steps], "actions": [s["action"].tolist() for s in steps],
               "num_clusters": int(len([c for c in np.unique(labels) if c >= 0])),
               "time_s": time.perf_counter() - t0}
    if error:
        summary["error"] = error
    return steps, summary

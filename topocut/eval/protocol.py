"""The evaluation protocol (paper §4, Table 1): episode list, one deterministic rollout, resumable runner.

Every policy sees the same episodes: ``episode_specs`` derives each episode's
seed from (base seed, task, object, index) with a stable hash, and the object
pose from that seed alone.  ``evaluate_episode`` resets the simulator, builds
the goal, and executes up to ``max_cuts`` cuts, scoring each with topology
discovery (consistent ids) and the spectral reward against the goal's pieces.
``run_evaluation`` writes one JSON per (policy, episode), atomically, and skips
the ones already written, so a killed evaluation resumes where it stopped.

The goal and the success condition are the task's (``topocut.tasks.get_task(task_cfg.name)``: ``make_goal``,
``success``).  Where the task's oracle lays pieces down between two cut directions (a ``Turn`` after its
k-th cut in ``Goal.steps``: stick, dice), the episode performs that turn after its k-th cut, whichever policy
cut (``CuttingEnv.turn``; the policies output knife planes only, as the demonstrations they learn from were
recorded with the same scripted turn); discovery then runs with the previous labels and no sweep, so the
cluster ids are kept.  The oracle policy (the goal's planes) so executes the whole ``Goal.steps``.

The simulator, topology, reward and goal modules are reached through their
contract entry points (docs/contracts.md); each can be replaced by keyword
(``goal_fn``, ``discover_fn``, ``reward_fn``) so the protocol is testable
without the simulator.
"""
from __future__ import annotations

import functools
import json
import time
import warnings
import zlib
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from topocut.data.store import write_json_atomic
from topocut.eval.config import EvalConfig
from topocut.policies.base import reset_policy
from topocut.sim.action import POSE_FEATURE_DIM, executed_action
from topocut.sim.primitives import TurnRefused

HISTORY_LEN = 3


@dataclass(frozen=True)
class EpisodeSpec:
    task: str
    object: str
    split: str  # "in" (seen object) | "out" (unseen object)
    episode: int  # index within (task, object)
    seed: int
    pose: object  # topocut.sim.objects.ObjectPose

    @property
    def key(self) -> str:
        return f"{self.task}_{self.object}_{self.episode:03d}"

    def asdict(self) -> dict:
        pose = asdict(self.pose) if hasattr(self.pose, "__dataclass_fields__") else dict(self.pose)
        return {"task": self.task, "object": self.object, "split": self.split, "episode": self.episode,
                "seed": self.seed, "pose": pose}


@dataclass
class EpisodeResult:
    spec: dict  # EpisodeSpec.asdict()
    policy: str
    status: str = "ok"  # ok | failed (simulation diverged) | error (the policy or the scoring raised)
    error: str | None = None
    initial_reward: float = 0.0  # reward of the uncut object against the goal
    rewards: list[float] = field(default_factory=list)  # after each executed cut
    cut_counts: list[int] = field(default_factory=list)  # RewardResult.cut_count after each cut
    successes: list[bool] = field(default_factory=list)  # the task's success (Task.success) after each cut
    turns: list[int] = field(default_factory=list)  # the cuts after which the goal's turn was performed
    num_pieces: list[int] = field(default_factory=list)
    actions: list[list[float]] = field(default_factory=list)  # executed [x, y, yaw, tilt]
    act_time_s: list[float] = field(default_factory=list)
    time_s: float = 0.0

    @property
    def num_cuts(self) -> int:
        return len(self.actions)

    @property
    def final_reward(self) -> float:
        # a diverged episode keeps the reward of the last state that was simulated
        return float(self.rewards[-1]) if self.rewards else float(self.initial_reward)

    @property
    def final_cut_count(self) -> int:
        return int(self.cut_counts[-1]) if self.cut_counts else 0

    @property
    def success(self) -> bool:
        return bool(self.successes and self.successes[-1])

    def asdict(self) -> dict:
        d = asdict(self)
        d.update(num_cuts=self.num_cuts, final_reward=self.final_reward, final_cut_count=self.final_cut_count,
                 success=self.success)
        return d


def episode_seed(base_seed: int, task: str, obj: str, episode: int) -> int:
    """Stable across processes and Python versions (unlike hash())."""
    return int((base_seed * 1_000_003 + zlib.crc32(f"{task}|{obj}|{episode}".encode())) % (2 ** 31 - 1))


def episode_pose(cfg: EvalConfig, seed: int):
    from topocut.sim.objects import ObjectPose, random_pose

    if not cfg.randomize_pose:
        return ObjectPose()
    return random_pose(np.random.default_rng(seed), translation=cfg.translation, yaw_deg=cfg.yaw_deg,
                       scale=(cfg.scale_min, cfg.scale_max))


def episode_specs(cfg: EvalConfig | None = None) -> list[EpisodeSpec]:
    """Deterministic episode list: tasks x (seen objects, unseen objects) x episodes_per_cell."""
    cfg = (cfg or EvalConfig()).validate()
    specs = []
    for task in cfg.tasks:
        for split, objects in (("in", cfg.seen), ("out", cfg.unseen)):
            for obj in objects:
                for ep in range(cfg.episodes_per_cell):
                    seed = episode_seed(cfg.seed, task, obj, ep)
                    specs.append(EpisodeSpec(task, obj, split, ep, seed, episode_pose(cfg, seed)))
    return specs


# -- observations -----------------------------------------------------------------------------------
def make_observe_fn(mode: str = "particles", num_points: int = 2048, obs_cfg=None, seed: int = 0) -> Callable:
    """``observe(x (N,3), labels (N,), seed) -> (points (M,3) f32, labels (M,) i32)`` for ``eval.observation``.

    particles: FPS of the particles to ``num_points`` (as the dataset stores them);
    depth: the depth-camera pipeline of topocut.topology.observation with ``obs_cfg``'s cameras and noise
    (its ``mode`` and ``num_points`` are set from ``mode`` and ``num_points`` here, so ``eval.observation``
    decides what the policy sees whatever the ``observation`` group says).
    ``seed`` (per call; evaluate_episode passes one per episode and cut) draws the FPS start and the
    sensor noise, so an episode observes the same points whenever and wherever it is run.
    """
    import dataclasses

    from topocut.topology.observation import MODES, ObservationConfig

    if mode not in MODES:
        raise ValueError(f"eval.observation={mode!r} is not valid; choose one of {', '.join(MODES)}")
    cfg = dataclasses.replace(obs_cfg or ObservationConfig(), mode=mode, num_points=int(num_points)).validate()
    base = int(seed)

    def observe(x, labels, seed: int = 0):
        from topocut.topology.observation import observe as observe_points

        s = (base * 1_000_003 + int(seed)) % (2**31 - 1)
        pts, lab = observe_points(np.asarray(x), np.asarray(labels), cfg, s)
        return np.asarray(pts, np.float32), np.asarray(lab, np.int32)

    return observe


def step_seed(episode_seed: int, cut: int) -> int:
    """Seed of the observation before cut ``cut`` (0-based) of an episode."""
    return (int(episode_seed) * 7919 + int(cut) + 1) % (2**31 - 1)


# -- one episode ---------------------------------------------------------------------------------------
def _default_goal_fn(task_cfg, obj, pose, spacing, board_z=0.05):
    from topocut.tasks import get_task

    return get_task(task_cfg.name).make_goal(task_cfg, obj, pose, spacing, board_z=board_z)


def _default_discover(x, damage, sweeps, previous, topo_cfg):
    from topocut.topology import discover

    return np.asarray(discover(x, damage, sweeps, previous_labels=previous, cfg=topo_cfg).labels, np.int32)


def _default_reward(fragments, goal_fragments, reward_cfg):
    from topocut.reward import spectral_reward

    return spectral_reward(fragments, goal_fragments, reward_cfg)


def _diverged_type() -> type:
    from topocut.planning.rollout import simulation_diverged_error

    return simulation_diverged_error()


def _fragments(x, labels, min_points: int) -> list[np.ndarray]:
    ids = [c for c in np.unique(labels) if c >= 0]  # -1: unassigned particles belong to no piece
    frags = [x[labels == c] for c in ids]
    return [f for f in frags if len(f) >= min_points]


def _board_z(env) -> float:
    return float(getattr(getattr(env, "cfg", None), "board_z", 0.05))


def _spacing(env) -> float:
    cfg = getattr(env, "cfg", None)
    for name in ("spacing", "particle_spacing", "dx_particle"):
        if hasattr(cfg, name):
            return float(getattr(cfg, name))
    raise ValueError("evaluate_episode: env.cfg has no particle spacing (spacing/particle_spacing); pass spacing=")


def evaluate_episode(spec: EpisodeSpec, policy, env, task_cfg, reward_cfg=None, topo_cfg=None,
                     observe_fn: Callable | None = None, policy_name: str = "policy", max_cuts: int = 5,
                     min_fragment_points: int = 4, stop_on_success: bool = False, spacing: float | None = None,
                     goal_fn: Callable | None = None, discover_fn: Callable | None = None,
                     reward_fn: Callable | None = None, turns: bool = True) -> EpisodeResult:
    """Deterministic rollout of up to ``max_cuts`` sequential cuts of ``policy`` on ``spec``.

    ``policy.act`` returning None ends the episode early.  SimulationDiverged (or a turn the simulator
    refuses) marks it ``failed``; an exception from the policy or from scoring a cut marks it ``error`` (all
    keep the steps completed before).  ``turns``: perform the goal's turns between cuts (module docstring).
    """
    from topocut.tasks import get_task, turns_after

    task = get_task(task_cfg.name)
    board_z = _board_z(env)
    goal_fn, discover_fn, reward_fn = (goal_fn or functools.partial(_default_goal_fn, board_z=board_z),
                                       discover_fn or _default_discover, reward_fn or _default_reward)
    observe_fn = observe_fn or (lambda x, labels, seed: (np.asarray(x, np.float32), np.asarray(labels, np.int32)))
    Diverged = _diverged_type()
    t0 = time.perf_counter()
    result = EpisodeResult(spec=spec.asdict(), policy=policy_name)
    B = int(getattr(env, "batch_size", 1) or 1)

    env.reset(spec.object, spec.pose, seed=spec.seed)
    goal = goal_fn(task_cfg, spec.object, spec.pose, spacing if spacing is not None else _spacing(env))
    goal_frags = [np.asarray(f) for f in goal.fragments]
    st = env.state()
    x = np.asarray(st.x[0])  # N,3
    labels = discover_fn(x, np.asarray(st.damage[0], bool), None, None, topo_cfg)
    result.initial_reward = float(reward_fn(_fragments(x, labels, min_fragment_points), goal_frags, reward_cfg).total)
    reset_policy(policy, goal, seed=spec.seed)
    history = deque([np.zeros(POSE_FEATURE_DIM, np.float32)] * HISTORY_LEN, maxlen=HISTORY_LEN)
    push = bool(getattr(task_cfg, "push", False))
    for k in range(max_cuts):
        points, obs_labels = observe_fn(x, labels, step_seed(spec.seed, k))
        obs = {"points": points, "labels": obs_labels, "history": np.stack(list(history)),  # 3,7 oldest first
               "goal": np.asarray(goal.points, np.float32), "goal_labels": np.asarray(goal.labels, np.int32),
               "particle_labels": labels, "cuts_done": len(result.actions)}
        if hasattr(env, "get_state"):
            obs["sim_state"] = env.get_state(0)  # lets planners (MPPI) act as policies
        ta = time.perf_counter()
        try:
            action = policy.act(obs)
        except Exception as e:  # noqa: BLE001 - a broken policy fails its episode, not the evaluation
            result.status, result.error = "error", f"{type(e).__name__}: {e}"
            break
        result.act_time_s.append(time.perf_counter() - ta)
        if "sim_state" in obs and hasattr(env, "set_state"):
            env.set_state(obs["sim_state"], b=None)  # a planner's rollouts may have moved the scenes
        if action is None:
            break
        action = executed_action(action)  # the pose that runs: the demonstrations' and teleop replay's rule
        try:
            env.cut([action] * B if B > 1 else action)
            if push:
                env.push()
        except Diverged as e:
            result.status, result.error = "failed", str(e)
            break
        st = env.state()
        x = np.asarray(st.x[0])
        try:
            labels = discover_fn(x, np.asarray(st.damage[0], bool), st.sweeps[0], labels, topo_cfg)
            frags = _fragments(x, labels, min_fragment_points)
            res = reward_fn(frags, goal_frags, reward_cfg)
        except Exception as e:  # noqa: BLE001 - recorded in the episode JSON and counted by the report
            result.status, result.error = "error", f"scoring cut {len(result.actions) + 1}: {type(e).__name__}: {e}"
            warnings.warn(f"{policy_name} {spec.key}: {result.error}", stacklevel=2)
            break
        result.rewards.append(float(res.total))
        result.cut_counts.append(int(res.cut_count))
        result.successes.append(bool(task.success(res, task_cfg)))
        result.num_pieces.append(len(frags))
        result.actions.append([float(v) for v in action.to_vector()])
        history.append(action.pose_feature(board_z))
        if stop_on_success and result.successes[-1]:
            break
        todo = turns_after(goal, len(result.actions)) if turns and k + 1 < max_cuts else []
        if todo:  # the goal's scripted turn before the next cut
            try:
                for turn in todo:
                    env.turn(turn)
            except (Diverged, TurnRefused) as e:
                result.status, result.error = "failed", f"turn after cut {len(result.actions)}: {e}"
                break
            result.turns.append(len(result.actions))
            st = env.state()
            x = np.asarray(st.x[0])
            try:  # no new sweep (CuttingEnv.turn clears them): the previous labels carry the ids over
                labels = discover_fn(x, np.asarray(st.damage[0], bool), st.sweeps[0], labels, topo_cfg)
            except Exception as e:  # noqa: BLE001 - as a cut's scoring error
                result.status, result.error = "error", f"labelling after turn {len(result.turns)}: {type(e).__name__}: {e}"
                warnings.warn(f"{policy_name} {spec.key}: {result.error}", stacklevel=2)
                break
    result.time_s = time.perf_counter() - t0
    return result


# -- the whole evaluation ---------------------------------------------------------------------------
def episode_path(out_dir, policy_name: str, spec: EpisodeSpec) -> Path:
    return Path(out_dir) / "episodes" / policy_name / f"{spec.key}.json"


def run_evaluation(specs: list[EpisodeSpec], policies: dict, env, task_cfgs: dict, out_dir, reward_cfg=None,
                   topo_cfg=None, observe_fn: Callable | None = None, cfg: EvalConfig | None = None,
                   progress: bool = True, logger=None, **episode_kw) -> dict[str, list[dict]]:
    """Evaluate every policy on every spec; returns {policy: [episode dicts]} (loaded + new).

    ``task_cfgs`` maps task name -> TaskConfig.  Episodes whose JSON already exists are skipped (resume).
    Specs run in the outer loop so that an interrupted evaluation holds comparable episodes for all policies.
    ``episode_kw`` goes to ``evaluate_episode`` (spacing, goal_fn, discover_fn, reward_fn, ...).
    """
    from topocut.utils.progress import progress_bar

    cfg = cfg or EvalConfig()
    missing = sorted({s.task for s in specs} - set(task_cfgs))
    if missing:
        raise KeyError(f"run_evaluation: no TaskConfig for task {missing[0]!r}; task_cfgs has {', '.join(task_cfgs)}")
    done: dict[tuple[str, str], dict] = {}
    for s in specs:
        for n in policies:
            p = episode_path(out_dir, n, s)
            if p.exists():
                done[n, s.key] = json.loads(p.read_text())
    todo = [(s, n) for s in specs for n in policies if (n, s.key) not in done]
    with progress_bar("eval", total=len(todo), enabled=progress) as advance:
        for spec, name in todo:
            res = evaluate_episode(spec, policies[name], env, task_cfgs[spec.task], reward_cfg, topo_cfg,
                                   observe_fn, policy_name=name, max_cuts=cfg.max_cuts,
                                   min_fragment_points=cfg.min_fragment_points,
                                   stop_on_success=cfg.stop_on_success, **episode_kw)
            d = res.asdict()
            write_json_atomic(episode_path(out_dir, name, spec), d)
            done[name, spec.key] = d
            if logger is not None:
                logger.log({f"eval/{name}/{spec.task}/final_reward": d["final_reward"],
                            f"eval/{name}/{spec.task}/cut_count": d["final_cut_count"]})
            advance(1, info=f"{name} {spec.key}: R={d['final_reward']:.3f} N_C={d['final_cut_count']} {d['status']}")
    return {n: [done[n, s.key] for s in specs] for n in policies}

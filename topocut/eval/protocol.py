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

import json
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from topocut.data.store import write_json_atomic
from topocut.episode import (
    Episode,
    EpisodeOutcome,
    env_board_z,
    eval_episode_seed,
    make_scoring,
    run_episodes,
    step_seed,  # noqa: F401 - the observation seeds, re-exported
)
from topocut.episode import simulation_diverged_error as _diverged_type  # noqa: F401 - the tests' SimulationDiverged
from topocut.eval.config import EvalConfig


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
class EpisodeResult(EpisodeOutcome):
    """One evaluated episode: its spec and policy, then the episode's outcome (topocut.episode.EpisodeOutcome,
    the fields the engine's EpisodeLog has too).  ``asdict`` (the episode JSON) keeps spec and policy first."""
    spec: dict = field(default=None, kw_only=True)  # EpisodeSpec.asdict()
    policy: str = field(default=None, kw_only=True)

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
        d = {"spec": d.pop("spec"), "policy": d.pop("policy"), **d}  # the JSON's key order
        d.update(num_cuts=self.num_cuts, final_reward=self.final_reward, final_cut_count=self.final_cut_count,
                 success=self.success)
        return d


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
                    seed = eval_episode_seed(cfg.seed, task, obj, ep)
                    specs.append(EpisodeSpec(task, obj, split, ep, seed, episode_pose(cfg, seed)))
    return specs


# -- observations -----------------------------------------------------------------------------------
def make_observe_fn(mode: str = "particles", num_points: int = 2048, obs_cfg=None, seed: int = 0,
                    device: str = "cpu") -> Callable:
    """``observe(x (N,3), labels (N,), seed) -> (points (M,3) f32, labels (M,) i32)`` for ``eval.observation``.

    particles: FPS of the particles to ``num_points`` (as the dataset stores them);
    depth: the depth-camera pipeline of topocut.topology.observation with ``obs_cfg``'s cameras and noise
    (its ``mode`` and ``num_points`` are set from ``mode`` and ``num_points`` here, so ``eval.observation``
    decides what the policy sees whatever the ``observation`` group says).
    ``seed`` (per call; evaluate_episode passes one per episode and cut) draws the FPS start and the
    sensor noise, so an episode observes the same points whenever and wherever it is run.
    ``observe.batch(xs, labels, seeds)`` observes several scenes at once, the same points as ``observe`` each
    (the episode engine's batches: on a CUDA ``device`` the particles' FPS of every scene is one launch).
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

    def batch(xs, labels, seeds):
        from topocut.topology.observation import observe_scenes

        seeds = [(base * 1_000_003 + int(s)) % (2**31 - 1) for s in seeds]
        return observe_scenes(xs, labels, cfg, seeds, device)

    observe.batch = batch
    return observe


# -- one episode ---------------------------------------------------------------------------------------
def scoring_for(env, reward_cfg=None, topo_cfg=None, min_fragment_points: int = 4, **parts):
    """``make_scoring(reward_cfg, topo_cfg, min_fragment_points=..., env=env, **parts)`` under its older name
    (topocut/eval/runner.py still calls it)."""
    return make_scoring(reward_cfg, topo_cfg, min_fragment_points=min_fragment_points, env=env, **parts)


def _result(spec: EpisodeSpec, name: str, log) -> EpisodeResult:
    return EpisodeResult(spec=spec.asdict(), policy=name, **EpisodeOutcome.outcome(log))


def _episode(spec: EpisodeSpec, task_cfg):
    return Episode(spec.object, spec.pose, spec.seed, task_cfg, key=spec.key)


def evaluate_episode(spec: EpisodeSpec, policy, env, task_cfg, reward_cfg=None, topo_cfg=None,
                     observe_fn: Callable | None = None, policy_name: str = "policy", max_cuts: int = 5,
                     min_fragment_points: int = 4, stop_on_success: bool = False, spacing: float | None = None,
                     goal_fn: Callable | None = None, discover_fn: Callable | None = None,
                     reward_fn: Callable | None = None, turns: bool = True) -> EpisodeResult:
    """Deterministic rollout of up to ``max_cuts`` sequential cuts of ``policy`` on ``spec`` (one episode of the
    engine, topocut.episode.run_episodes: its rules for stopping, failures, turns and observations).

    ``policy.act`` returning None ends the episode early.  SimulationDiverged (or a turn the simulator
    refuses) marks it ``failed``; an exception from the policy or from scoring a cut marks it ``error`` (all
    keep the steps completed before).  ``turns``: perform the goal's turns between cuts (module docstring).
    """
    sc = make_scoring(reward_cfg, topo_cfg, min_fragment_points=min_fragment_points, env=env, goal_fn=goal_fn,
                      discover_fn=discover_fn, reward_fn=reward_fn)
    [log] = run_episodes(env, [_episode(spec, task_cfg)], policy, sc, max_cuts=max_cuts, observe_fn=observe_fn,
                         stop_on_success=stop_on_success, turns=turns, spacing=spacing)
    return _result(spec, policy_name, log)


# -- the whole evaluation ---------------------------------------------------------------------------
def episode_path(out_dir, policy_name: str, spec: EpisodeSpec) -> Path:
    return Path(out_dir) / "episodes" / policy_name / f"{spec.key}.json"


def run_evaluation(specs: list[EpisodeSpec], policies: dict, env, task_cfgs: dict, out_dir, reward_cfg=None,
                   topo_cfg=None, observe_fn: Callable | None = None, cfg: EvalConfig | None = None,
                   progress: bool = True, logger=None, film=None, **episode_kw) -> dict[str, list[dict]]:
    """Evaluate every policy on every spec; returns {policy: [episode dicts]} (loaded + new).

    ``task_cfgs`` maps task name -> TaskConfig.  Episodes whose JSON already exists are skipped (resume).
    Specs run in the outer loop so that an interrupted evaluation holds comparable episodes for all policies.
    ``episode_kw`` goes to ``evaluate_episode`` (spacing, goal_fn, discover_fn, reward_fn, ...).  ``film``
    (topocut.eval.videos.Filming): a batch holding an episode it wants keeps its frames, and that episode's video
    is written from them before its JSON, so a filmed episode is never run twice.
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
    episode_kw = dict(episode_kw)
    sc = make_scoring(reward_cfg, topo_cfg, min_fragment_points=cfg.min_fragment_points, env=env,
                      **{k: episode_kw.pop(k, None) for k in ("goal_fn", "discover_fn", "reward_fn")})
    B = int(getattr(env, "batch_size", 1) or 1)
    board_z = env_board_z(env)
    with progress_bar("eval", total=len(todo), enabled=progress) as advance:
        # B specs at a time, every policy on them before the next B: an interrupted evaluation holds
        # comparable episodes for all policies; each policy's B episodes run as one batch (topocut.episode)
        for g0 in range(0, len(specs), B):
            group = specs[g0:g0 + B]
            for name, policy in policies.items():
                mine = [s for s in group if (name, s.key) not in done]
                if not mine:
                    continue
                filmed = {s.key for s in mine if film is not None and film.wants(name, s)}
                # the batch keeps its frames when it films: its episodes run as they would without (same batch-mates)
                frames = dict(frames=True, cut_frames=film.frames_per_cut) if filmed else {}

                def finished(i, log, mine=mine, name=name, filmed=filmed):
                    spec = mine[i]
                    if spec.key in filmed:  # the video first: an episode committed without it is filmed again later
                        film.write(name, spec, log, board_z)
                    d = _result(spec, name, log).asdict()
                    write_json_atomic(episode_path(out_dir, name, spec), d)
                    done[name, spec.key] = d
                    if logger is not None:
                        logger.log({f"eval/{name}/{spec.task}/final_reward": d["final_reward"],
                                    f"eval/{name}/{spec.task}/cut_count": d["final_cut_count"]})
                    advance(1, info=f"{name} {spec.key}: R={d['final_reward']:.3f} N_C={d['final_cut_count']} "
                                    f"{d['status']}")

                run_episodes(env, [_episode(s, task_cfgs[s.task]) for s in mine], policy, sc,
                             max_cuts=cfg.max_cuts, observe_fn=observe_fn, stop_on_success=cfg.stop_on_success,
                             on_done=finished, **frames, **episode_kw)
    return {n: [done[n, s.key] for s in specs] for n in policies}

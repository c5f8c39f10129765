"""Gymnasium environments over the batched cutting simulator (docs/gym.md).

``CuttingVectorEnv`` is a ``gymnasium.vector.VectorEnv`` whose ``num_envs`` sub-environments are the B scenes
of ONE ``topocut.sim.CuttingEnv`` batch: one ``step`` is one batched ``CuttingEnv.cut`` (a knife action per
scene), the push where the task pushes, the goal's scripted turn where the goal has one after that cut, and
topology discovery + the spectral reward per scene.  ``CuttingEnvGym`` is the single-scene ``gymnasium.Env``
(num_envs = 1) on top of it, for ``gymnasium.utils.env_checker.check_env`` and single-env code.

Episode rule = the evaluation protocol's, through the same engine (topocut.episode.EpisodeBatch, which
evaluate_episode and the demonstrations run): ``reset(seed=s)`` gives scene b the episode of seed s + b: its
object (``objects``: one name, or a list each scene draws one from), the pose ``episode_pose(eval_cfg, s + b)``
and particle sampling seed s + b, the goal from the task's ``make_goal``, the uncut object labelled.  A step
executes ``executed_action(KnifeAction.from_vector(a))`` per scene, then as the evaluation: the push where the
task pushes (per scene), discovery with the previous labels, the spectral reward against the scene's own goal,
``task.success``, and after cut k < max_cuts the goal's turns.

Scenes of one batch may hold different objects and poses (CuttingEnv pads them to one particle count), but
they reset together: autoreset is DISABLED (``metadata["autoreset_mode"] = AutoresetMode.DISABLED``); call
``reset()`` when you want new episodes (``options={"reset_mask": m}`` is accepted only with every scene
set).  A scene that has terminated or been truncated idles (frozen: no substep touches it); its reward is 0
and its flags stay.

Reward (``reward_mode``): "total" (default; the paper's per-step reward: R, the task's total spectral reward
``RewardResult.total`` after the cut) or "gain" (R after the cut minus R before it).  ``info`` always holds
both as ``reward_total`` and ``reward_gain``, with ``cut_count``, ``num_pieces``, ``success``, ``failed``.
terminated = ``task.success(result, task_cfg)``; truncated = cuts == max_cuts, or the batch diverged / a turn
was refused (``info["failed"]``).

Rendering: ``render_mode="rgb_array"`` makes ``render()`` return each scene's (H,W,3) uint8 frame
(topocut.sim.render.render_frame: pieces by cluster id, the board, the knife of the scene's last cut) -- a tuple
of them from the vector env, one array from ``CuttingEnvGym``.  ``import topocut.envs`` registers
``TopoCut/Slice-v0``, ``TopoCut/Stick-v0`` and ``TopoCut/Dice-v0`` (``make_env`` / ``make_vector_env``).
"""
from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from topocut.policies.base import HISTORY_LEN
from topocut.sim.action import ACTION_DIM, POSE_FEATURE_DIM, KnifeAction, executed_action

ID_MAX = 2**31 - 1  # cluster ids / goal piece labels are int32 in the pipeline
REWARD_MODES = ("total", "gain")
OBS_FIELDS = ("points", "labels", "history", "goal", "goal_labels", "cuts_done")
RENDER_MODES = ["rgb_array"]
RENDER_FPS = 2  # a frame per cut
VIEW_MARGIN = 0.05  # [units] round the uncut object in a rendered episode's view box: room for pushed/turned pieces


def default_tilt_max(task_cfg) -> float:
    """The knife tilt range |tilt| <= tilt_max: MPPI's ``planner.tilt_max`` (MPPIConfig) where the task samples tilt
    (``task.sample_tilt``: pyramid), else 0 (vertical cuts, as the other tasks' planners and oracles)."""
    from topocut.planning.config import MPPIConfig

    return float(MPPIConfig.tilt_max) if getattr(task_cfg, "sample_tilt", False) else 0.0


def single_spaces(num_points: int, num_goal_points: int, max_cuts: int, tilt_max: float):
    """(single_action_space, single_observation_space).

    action: Box [x, y, yaw, tilt] float32 -- x, y the board point in the unit-square domain, yaw in
    [-pi/2, pi/2] (the canonical range (-pi/2, pi/2]; -pi/2 runs as pi/2 with the normal reversed, the same
    plane), tilt in [-tilt_max, tilt_max].
    observation (Dict): points (P,3) f32 in the unit cube and labels (P,) i64 (cluster ids, -1 unassigned):
    a deterministic FPS of the particles (``topocut.policies.inputs.sample_indices``, start "farthest");
    history (3,7) f32 pose features of the last cuts (board point in the unit square, unit quaternion wxyz),
    oldest first, zeros before; goal (M,3) f32 and
    goal_labels (M,) i64 (0 = not a goal piece, i = goal piece i): the goal cloud, FPS'd the same way;
    cuts_done () i64 in [0, max_cuts].
    """
    half = np.float32(np.pi / 2)
    action = spaces.Box(low=np.array([0.0, 0.0, -half, -tilt_max], np.float32),
                        high=np.array([1.0, 1.0, half, tilt_max], np.float32), shape=(ACTION_DIM,), dtype=np.float32)
    obs = spaces.Dict({
        "points": spaces.Box(0.0, 1.0, (num_points, 3), np.float32),
        "labels": spaces.Box(-1, ID_MAX, (num_points,), np.int64),
        "history": spaces.Box(-1.0, 1.0, (HISTORY_LEN, POSE_FEATURE_DIM), np.float32),
        "goal": spaces.Box(0.0, 1.0, (num_goal_points, 3), np.float32),
        "goal_labels": spaces.Box(0, ID_MAX, (num_goal_points,), np.int64),
        "cuts_done": spaces.Box(0, max_cuts, (), np.int64),
    })
    return action, obs


class CuttingVectorEnv(VectorEnv):
    """``num_envs`` cutting scenes in one CuttingEnv batch (module docstring for the episode rule)."""

    metadata = {"autoreset_mode": AutoresetMode.DISABLED, "render_modes": RENDER_MODES, "render_fps": RENDER_FPS}

    def __init__(self, task: str = "slice", objects: str | list[str] = "cube", num_envs: int = 2, sim_cfg=None,
                 topo_cfg=None, reward_cfg=None, task_cfg=None, eval_cfg=None, num_points: int = 1024,
                 num_goal_points: int = 1024, max_cuts: int | None = None, push: bool | None = None,
                 reward_mode: str = "total", tilt_max: float | None = None, device: str = "cpu",
                 min_fragment_points: int | None = None, turns: bool = True, render_mode: str | None = None):
        """task: a task name (knife tasks: slice, stick, dice, pyramid); task_cfg: its task config (default
        ``task_config(task)``, the task's defaults: stick and dice push).  objects: one object name, or a list from which each scene draws its own at
        every reset.  sim_cfg: SimConfig (its batch_size is replaced by num_envs).  topo_cfg /
        reward_cfg: TopologyConfig / RewardConfig (None: defaults).  eval_cfg: EvalConfig whose pose
        randomisation (randomize_pose, translation, yaw_deg, scale_min/max) and min_fragment_points are used.
        num_points / num_goal_points: P and M of the observation.  max_cuts (None: task_cfg.max_cuts), push
        (None: task_cfg.push).  device: where topology discovery runs ("cpu" / "cuda").  render_mode: None or
        "rgb_array" (``render()`` returns frames)."""
        from topocut.eval.config import EvalConfig
        from topocut.sim.config import SimConfig
        from topocut.sim.env import CuttingEnv
        from topocut.tasks import get_task, task_config

        if reward_mode not in REWARD_MODES:
            raise ValueError(f"reward_mode={reward_mode!r}; choose one of {', '.join(REWARD_MODES)}")
        check_render_mode(render_mode)
        self.task_cfg = (task_cfg if task_cfg is not None else task_config(task)).validate()
        self.task = get_task(self.task_cfg.name)
        if getattr(self.task, "tool", "knife") != "knife":
            raise ValueError(f"CuttingVectorEnv runs the knife tasks; task {self.task_cfg.name!r} uses a "
                             f"{self.task.tool}")
        self.objects = [objects] if isinstance(objects, str) else list(objects)
        if not self.objects:
            raise ValueError("CuttingVectorEnv: objects is empty")
        self.eval_cfg = eval_cfg or EvalConfig()
        self.num_envs = int(num_envs)
        if self.num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.max_cuts = int(self.task_cfg.max_cuts if max_cuts is None else max_cuts)
        if self.max_cuts < 1:
            raise ValueError(f"max_cuts must be >= 1, got {self.max_cuts}")
        self.push = bool(self.task_cfg.push if push is None else push)
        self.turns = bool(turns)
        self.reward_mode = reward_mode
        self.topo_cfg, self.reward_cfg, self.device = topo_cfg, reward_cfg, device
        self.min_fragment_points = int(self.eval_cfg.min_fragment_points if min_fragment_points is None
                                       else min_fragment_points)
        self.num_points, self.num_goal_points = int(num_points), int(num_goal_points)
        self.tilt_max = float(default_tilt_max(self.task_cfg) if tilt_max is None else tilt_max)
        sim_cfg = dataclasses.replace(sim_cfg or SimConfig(), batch_size=self.num_envs)
        self.sim = CuttingEnv(sim_cfg, batch_size=self.num_envs)
        self.board_z = float(self.sim.cfg.board_z)
        self.single_action_space, self.single_observation_space = single_spaces(
            self.num_points, self.num_goal_points, self.max_cuts, self.tilt_max)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.render_mode = render_mode
        self.goal = None
        self.engine = None  # topocut.episode.EpisodeBatch, built at the first reset
        self.episode_seed = None
        self.knife = [None] * self.num_envs  # per scene, the KnifeAction of its last cut in this episode (renders)
        self.view = [None] * self.num_envs  # per scene, the (lo, hi) view box of its rendered frames

    # -- helpers ---------------------------------------------------------------------------------------
    def _sample(self, pts, n: int, labels) -> tuple[np.ndarray, np.ndarray]:
        from topocut.policies.inputs import sample_indices

        idx = sample_indices(np.asarray(pts, np.float64), n, seed=0, start="farthest")
        return np.asarray(pts, np.float32)[idx], np.asarray(labels, np.int64)[idx]

    def _obs(self) -> dict:
        B, e = self.num_envs, self.engine
        pts = np.zeros((B, self.num_points, 3), np.float32)
        lab = np.zeros((B, self.num_points), np.int64)
        for b in range(B):
            pts[b], lab[b] = self._sample(e.xs[b], self.num_points, e.labels[b])
        pts = np.clip(pts, 0.0, 1.0)  # particles stay in the domain (walls); float noise at its faces
        history = np.stack([np.stack(list(h)) for h in e.hist]).astype(np.float32)  # B,3,7 oldest first
        return {"points": pts, "labels": lab, "history": history, "goal": self.goal_points.copy(),
                "goal_labels": self.goal_labels.copy(),
                "cuts_done": np.array([len(lg.actions) for lg in e.logs], np.int64)}

    # -- gymnasium API ---------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """New episodes in every scene: scene b the episode of seed ``seed`` + b (module docstring); None draws
        the seed from ``np_random``.  ``options``: {"object": name} puts that object in every scene;
        {"reset_mask": (B,) bool} must hold every scene (the scenes of one batch reset together)."""
        from gymnasium.utils import seeding

        from topocut.episode import Episode, EpisodeBatch, make_scoring
        from topocut.eval.protocol import episode_pose

        options = dict(options or {})
        mask = options.get("reset_mask")
        if mask is not None and not np.all(mask):
            raise ValueError("CuttingVectorEnv resets every scene together (one simulator batch): "
                             "options['reset_mask'] must be all True")
        if seed is not None:
            self._np_random, self._np_random_seed = seeding.np_random(seed)
            ep_seed = int(seed)
        else:
            if self._np_random is None:
                self._np_random, self._np_random_seed = seeding.np_random()
            ep_seed = int(self._np_random.integers(ID_MAX - self.num_envs))
        B = self.num_envs
        if options.get("object") is not None:
            objects = [options["object"]] * B
        elif len(self.objects) == 1:
            objects = self.objects * B
        else:
            objects = [self.objects[int(i)] for i in self._np_random.integers(len(self.objects), size=B)]
        seeds = [ep_seed + b for b in range(B)]
        task = dataclasses.replace(self.task_cfg, push=self.push)
        episodes = [Episode(o, episode_pose(self.eval_cfg, s), s, task, key=f"{o}_{s}") for o, s in zip(objects, seeds)]
        if self.engine is None:
            scoring = make_scoring(self.reward_cfg, self.topo_cfg, device=self.device, board_z=self.board_z,
                                   min_fragment_points=self.min_fragment_points)
            self.engine = EpisodeBatch(self.sim, scoring, self.max_cuts, self.turns, self.sim.cfg.spacing,
                                       stop_on_success=True)
        self.engine.start(episodes)
        self.object, self.episode_seed = objects, ep_seed
        gp = [self._sample(g.points, self.num_goal_points, g.labels) for g in self.engine.goals]
        self.goal_points = np.stack([p for p, _ in gp])
        self.goal_labels = np.stack([lab for _, lab in gp])
        self.goal = self.engine.goals
        self.total = np.array([s.total for s in self.engine.initial], np.float64)
        self.done = np.zeros(B, bool)
        self.knife = [None] * B
        self.view = [None] * B
        info = {"reward_total": self.total.copy(), "num_pieces": np.array([s.pieces for s in self.engine.initial],
                                                                          np.int64),
                "episode_seed": np.array(seeds, np.int64)}
        return self._obs(), self._with_masks(info, np.ones(B, bool))

    def step(self, actions):
        if self.engine is None:
            raise RuntimeError("CuttingVectorEnv.step before reset()")
        B = self.num_envs
        acts = np.asarray(actions, np.float32).reshape(B, ACTION_DIM)
        knives = [executed_action(KnifeAction.from_vector(a)) for a in acts]
        active = ~self.done
        scores = self.engine.step([k if active[b] else None for b, k in enumerate(knives)])
        reward, gain = np.zeros(B, np.float64), np.zeros(B, np.float64)
        cut_count, num_pieces = np.zeros(B, np.int64), np.zeros(B, np.int64)
        success, failed = np.zeros(B, bool), np.zeros(B, bool)
        for b in np.flatnonzero(active):
            res = scores[b]
            if res is None or self.engine.logs[b].status != "ok":  # diverged, a refused turn, a scoring error
                failed[b] = True
                continue
            gain[b] = res.total - self.total[b]
            self.total[b] = res.total
            cut_count[b], num_pieces[b], success[b] = res.cut_count, res.pieces, res.success
        reward[active] = (gain if self.reward_mode == "gain" else self.total)[active]
        reward[failed] = 0.0
        cuts = np.array([len(lg.actions) for lg in self.engine.logs])
        terminated = active & success & ~failed
        truncated = active & ~terminated & ((cuts >= self.max_cuts) | failed)
        self.done |= terminated | truncated
        self.knife = [k if active[b] else self.knife[b] for b, k in enumerate(knives)]
        info = {"reward_total": self.total.copy(), "reward_gain": gain, "cut_count": cut_count,
                "num_pieces": num_pieces, "success": success, "failed": failed,
                "actions": np.stack([a.to_vector() for a in knives])}
        return (self._obs(), reward.astype(np.float64), terminated, truncated, self._with_masks(info, active))

    def render(self) -> tuple[np.ndarray, ...] | None:
        """render_mode "rgb_array": each scene's (H,W,3) uint8 frame (topocut.sim.render.render_frame) -- its pieces
        by cluster id, the board, the knife at the plane of its last cut.  A scene's view box is its uncut object
        with VIEW_MARGIN round it, grown to hold every state rendered since the reset, so a piece is never cropped
        and the view stays put while the pieces stay near the object."""
        if self.render_mode is None:
            gym.logger.warn("render() without a render_mode: make the env with render_mode='rgb_array'")
            return None
        if self.engine is None:
            raise RuntimeError("CuttingVectorEnv.render before reset()")
        from topocut.sim.render import render_frame

        frames = []
        for b in range(self.num_envs):
            x = np.asarray(self.engine.xs[b], np.float64)  # n_b,3
            if self.view[b] is None:
                lo, hi = x.min(0) - VIEW_MARGIN, x.max(0) + VIEW_MARGIN
                lo[2] = min(x[:, 2].min(), self.board_z) - 0.01
                hi[2] = x[:, 2].max() + 0.02  # no margin above: the object rests on the board
            else:
                lo, hi = self.view[b]
            self.view[b] = (np.minimum(lo, x.min(0) - 0.01), np.maximum(hi, x.max(0) + 0.01))
            cuts = len(self.engine.logs[b].actions)
            frames.append(render_frame(x, self.engine.labels[b], knife=self.knife[b], board_z=self.board_z,
                                       limits=self.view[b], title=f"{self.task_cfg.name}: {self.object[b]}, cut "
                                                                  f"{cuts}, R = {self.total[b]:.2f}"))
        return tuple(frames)

    @staticmethod
    def _with_masks(info: dict, mask: np.ndarray) -> dict:
        """gymnasium's vector info convention: every key k has a boolean "_k" naming the scenes it holds."""
        out = dict(info)
        for k in info:
            out[f"_{k}"] = mask.copy()
        return out

    def close_extras(self, **kwargs):
        solver = getattr(self.sim, "solver", None)
        if solver is not None and hasattr(solver, "destroy"):
            solver.destroy()
            self.sim.solver = None


class CuttingEnvGym(gym.Env):
    """One scene (``CuttingVectorEnv`` with num_envs = 1) as a ``gymnasium.Env``; same arguments, unbatched
    spaces, observations and scalar reward / flags."""

    metadata = {"render_modes": RENDER_MODES, "render_fps": RENDER_FPS}

    def __init__(self, **kwargs):
        kwargs["num_envs"] = 1
        self.vec = CuttingVectorEnv(**kwargs)
        self.action_space = self.vec.single_action_space
        self.observation_space = self.vec.single_observation_space
        self.render_mode = self.vec.render_mode

    @property
    def goal(self):
        """The scene's goal (topocut.tasks.base.Goal: its pieces, planes and steps)."""
        return None if self.vec.goal is None else self.vec.goal[0]

    @staticmethod
    def _one(d: dict) -> dict:
        return {k: (np.asarray(v[0]) if isinstance(v, np.ndarray) and v.ndim >= 1 else v) for k, v in d.items()
                if not k.startswith("_")}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = self.vec.reset(seed=seed, options=options)
        self._np_random = self.vec._np_random  # one generator: the vector env draws the episodes from it
        return self._one(obs), self._one(info)

    def step(self, action):
        obs, r, term, trunc, info = self.vec.step(np.asarray(action, np.float32)[None])
        return self._one(obs), float(r[0]), bool(term[0]), bool(trunc[0]), self._one(info)

    def render(self) -> np.ndarray | None:
        """render_mode "rgb_array": the scene's (H,W,3) uint8 frame (CuttingVectorEnv.render)."""
        frames = self.vec.render()
        return None if frames is None else frames[0]

    def close(self):
        self.vec.close()


def check_render_mode(render_mode) -> None:
    if render_mode is not None and render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode={render_mode!r}; valid: None, {', '.join(map(repr, RENDER_MODES))}")


def protocol_task_config(task: str, max_cuts: int | None = None):
    """The evaluation protocol's TaskConfig of ``task`` (conf/task/<task>.yaml: stick and dice push; the evaluation's
    cut budget, eval.max_cuts, unless ``max_cuts``): what the registered TopoCut/<Task>-v0 ids run."""
    from topocut.eval.config import EvalConfig
    from topocut.eval.runner import task_configs

    return task_configs([task], EvalConfig().max_cuts if max_cuts is None else int(max_cuts))[task]


def _registered_kwargs(task: str, kwargs: dict) -> dict:
    from topocut.eval.config import EvalConfig

    if kwargs.get("task_cfg") is None:
        kwargs["task_cfg"] = protocol_task_config(task, kwargs.get("max_cuts"))
    kwargs.setdefault("objects", list(EvalConfig().seen))  # Table 1's seen objects, one drawn per scene and reset
    return kwargs


def make_env(task: str = "slice", **kwargs) -> CuttingEnvGym:
    """Entry point of ``gymnasium.make("TopoCut/<Task>-v0", ...)``: CuttingEnvGym on the protocol's task config and,
    unless given, Table 1's seen objects; every CuttingVectorEnv argument may be passed."""
    return CuttingEnvGym(task=task, **_registered_kwargs(task, kwargs))


def make_vector_env(task: str = "slice", num_envs: int = 2, **kwargs) -> CuttingVectorEnv:
    """Entry point of ``gymnasium.make_vec("TopoCut/<Task>-v0", num_envs=B, ...)``: B scenes in one simulator batch
    (CuttingVectorEnv), as make_env."""
    return CuttingVectorEnv(task=task, num_envs=num_envs, **_registered_kwargs(task, kwargs))


make_env.metadata = CuttingEnvGym.metadata  # gymnasium.make reads the render modes off the entry point
make_vector_env.metadata = CuttingVectorEnv.metadata
REGISTERED = {"TopoCut/Slice-v0": "slice", "TopoCut/Stick-v0": "stick", "TopoCut/Dice-v0": "dice"}  # Table 1's tasks


def register_envs() -> None:
    """Register REGISTERED with gymnasium (``import topocut.envs`` does; idempotent)."""
    for env_id, task in REGISTERED.items():
        if env_id not in gym.registry:
            gym.register(env_id, entry_point="topocut.envs.vector:make_env",
                         vector_entry_point="topocut.envs.vector:make_vector_env", kwargs={"task": task})

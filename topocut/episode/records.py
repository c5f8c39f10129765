"""What an episode is and what it leaves: ``Episode`` (its scene and task), the pose history a policy sees,
the per-cut ``Score``, the episode's outcome (``EpisodeOutcome``: the fields evaluation's ``EpisodeResult``
and the engine's ``EpisodeLog`` share) and the dataset record of one cut (``make_record``)."""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field, fields

import numpy as np

from topocut.sim.action import POSE_FEATURE_DIM, executed_action

HISTORY_LEN = 3  # the pose features of the last cuts a policy sees (default; a policy may declare its own)


def history_len_of(policy) -> int:
    """The history length ``policy`` declares (its ``history_len``, e.g. a learned policy's ``policy.net
    .history_len``), else HISTORY_LEN."""
    n = getattr(policy, "history_len", None)
    return HISTORY_LEN if n is None else int(n)


def reads_points(policy) -> bool:
    """Whether ``policy`` reads the observed points (``points``, ``labels``: an FPS of the scene, ~0.5 s a scene of
    69k particles on one core): its ``observation_fields`` where its class declares them (the scripted policies:
    topocut.policies.registry's ``inputs``), else yes (a learned policy, your own)."""
    fields = getattr(policy, "observation_fields", None)
    return fields is None or "points" in fields or "labels" in fields


def new_history(history_len: int = HISTORY_LEN) -> deque:
    """The pose features (history_len,7) of the last cuts, oldest first: zeros before the first cut."""
    return deque([np.zeros(POSE_FEATURE_DIM, np.float32)] * history_len, maxlen=history_len)


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
class Score:
    total: float  # the reward
    cut_count: int  # N_C
    success: bool  # the task's success
    pieces: int  # fragments scored


@dataclass
class EpisodeOutcome:
    """What happened in one episode, cut by cut: the fields evaluation's EpisodeResult (its JSON) and the
    engine's EpisodeLog share."""
    status: str = "ok"  # ok | failed (simulation diverged, turn refused) | error (policy or scoring raised)
    error: str | None = None
    initial_reward: float = 0.0  # reward of the uncut object against the goal
    rewards: list[float] = field(default_factory=list)  # after each executed cut
    cut_counts: list[int] = field(default_factory=list)  # RewardResult.cut_count after each cut
    successes: list[bool] = field(default_factory=list)  # the task's success (Task.success) after each cut
    turns: list[int] = field(default_factory=list)  # the cuts after which the goal's turn was performed
    num_pieces: list[int] = field(default_factory=list)
    # after each cut: the simulator's own pieces (its bond components, CuttingEnv.piece, >= 4 particles) and the
    # worst IoU of a discovered piece with its best simulator piece (piece_agreement); empty for an env without
    sim_pieces: list[int] = field(default_factory=list)
    piece_iou: list[float] = field(default_factory=list)
    actions: list[list[float]] = field(default_factory=list)  # executed [x, y, yaw, tilt]
    act_time_s: list[float] = field(default_factory=list)
    time_s: float = 0.0

    def outcome(self) -> dict:
        """The shared fields, by name (as they are: no copies)."""
        return {f.name: getattr(self, f.name) for f in fields(EpisodeOutcome)}


@dataclass
class EpisodeLog(EpisodeOutcome):
    """What happened in one episode (evaluation's EpisodeResult and the demonstrations' records come from it)."""
    steps: list[dict] = field(default_factory=list)  # dataset records (record=True)
    labels: np.ndarray | None = None  # the final particle labels
    # (x, labels, what, knife) after reset, each cut, each turn (frames=True); knife: the cut's executed KnifeAction
    frames: list = field(default_factory=list)
    # per entry of ``frames``: the topocut.sim.cut_frames.CutFrames during the cut that led to it (cut_frames=F > 0: F of
    # them; [] after reset and turns, and for every frame with cut_frames=0)
    motion: list = field(default_factory=list)
    goal: object = None


def make_record(x_t, f_t, x_t1, f_t1, action, history, reward: float, success: bool, board_z: float) -> dict:
    """One dataset record (EpisodeWriter input); ``action`` as executed, history the previous pose features."""
    action = executed_action(action)
    return {"x_t": np.asarray(x_t, np.float32).copy(), "f_t": np.asarray(f_t, np.int32).copy(),
            "x_t1": np.asarray(x_t1, np.float32).copy(), "f_t1": np.asarray(f_t1, np.int32).copy(),
            "action": action.to_vector(), "pose": action.to_matrix(board_z).astype(np.float32),
            "history": np.stack(list(history)).astype(np.float32), "reward": float(reward),
            "success": bool(success)}

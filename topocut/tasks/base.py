"""The task protocol, the goal record, oracle steps and the geometry shared by the knife tasks.

A task (one module per task in ``topocut.tasks``) owns its goal construction, its oracle sequence, its
success condition and its scene set-up; stages, MPPI and evaluation ask the task found by
``topocut.tasks.get_task(name)`` instead of branching on the name.

Oracle steps (``Goal.steps``) are data: a ``Cut`` (one downward knife plane, a KnifeAction) or a ``Turn``
(pieces picked up, rotated about a horizontal axis and laid on the board between two cut directions, as a
cook lays a slab flat before cutting it into sticks).  The simulator executes a turn
(``topocut.sim.CuttingEnv.turn``, docs/tasks.md#turn-primitive); ``Turn.transform`` is its rigid motion, so the
planes after a turn are given in the world frame *after* it.  ``turns_after(goal, k)`` is what a runner does
between the k-th and the (k+1)-th cut (the planner plans the cuts; the turn is the scripted primitive).

Frame of the knife tasks: the object's yaw gives two horizontal axes; a1 is the longer of the two (by
particle extent, ties within 2% go to the local x axis), a2 the other, z up.  Faces are located with the
object's SDF (max_j (s_j + depth_j), depth_j = -sdf(x_j)), so a piece of thickness t holds t / spacing
layers.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from topocut.sim.action import KnifeAction
from topocut.tasks.config import SIZE_KEYS, KnifeTaskConfig


@dataclass(frozen=True)
class Cut:
    """One knife cut: the plane of ``action`` (world frame at the time of the cut)."""

    action: KnifeAction
    kind: str = "cut"


@dataclass(frozen=True)
class Turn:
    """Pick up the pieces named by ``pieces``, turn them rigidly and lay them on the board.

    pieces: goal-piece selector, ``"slab"`` = the material of the first slab (every particle whose label
    at the time of the turn lies inside it: the slab freed by the first cut).  The rigid motion is
    x' = R (x - center) + target with R the rotation by ``angle`` (rad) about ``axis`` (unit, horizontal,
    world) -- ``transform`` applies it.  ``target``'s z is the centroid height at which the turned pieces
    rest on the board (the simulator may let them settle from slightly above).
    """

    pieces: str
    axis: tuple
    angle: float
    center: tuple
    target: tuple
    note: str = ""
    kind: str = "turn"

    def rotation(self) -> np.ndarray:
        from scipy.spatial.transform import Rotation

        return Rotation.from_rotvec(np.asarray(self.axis, np.float64) * self.angle).as_matrix()

    def transform(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, np.float64)
        return (p - np.asarray(self.center)) @ self.rotation().T + np.asarray(self.target)


@dataclass
class Goal:
    fragments: list  # [(m_i,3) f32] target pieces at particle resolution, in the object's initial pose
    planes: list  # [KnifeAction] the cuts of ``steps``, in order (the knife-only view of the oracle)
    points: np.ndarray  # M,3 f32 the ideally cut object (FPS-downsampled to task.num_goal_points)
    labels: np.ndarray  # M, i32 0 = not a goal piece, i+1 = goal piece i
    task: str = "slice"
    object: str = ""
    axes: np.ndarray = field(default=None)  # 3,3 rows a1, a2, z (world)
    steps: list = field(default_factory=list)  # [Cut | Turn] the oracle sequence
    # the pieces the steps make besides the goal pieces and the uncut rest (a die's rims, a stick's edge band), in
    # the initial pose: not waste (docs/reward.md#planned-offcuts); topocut.tasks.ideal
    offcuts: list = field(default_factory=list)  # [(k_i,3) f32]
    anchors: list = field(default_factory=list)  # [ideal.Anchor] per Cut: the piece it splits, for the oracle

    @property
    def turns(self) -> list:
        return [s for s in self.steps if isinstance(s, Turn)]

    def turns_after(self, k: int) -> list:
        return turns_after(self, k)


def turns_after(goal, k: int) -> list:
    """The Turn steps of ``goal.steps`` between its k-th and (k+1)-th Cut (k >= 1; k = 0: before the first cut).

    A goal without ``steps`` (a bare plane list, another task's goal) has none.  Runners call this after every
    executed cut: the turn is scripted, whatever planned the cut."""
    out, cuts = [], 0
    for step in getattr(goal, "steps", None) or []:
        if getattr(step, "kind", "cut") == "turn":
            if cuts == k:
                out.append(step)
        else:
            cuts += 1
            if cuts > k:
                break
    return out


def truncate_steps(steps, max_cuts: int) -> list:
    """The first ``max_cuts`` Cut steps of ``steps`` with the Turns between them (none after the last cut)."""
    out, cuts = [], 0
    for step in steps:
        if getattr(step, "kind", "cut") != "turn":
            if cuts == max_cuts:
                break
            cuts += 1
        out.append(step)
    while out and getattr(out[-1], "kind", "cut") == "turn":
        out.pop()
    return out


@runtime_checkable
class Task(Protocol):
    """What a task provides (module docstrings: Task, Randomisations, Success)."""

    name: str  # register_task: its config's name default unless the class states one
    # its parameters: a TaskConfig subclass holding only what the task reads (topocut.tasks.task_config builds it;
    # Hydra's task group is backed by it).  Optional: a class without one gets TaskConfig, a KnifeTask
    # KnifeTaskConfig, either with the class's ``defaults`` dict over it
    config: type
    tool: str  # "knife" | "pen" | "spoon": which scene the stages build (pipelines dispatch on it)
    stages: tuple  # the stages with a pipeline for this task (stage.name values)
    min_cuts: int  # the fewest task.max_cuts that makes a goal piece
    min_cuts_why: str  # why, for the config error naming task.max_cuts

    def make_goal(self, cfg, object: str, pose=None, spacing: float = 0.008, board_z: float = 0.05, seed: int = 0,
                  skin_thickness: float = 0.01):
        """The task's goal (a Goal for the knife tasks)."""

    def oracle(self, goal) -> list:
        """The ideal step sequence (Cut / Turn) for ``goal``."""

    def success(self, result, cfg) -> bool:
        """Episode success from a RewardResult."""


REGISTRY: dict[str, object] = {}  # task name -> the task object (register_task)


def register_task(cls):
    """Class decorator: the task ``cls`` (a Task) is known by ``cls.name`` to ``topocut.tasks.get_task``, and so to
    every stage.  A class that states no name takes its config's (``SliceConfig.name`` = "slice"), so that the
    name Hydra's task group composes and the registry's are one.  A second class under a taken name is refused
    (the same class re-imported replaces itself)."""
    if not getattr(cls, "name", ""):
        cls.name = getattr(getattr(cls, "config", None), "name", "")
    if not cls.name:
        raise ValueError(f"task class {cls.__module__}.{cls.__qualname__} has no name: set its config's name "
                         "default or the class's name")
    old = REGISTRY.get(cls.name)
    if old is not None and (type(old).__module__, type(old).__qualname__) != (cls.__module__, cls.__qualname__):
        raise ValueError(f"task name {cls.name!r} is taken by {type(old).__module__}.{type(old).__qualname__}")
    REGISTRY[cls.name] = cls()
    return cls


class KnifeTask(ABC):
    """Shared behaviour of the knife tasks (slice, stick, dice, pyramid); each defines ``pieces``."""

    name = ""  # register_task: the config's name unless the class states one
    config = KnifeTaskConfig  # a task with parameters of its own declares a subclass (SliceConfig, DiceConfig)
    tool = "knife"
    turns = False  # whose oracle lays pieces down between cut directions (Turn steps)
    stages = ("simulate", "mppi", "teleop", "merge", "pretrain", "bc", "eval", "all")
    min_cuts = 1
    min_cuts_why = "one cut makes the first piece"

    def make_goal(self, cfg, object: str, pose=None, spacing: float = 0.008, board_z: float = 0.05, seed: int = 0,
                  skin_thickness: float = 0.01) -> Goal:
        from topocut.metrics import fps
        from topocut.sim.objects import ObjectPose, object_sdf, sample_object
        from topocut.tasks import ideal
        from topocut.tasks.config import check_max_cuts

        cfg = cfg.validate()
        check_max_cuts(cfg.max_cuts, self)  # e.g. dice with 2 cuts cannot free a die
        pose = pose or ObjectPose()
        pts, _ = sample_object(object, pose, spacing, skin_thickness=skin_thickness, seed=seed, board_z=board_z)
        p64 = pts.astype(np.float64)
        axes = object_axes(p64, pose.yaw)
        pad = -object_sdf(object, p64, pose, board_z)  # each particle's depth below the surface
        steps, cells = self.pieces(cfg, p64, axes, pad, spacing, board_z)
        # what the plan's steps make (a cut that separates nothing, or only trims a sliver, is left out)
        sim_cfg = ideal.sim_config_for(spacing, board_z)
        if cfg.push:  # parallel cuts in the order whose pushes slide aside only what no later cut crosses
            steps = ideal.push_safe(p64, steps, sim_cfg)
        full_cell = int(np.bincount(cells)[1:].max()) if cells.max() > 0 else 0  # a full goal cell's particles
        steps, run = ideal.effective_steps(p64, steps, sim_cfg, min_cut_off=int(ideal.MIN_CUT_SHARE * full_cell))
        goal_ids, offcut_ids, _ = ideal.roles(run.piece, cells)
        if not goal_ids:
            from topocut.config import ConfigError  # a ValueError: the user's to fix (exit 2 from a stage)

            keys = [k for k in SIZE_KEYS if hasattr(cfg, k)]  # the sizes this task has
            sizes = ", ".join(f"task.{k}={getattr(cfg, k)}" for k in keys)
            raise ConfigError(f"task {self.name!r} produced no goal piece on {object!r} at particle spacing "
                              f"{spacing:.4g} ({sizes}): a piece must be thinner than the object "
                              f"({np.ptp(p64 @ axes[0]):.3f} along its longer axis) and at least {3 * spacing:.3f} "
                              f"(3 particle spacings) thick; set {'/'.join(f'task.{k}' for k in keys) or 'its size'} "
                              f"in that range, or a finer sim.n_grid")
        for anchor in run.anchors:  # the oracle tracks a cut by the goal pieces it makes (topocut.planning.oracle)
            anchor.goal = np.isin(run.piece[anchor.index], goal_ids)
        fragments = [pts[run.piece == p] for p in goal_ids]
        labels = np.zeros(len(pts), np.int32)  # 0 = not a goal piece, i + 1 = fragments[i]
        for i, p in enumerate(goal_ids):
            labels[run.piece == p] = i + 1
        keep = np.arange(len(pts))
        if 0 < cfg.num_goal_points < len(pts):
            keep = fps(p64, cfg.num_goal_points)
        planes = [s.action for s in steps if isinstance(s, Cut)]
        return Goal(fragments, planes, pts[keep], labels[keep], self.name, object, axes, steps,
                    offcuts=[pts[run.piece == p] for p in offcut_ids], anchors=run.anchors)

    @abstractmethod
    def pieces(self, cfg, pts, axes, pad, spacing, board_z):
        """The oracle's steps and each point's goal piece: (steps, labels (N,), 0 = not a goal piece)."""

    def oracle(self, goal: Goal) -> list:
        return list(goal.steps)

    def success(self, result, cfg) -> bool:
        """The one success of the knife tasks (docs/tasks.md#success): every goal piece made (N_C = G: each
        matched with d <= reward.success_distance) *and* the total at task.success_threshold, so that no
        episode whose waste ate its pieces' reward succeeds.  The episode flag, Table 1, the demonstrations'
        report and MPPI's stopping rule all call this."""
        G = len(getattr(result, "per_goal", []))
        return bool(G and result.cut_count >= G and result.total >= cfg.success_threshold)


# -- geometry ---------------------------------------------------------------------------------------------
def object_axes(points: np.ndarray, yaw: float) -> np.ndarray:
    """Rows (a1, a2, z): a1 the longer horizontal axis of the yawed object, a2 the other."""
    ex = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    ey = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
    ext = [np.ptp(points @ e) for e in (ex, ey)]
    a1, a2 = (ey, -ex) if ext[1] > 1.02 * ext[0] else (ex, ey)  # (a1, a2, z) stays right-handed
    return np.stack([a1, a2, np.array([0.0, 0.0, 1.0])])


def plane(normal, point, board_z) -> Cut:
    return Cut(KnifeAction.from_plane(normal, point, board_z))


def slices(pts, axes, step, count, board_z, pad):
    """Planes normal to axes[0] every ``step`` from the +end; (steps, piece labels (N,))."""
    s = pts @ axes[0]
    hi, lo = (s + pad).max(), s.min()
    labels = np.zeros(len(pts), np.int32)
    steps = []
    for i in range(1, count + 1):
        cut = hi - i * step
        if cut <= lo:  # the plane would miss the object: no further full piece
            break
        steps.append(plane(axes[0], pts.mean(0) + (cut - pts.mean(0) @ axes[0]) * axes[0], board_z))
        labels[(s > cut) & (s <= hi - (i - 1) * step)] = i
    return steps, labels


def first_slab(pts, axes, thickness, board_z, pad, key="task.thickness"):
    """The first slab (thickness off the +a1 face): (its Cut, mask (N,))."""
    steps, lab = slices(pts, axes, thickness, 1, board_z, pad)
    if not steps:
        from topocut.config import ConfigError  # a ValueError: the user's to fix (exit 2 from a stage)

        raise ConfigError(f"{key}={thickness} exceeds the object's extent ({np.ptp(pts @ axes[0]):.3f} along its "
                          f"longer axis); set {key} below it")
    return steps[0], lab == 1


def lay_flat(pts, slab, axes, board_z, gap: float = 0.02, beside: bool = False) -> Turn:
    """Turn the freed slab 90 deg about a2 so that its thickness is vertical (a1 -> +z, z -> -a1): its cut face
    (planar) on the board, its outer face up, its former height along a1, laid ``gap`` beyond the object.

    Cut face down, as a cook lays a slab: an end slab's outer face is a dome (a potato's, a burger's), and laid on
    it the slab rocks and settles tilted, so vertical cuts through it make sheared sticks and dice (dice / potato /
    3 at 128^3: a die of the goal's 451 particles, 55 x 30 mm from above with wedge-shaped ends, R 0; docs/tasks.md).

    ``beside``: also move it past the object's +a2 side (laid diagonally off the corner), so that cuts normal to
    a2 through the laid slab (dice's stick cuts) miss the rest of the object; cuts normal to a1 miss it anyway."""
    p = pts[slab]
    c = p.mean(0)
    a1, a2, z = axes
    far = (pts @ a1).max()  # the object's +a1 end (before the slab is taken away)
    height = np.ptp(p @ z)
    thick = np.ptp(p @ a1)
    target = c + (far + gap + height / 2 - c @ a1) * a1
    if beside:
        target = target + ((pts @ a2).max() + gap - (p @ a2).min()) * a2
    target = target - (target @ z) * z + (board_z + thick / 2) * z
    return Turn("slab", tuple(a2.tolist()), float(-np.pi / 2), tuple(c.tolist()), tuple(target.tolist()),
                note="lay the slab flat, cut face down: a1 -> +z, z -> -a1, about a2 through its centroid"
                + (", beside the object's +a2 side" if beside else ""))


def move_aside(pts, slab, axes, gap: float = 0.02) -> Turn:
    """Set the freed slab down, unturned, off the object's +a1/+a2 corner (``gap`` beyond the object along both):
    a cut normal to a2 (or a1) through it then misses the rest of the object.  A Turn by 0 deg about a2."""
    p = pts[slab]
    c = p.mean(0)
    a1, a2, _ = axes
    target = c + ((pts @ a1).max() + gap - (p @ a1).min()) * a1 + ((pts @ a2).max() + gap - (p @ a2).min()) * a2
    return Turn("slab", tuple(a2.tolist()), 0.0, tuple(c.tolist()), tuple(target.tolist()),
                note="move the standing slab off the object's +a1/+a2 corner, unturned")


def bands(values, start, step, count, sign=-1):
    """Band index 1..count of each value counting from ``start`` in direction ``sign`` (0 outside)."""
    k = np.floor((values - start) * sign / step).astype(np.int64) + 1  # 1 for the first band
    k[(k < 1) | (k > count)] = 0
    return k


def band_cuts(turned_or_world_point, normal, positions, board_z):
    """Cuts normal to ``normal`` through the points p0 + (pos - p0.n) n."""
    p0 = np.asarray(turned_or_world_point, np.float64)
    n = np.asarray(normal, np.float64)
    return [plane(n, p0 + (pos - p0 @ n) * n, board_z) for pos in positions]

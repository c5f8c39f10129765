"""Ideal goal pieces: the object's particles split by the task's ideal cutting planes.

Frame: the object's yaw gives two horizontal axes; a1 is the longer of the two
(by particle extent, ties within 2% go to the local x axis), a2 the other.
Coordinates s1, s2 are projections onto a1, a2; the cuts start at the +a1 / +a2 ends, whose
position is the object's face, max_j (s_j + depth_j) with depth_j = -object_sdf(x_j) (the lattice's
particles stop about half a spacing inside), so a piece of thickness t holds t / spacing layers.

  slice   : planes normal to a1 at s1max - i*thickness, i = 1..max_cuts; the slabs between
            consecutive planes are the goal pieces (one per cut).
  stick   : one slice plane at s1max - thickness, then planes normal to a2 at
            s2max - j*width, j = 1..max_cuts-1; goal pieces are the sticks
            slab ∩ band_j (thickness x width x the object's height).
  dice    : a stick task with thickness = width = size.  A downward knife makes only vertical
            or tilted planes, so on the resting object a die's top and bottom are the object's
            top and the board: the ideal die is a size x size prism of the object's height.
  pyramid : one tilted plane cuts the top (+a1, +a2, +z) corner off the object's bounding
            box: normal (a1 + a2 + z)/sqrt(3) (tilt = atan(1/sqrt 2) = 35.3 deg) through the
            three points at distance size from the corner along the edges.  The goal piece is
            the corner tetrahedron (volume size^3 / 6 for a box-shaped object).

Goal.labels: 0 for material outside every goal piece, i + 1 for goal piece i.
Goal.planes: KnifeActions in the order a heuristic controller should execute them.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from topocut.goals.config import TaskConfig
from topocut.sim.action import KnifeAction


@dataclass
class Goal:
    fragments: list  # [(m_i,3) f32] target pieces at particle resolution
    planes: list  # [KnifeAction] ideal cut sequence
    points: np.ndarray  # M,3 f32 the ideally cut object (FPS-downsampled to task.num_goal_points)
    labels: np.ndarray  # M, i32 0 = not a goal piece, i+1 = goal piece i
    task: str = "slice"
    object: str = ""
    axes: np.ndarray = field(default=None)  # 3,3 rows a1, a2, z (world)


def object_axes(points: np.ndarray, yaw: float) -> np.ndarray:
    """Rows (a1, a2, z): a1 the longer horizontal axis of the yawed object, a2 the other."""
    ex = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    ey = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
    ext = [np.ptp(points @ e) for e in (ex, ey)]
    a1, a2 = (ey, -ex) if ext[1] > 1.02 * ext[0] else (ex, ey)  # (a1, a2, z) stays right-handed
    return np.stack([a1, a2, np.array([0.0, 0.0, 1.0])])


def _plane(normal, point, board_z) -> KnifeAction:
    return KnifeAction.from_plane(normal, point, board_z)


def _slices(pts, axes, step, count, board_z, pad):
    """Planes normal to axes[0] every ``step`` from the +end; (planes, piece labels (N,))."""
    s = pts @ axes[0]
    hi, lo = (s + pad).max(), s.min()
    labels = np.zeros(len(pts), np.int32)
    planes = []
    for i in range(1, count + 1):
        cut = hi - i * step
        if cut <= lo:  # the plane would miss the object: no further full piece
            break
        planes.append(_plane(axes[0], pts.mean(0) + (cut - pts.mean(0) @ axes[0]) * axes[0], board_z))
        labels[(s > cut) & (s <= hi - (i - 1) * step)] = i
    return planes, labels


def _sticks(pts, axes, thickness, width, max_cuts, board_z, pad, key="task.thickness"):
    slab_planes, slab = _slices(pts, axes, thickness, 1, board_z, pad)
    if not slab_planes:
        raise ValueError(f"{key}={thickness} exceeds the object's extent")
    in_slab = slab == 1
    s2 = pts @ axes[1]
    hi, lo = (s2 + pad)[in_slab].max(), s2[in_slab].min()
    labels = np.zeros(len(pts), np.int32)
    planes = list(slab_planes)
    base = pts[in_slab].mean(0)  # the knife centred on the slab, so a finite blade cuts the slab first
    for j in range(1, max_cuts):
        cut = hi - j * width
        if cut <= lo:
            break
        planes.append(_plane(axes[1], base + (cut - base @ axes[1]) * axes[1], board_z))
        labels[in_slab & (s2 > cut) & (s2 <= hi - (j - 1) * width)] = j
    return planes, labels


def _pyramid(pts, axes, size, board_z, pad):
    local = pts @ axes.T  # N,3 coordinates along a1, a2, z
    corner_local = (local + pad[:, None]).max(0)
    corner = corner_local @ axes  # back to world (axes orthonormal)
    n = axes.sum(0) / np.sqrt(3.0)
    labels = ((pts - corner) @ n >= -size / np.sqrt(3.0)).astype(np.int32)
    return [_plane(n, corner - size * axes[0], board_z)], labels


def make_goal(task: TaskConfig | None, object: str, pose=None, spacing: float = 0.008, board_z: float = 0.05,
              seed: int = 0, skin_thickness: float = 0.01) -> Goal:
    """The ideal goal of ``task`` on ``object`` at ``pose`` (topocut.sim.objects.ObjectPose)."""
    from topocut.metrics import fps
    from topocut.sim.objects import ObjectPose, object_sdf, sample_object

    task = (task or TaskConfig()).validate()
    pose = pose or ObjectPose()
    pts, _ = sample_object(object, pose, spacing, skin_thickness=skin_thickness, seed=seed, board_z=board_z)
    p64 = pts.astype(np.float64)
    axes = object_axes(p64, pose.yaw)
    # each particle's depth below the surface: max(s + depth) is the object's face position along s
    pad = -object_sdf(object, p64, pose, board_z)  # N,
    if task.name == "slice":
        planes, labels = _slices(p64, axes, task.thickness, task.max_cuts, board_z, pad)
    elif task.name == "stick":
        planes, labels = _sticks(p64, axes, task.thickness, task.width, task.max_cuts, board_z, pad)
    elif task.name == "dice":
        planes, labels = _sticks(p64, axes, task.size, task.size, task.max_cuts, board_z, pad, key="task.size")
    elif task.name == "pyramid":
        planes, labels = _pyramid(p64, axes, task.size, board_z, pad)
    else:
        raise ValueError(f"task.name={task.name!r} has no knife goal; valid: slice, stick, dice, pyramid")
    ids = [i for i in range(1, labels.max(initial=0) + 1) if (labels == i).any()]
    if not ids:
        raise ValueError(f"task {task.name!r} produced no goal piece on {object!r} at spacing {spacing}: "
                         f"increase task.thickness/width/size or decrease spacing")
    fragments = [pts[labels == i] for i in ids]
    remap = np.zeros(labels.max() + 1, np.int32)  # a plane that caught no particle leaves an empty label:
    remap[ids] = np.arange(1, len(ids) + 1)  # renumber so that label i + 1 is fragments[i]
    labels = remap[labels]
    keep = np.arange(len(pts))
    if 0 < task.num_goal_points < len(pts):
        keep = fps(p64, task.num_goal_points)
    return Goal(fragments, planes, pts[keep], labels[keep].astype(np.int32), task.name, object, axes)

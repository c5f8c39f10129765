"""What a learned policy's action means: the pose-consistent cut mask, and the plane of a previous cut.

**The mask label** (docs/policy.md#mask-label).  A cut plane has two sides and a mask names one of them 1.  The
plane-side mask stored in a dataset (``topocut.sim.action.cut_mask``: 1 on the +n side of the *canonical*
plane) flips with the pose: the canonical yaw wraps at +-90 deg, so the stick task's width cut (normal along
the object's a2 axis, i.e. world yaw ~ 90 deg at object yaw 0) is 1 on the stick side at object yaw -1 deg and 0
at +1 deg.  A policy trained on it learns complementary labels for the same cut.  The policy's label is
instead oriented in the frame of the goal, which turns with the object:

    u  = the horizontal direction from the goal cloud's centroid to the centroid of its goal-piece points
         (labels > 0), unit; world +x when the goal has no goal piece or the two centroids coincide
    v  = z x u  (u, v, z right-handed)
    r  = (u + v) / sqrt(2)   the reference direction
    mask_j = 1  iff  n_r . (x_j - p0) > 0,  with n_r = +-n the plane's normal oriented so that n_r . r >= 0.

So a cut across u (a slab cut: normal along the direction of the goal pieces) is 1 on the goal-piece side, and
a cut along u (a stick cut: normal along v) is 1 on its +v side, at every pose: u and every cut of the task
turn together with the object.  The rule's one discontinuity (n_r . r = 0, unavoidable for an undirected
plane) lies at 45 deg between the two cut families of slice, stick and dice in the goal frame, and opposite
the pyramid's diagonal cut (whose normal points along u).  u follows the goal pieces' centroid, not the
object's a1 axis: off-centre goal pieces turn it (the cube's corner dice by 37 deg, the cube's sticks by 22
deg; 0-8 deg for slices, sticks and dice of the other objects, measured over 3 random poses each), which is what
the margin to the discontinuity (45 deg minus that angle) absorbs.  Everything the rule reads -- the goal cloud
and its labels -- is a policy input, so the label is a function of what the network sees.

**The plane of the previous cut** recovers the knife plane from an action-history row (``pose_feature``:
board point and quaternion); ``previous_plane_mask`` is that plane's mask under the same rule, the
"plane-from-previous-cut" floor of ``val/mask_acc_prev_plane`` (docs/policy.md#metrics-and-their-floors).

Pure numpy (no torch), as topocut.sim.action.
"""
from __future__ import annotations

import numpy as np

from topocut.sim.action import POSE_FEATURE_DIM, KnifeAction, signed_distance_to_plane

REFERENCE_TURN = np.pi / 4  # r = u turned by 45 deg towards v


def goal_frame(goal_points, goal_labels=None) -> np.ndarray:
    """Rows (u, v, z) of the goal frame (module docstring); u from the goal-piece centroid, world +x without one."""
    g = np.asarray(goal_points, np.float64).reshape(-1, 3)
    lab = np.zeros(len(g), np.int64) if goal_labels is None else np.asarray(goal_labels).reshape(-1)
    if len(lab) != len(g):
        raise ValueError(f"goal points ({len(g)}) and goal labels ({len(lab)}) differ in length")
    u = np.array([1.0, 0.0, 0.0])
    piece = lab > 0
    if piece.any() and len(g):
        d = g[piece].mean(0) - g.mean(0)
        d[2] = 0.0
        norm = float(np.linalg.norm(d))
        if norm > 1e-9:
            u = d / norm
    return np.stack([u, np.array([-u[1], u[0], 0.0]), np.array([0.0, 0.0, 1.0])])


def reference_direction(goal_points, goal_labels=None) -> np.ndarray:
    """r = (u + v) / sqrt(2): the mask is 1 on the side of a cut plane that r points to."""
    u, v, _ = goal_frame(goal_points, goal_labels)
    return np.cos(REFERENCE_TURN) * u + np.sin(REFERENCE_TURN) * v


def side_sign(action: KnifeAction, reference) -> float:
    """+1 when the canonical normal of ``action`` points to ``reference``'s side (n . r >= 0), else -1."""
    n = action.canonical().normal
    return 1.0 if float(n @ np.asarray(reference, np.float64)) >= 0.0 else -1.0


def action_mask(points, action: KnifeAction, goal_points, goal_labels=None, board_z: float = 0.05) -> np.ndarray:
    """The policy's mask label (N,) uint8 of ``action`` over ``points``: 1 on the reference side of its plane."""
    a = action.canonical()
    s = side_sign(a, reference_direction(goal_points, goal_labels))
    return (s * signed_distance_to_plane(points, a, board_z) > 0).astype(np.uint8)


def orient_mask(plane_mask, action: KnifeAction, goal_points, goal_labels=None) -> np.ndarray:
    """A stored plane-side mask (``cut_mask``: 1 on the canonical +n side) turned into the policy's label:
    unchanged when the canonical normal already points to the reference side, complemented otherwise."""
    m = np.asarray(plane_mask).astype(np.uint8)
    return m if side_sign(action, reference_direction(goal_points, goal_labels)) > 0 else (1 - m).astype(np.uint8)


def action_from_pose_feature(feature, board_z: float = 0.05) -> KnifeAction | None:
    """The cut whose ``pose_feature`` (board point, quaternion w x y z) is ``feature`` (7,); None for a zero
    row (the history's padding before the first cut)."""
    f = np.asarray(feature, np.float64).reshape(-1)
    if f.shape[0] != POSE_FEATURE_DIM:
        raise ValueError(f"a pose feature has {POSE_FEATURE_DIM} entries (x, y, z, qw, qx, qy, qz), got {f.shape[0]}")
    if not np.abs(f[3:]).sum() > 0:
        return None
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_quat([f[4], f[5], f[6], f[3]]).as_matrix()  # scipy: x, y, z, w
    try:
        return KnifeAction.from_plane(rot[:, 2], f[:3], board_z)  # column 3 of KnifeAction.rotation(): n
    except ValueError:  # a horizontal plane: no knife pose
        return None


def previous_action(history, board_z: float = 0.05) -> KnifeAction | None:
    """The last cut of an action history (h,7), oldest first; None before the first cut."""
    h = np.asarray(history, np.float64).reshape(-1, POSE_FEATURE_DIM)
    return action_from_pose_feature(h[-1], board_z) if len(h) else None


def previous_plane_mask(points, history, goal_points, goal_labels=None, board_z: float = 0.05) -> np.ndarray | None:
    """The mask of the previous cut's plane over the current ``points`` (the policy's label rule); None before
    the first cut."""
    prev = previous_action(history, board_z)
    if prev is None:
        return None
    return action_mask(points, prev, goal_points, goal_labels, board_z)

"""Knife actions, cut planes, cut masks and swept volumes.

Pure numpy (no Taichi import) so that planners, datasets and policies can use
it without starting a simulator.

Scene convention (see docs/architecture.md): the simulation domain is the unit
cube [0, 1]^3, z points up, gravity is -z, the cutting board's top face is the
plane z = board_z (SimConfig.board_z, 0.05 by default).

A cut is parameterised by the knife's start pose.  The blade is a thin
rectangle; its plane has unit normal

    n(yaw, tilt) = (cos(yaw) cos(tilt), sin(yaw) cos(tilt), sin(tilt))

and passes through the board point p0 = (x, y, board_z).  The blade's long
axis u = (-sin(yaw), cos(yaw), 0) is horizontal; its travel direction
w = -(n x u) (unit; n x u points up for |tilt| < pi/2, so w points down into the board) lies in the
blade plane, so the knife always moves parallel to its own blade.

Canonical form: yaw in (-pi/2, pi/2] and tilt in (-pi/2, pi/2), so that every
cut plane has exactly one action.  The *cut mask* of an action over a point
set is the half-space indicator  mask_j = 1  iff  n . (x_j - p0) > 0,
i.e. the points on the +n side of the plane (see docs/data.md).  A linear
classifier fitted to a mask therefore recovers the plane, and hence the action.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

ACTION_DIM = 4  # x, y, yaw, tilt
POSE_FEATURE_DIM = 7  # position (3) + quaternion wxyz (4), used for action history


def _wrap_half_pi(yaw: float, tilt: float) -> tuple[float, float, bool]:
    """Map (yaw, tilt) to canonical range; return flipped=True if n changed sign."""
    yaw = float(np.arctan2(np.sin(yaw), np.cos(yaw)))  # (-pi, pi]
    flipped = False
    if yaw <= -np.pi / 2 or yaw > np.pi / 2:
        yaw = yaw - np.pi if yaw > 0 else yaw + np.pi
        tilt = -tilt
        flipped = True
    return yaw, float(tilt), flipped


@dataclass(frozen=True)
class KnifeAction:
    """One cut: the blade plane through (x, y, board_z) with normal n(yaw, tilt).

    ``z_start`` is the height of the blade's lower edge when the cut begins
    (None: the simulator starts just above the object) and ``depth`` how far
    the knife travels along w (None: down to the board).
    """

    x: float
    y: float
    yaw: float = 0.0
    tilt: float = 0.0
    z_start: float | None = None
    depth: float | None = None

    # -- geometry -----------------------------------------------------------
    def canonical(self) -> KnifeAction:
        yaw, tilt, _ = _wrap_half_pi(self.yaw, self.tilt)
        return KnifeAction(self.x, self.y, yaw, tilt, self.z_start, self.depth)

    @property
    def normal(self) -> np.ndarray:  # 3,
        cy, sy, ct, st = np.cos(self.yaw), np.sin(self.yaw), np.cos(self.tilt), np.sin(self.tilt)
        return np.array([cy * ct, sy * ct, st], dtype=np.float64)

    @property
    def blade_axis(self) -> np.ndarray:  # 3, u: along the blade's length
        return np.array([-np.sin(self.yaw), np.cos(self.yaw), 0.0], dtype=np.float64)

    @property
    def travel(self) -> np.ndarray:  # 3, w: direction of motion, in the blade plane, downwards
        w = np.cross(self.normal, self.blade_axis)
        return w if w[2] <= 0 else -w

    def plane_point(self, board_z: float = 0.05) -> np.ndarray:  # 3,
        return np.array([self.x, self.y, board_z], dtype=np.float64)

    def rotation(self) -> np.ndarray:  # 3,3 columns: u, up-in-plane (-w), n
        u, w, n = self.blade_axis, self.travel, self.normal
        return np.stack([u, -w, n], axis=1)

    def to_matrix(self, board_z: float = 0.05) -> np.ndarray:  # 4,4 SE(3) pose of the plane frame
        T = np.eye(4)
        T[:3, :3] = self.rotation()
        T[:3, 3] = self.plane_point(board_z)
        return T

    def shifted(self, offset: float) -> KnifeAction:
        """The same cut with its plane moved ``offset`` along the normal: the board point moves offset / |n_xy|
        horizontally along n_xy / |n_xy| (a tilted plane's board line moves further than the plane does)."""
        n = self.normal
        h2 = float(n[0] ** 2 + n[1] ** 2)
        return replace(self, x=self.x + offset * n[0] / h2, y=self.y + offset * n[1] / h2)

    def to_vector(self) -> np.ndarray:  # ACTION_DIM,
        return np.array([self.x, self.y, self.yaw, self.tilt], dtype=np.float32)

    @classmethod
    def from_vector(cls, v) -> KnifeAction:
        v = np.asarray(v, dtype=np.float64).reshape(-1)
        if v.shape[0] != ACTION_DIM:
            raise ValueError(f"action vector must have {ACTION_DIM} entries (x, y, yaw, tilt), got {v.shape[0]}")
        return cls(float(v[0]), float(v[1]), float(v[2]), float(v[3])).canonical()

    @classmethod
    def from_plane(cls, normal, point, board_z: float = 0.05) -> KnifeAction:
        """The canonical action whose plane is {x : normal . (x - point) = 0}.

        Raises ValueError for a horizontal plane, which no downward cut can make.
        """
        n = np.asarray(normal, dtype=np.float64)
        n = n / np.linalg.norm(n)
        p = np.asarray(point, dtype=np.float64)
        h = np.hypot(n[0], n[1])
        if h < 1e-6:
            raise ValueError("a horizontal cutting plane cannot be reached by a downward knife")
        yaw = float(np.arctan2(n[1], n[0]))
        tilt = float(np.arctan2(n[2], h))
        yaw, tilt, flipped = _wrap_half_pi(yaw, tilt)
        if flipped:
            n = -n
        # the board point of the plane closest to `point` along the horizontal normal direction
        nh = n[:2] / h
        # solve n . ((x, y, board_z) - p) = 0 with (x, y) = p_xy + s * nh
        s = -(n[2] * (board_z - p[2])) / h
        xy = p[:2] + s * nh
        return cls(float(xy[0]), float(xy[1]), yaw, tilt)

    def pose_feature(self, board_z: float = 0.05) -> np.ndarray:  # 7, position + quaternion (w, x, y, z)
        from scipy.spatial.transform import Rotation

        q = Rotation.from_matrix(self.rotation()).as_quat()  # x, y, z, w
        return np.concatenate([self.plane_point(board_z), [q[3], q[0], q[1], q[2]]]).astype(np.float32)

    def asdict(self) -> dict:
        return asdict(self)


def signed_distance_to_plane(points, action: KnifeAction, board_z: float = 0.05) -> np.ndarray:
    """n . (x - p0) for each point; points (N,3) -> (N,)."""
    pts = np.asarray(points, dtype=np.float64)
    return (pts - action.plane_point(board_z)) @ action.normal


def cut_mask(points, action: KnifeAction, board_z: float = 0.05) -> np.ndarray:
    """Half-space cut mask (N,) uint8: 1 on the +n side of the canonical plane."""
    a = action.canonical()
    return (signed_distance_to_plane(points, a, board_z) > 0).astype(np.uint8)


PLANE_CLEAR = 1e-5  # a float32 signed distance beyond this is on its float64 side (rounding < 1e-6 in the unit box)


def plane_splits(points, action: KnifeAction, board_z: float = 0.05) -> bool:
    """Whether ``cut_mask`` of ``points`` (N,3) is neither all 0 nor all 1 (the plane has points on both sides).

    A float32 pass decides where the points' extremes are clear of the plane by PLANE_CLEAR (every cut through the
    object: no float64 copy of N points); otherwise ``cut_mask`` itself decides, so the answer is always its."""
    pts = np.asarray(points)
    if pts.dtype == np.float32 and len(pts):
        a = action.canonical()
        normal = np.asarray(a.normal, np.float64)
        d = pts @ normal.astype(np.float32) - np.float32(np.dot(a.plane_point(board_z), normal))  # N,
        lo, hi = float(d.min()), float(d.max())
        if lo < -PLANE_CLEAR and hi > PLANE_CLEAR:
            return True
        if hi < -PLANE_CLEAR or lo > PLANE_CLEAR:
            return False
    m = cut_mask(pts, action, board_z)
    return bool(0 < m.sum() < len(m))


@dataclass(frozen=True)
class KnifeSweep:
    """The volume the blade swept during one cut: an oriented box.

    {p : |n.(p-o)| <= half_thickness, |u.(p-o)| <= half_length, 0 <= w.(p-o) <= depth}
    with o the blade's lower-edge midpoint at the start of the cut.
    """

    origin: tuple  # 3,
    u: tuple  # 3, blade long axis (unit)
    w: tuple  # 3, travel direction (unit)
    n: tuple  # 3, blade normal (unit)
    half_length: float
    depth: float
    half_thickness: float

    def as_arrays(self):
        return (np.asarray(self.origin, float), np.asarray(self.u, float),
                np.asarray(self.w, float), np.asarray(self.n, float))

    def sdf(self, points) -> np.ndarray:
        """Signed distance (N,) from points (N,3) to the swept box (negative inside)."""
        o, u, w, n = self.as_arrays()
        d = np.asarray(points, float) - o
        # box centre along w is depth/2
        local = np.stack([d @ u, d @ w - self.depth / 2.0, d @ n], axis=-1)
        half = np.array([self.half_length, self.depth / 2.0, self.half_thickness])
        q = np.abs(local) - half
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
        inside = np.minimum(np.max(q, axis=-1), 0.0)
        return outside + inside

    def contains(self, points) -> np.ndarray:
        return self.sdf(points) <= 0.0

    def asdict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    @classmethod
    def fromdict(cls, d: dict) -> KnifeSweep:
        return cls(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items()})


def executed_action(action: KnifeAction) -> KnifeAction:
    """The knife pose that runs for a policy's ``action``: the one rule of demonstrations, evaluation and teleop
    replay (topocut.planning.rollout.run_episode, topocut.eval.protocol.evaluate_episode, TeleopSession.cut).

    The canonical action that its own float32 vector (``to_vector``: what MPPI's rollouts evaluate, a dataset
    record and an evaluation episode store, and a teleop log holds) maps back to exactly, so that what runs, what
    is stored and its pose all agree.  Rounding to float32 can move a yaw across the canonical range's end:
    float32(pi/2) > pi/2 wraps to about -pi/2 with the normal reversed (the plane-side mask inverted), so the
    vector is re-read until it is stable (at most twice).  z_start and depth, which the vector does not hold,
    are kept.  Idempotent: ``executed_action(executed_action(a)) == executed_action(a)``.
    """
    from dataclasses import replace

    v = action.to_vector()
    for _ in range(4):
        quantized = KnifeAction.from_vector(v)
        w = quantized.to_vector()
        if np.array_equal(w, v):
            break
        v = w
    return replace(quantized, z_start=action.z_start, depth=action.depth)

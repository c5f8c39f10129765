"""Procedural objects: signed distance functions and particle sampling.

Pure numpy.  Every shape is written in a local frame (x, y centred on 0, bottom
face on z = 0, sizes in scene units); ``ObjectPose`` scales it, turns it about
z by ``yaw`` (radians) and places its bottom centre at (x, y, board_z).
Every shape is intersected with the half-space z >= 0 so it rests flat on the
cutting board.

Particles fill the inside on a jittered lattice (spacing ``spacing``); those
within ``skin_thickness`` of the surface get material 1 (von Mises skin), the
rest material 0 (plasto-elastic core).  See docs/sim.md for a picture.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

OBJECTS = ("cake", "cube", "ditto", "ham", "potato", "donut", "burger", "sushi", "steak", "tomato")
SEEN = ("cake", "cube", "ditto", "ham", "potato")
UNSEEN = ("donut", "burger", "sushi", "steak")
BOARD_Z = 0.05
CORE, SKIN = 0, 1


@dataclass(frozen=True)
class ObjectPose:
    x: float = 0.5
    y: float = 0.5
    yaw: float = 0.0  # radians, about +z
    scale: float = 1.0


def random_pose(rng: np.random.Generator, translation: float = 0.03, yaw_deg: float = 15.0,
                scale=(0.8, 1.2)) -> ObjectPose:
    """Uniform translation (± translation about (0.5, 0.5)), yaw (± yaw_deg) and scale in [scale[0], scale[1]]."""
    lo, hi = float(scale[0]), float(scale[1])
    if lo > hi or lo <= 0:
        raise ValueError(f"scale range must satisfy 0 < min <= max, got {scale}")
    return ObjectPose(x=0.5 + float(rng.uniform(-translation, translation)),
                      y=0.5 + float(rng.uniform(-translation, translation)),
                      yaw=float(np.deg2rad(rng.uniform(-yaw_deg, yaw_deg))),
                      scale=float(rng.uniform(lo, hi)))


# -- SDF primitives (p: N,3 local coordinates) --------------------------------
def _box(p, half):  # exact
    q = np.abs(p) - np.asarray(half)
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(-1), 0.0)


def _round_box(p, half, r):  # exact: a box shrunk by r, inflated by r
    return _box(p, np.asarray(half) - r) - r


def _cylinder(p, radius, half_h, r=0.0):  # z-axis cylinder centred on 0, edges rounded by r (exact)
    d = np.stack([np.linalg.norm(p[:, :2], axis=-1) - (radius - r), np.abs(p[:, 2]) - (half_h - r)], -1)
    return np.linalg.norm(np.maximum(d, 0.0), axis=-1) + np.minimum(d.max(-1), 0.0) - r


def _sphere(p, radius):
    return np.linalg.norm(p, axis=-1) - radius


def _ellipsoid(p, radii):  # Quilez's bound: exact on the axes, close elsewhere
    r = np.asarray(radii)
    k0 = np.linalg.norm(p / r, axis=-1)
    k1 = np.linalg.norm(p / (r * r), axis=-1)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)


def _torus(p, major, minor):
    q = np.stack([np.linalg.norm(p[:, :2], axis=-1) - major, p[:, 2]], -1)
    return np.linalg.norm(q, axis=-1) - minor


def _smin(a, b, k):  # polynomial smooth union
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b * (1 - h) + a * h - k * h * (1 - h)


def _at(p, z):  # shift the local frame up by z
    return p - np.array([0.0, 0.0, z])


# -- shapes (local frame, bottom on z = 0) -------------------------------------
def _cake(p):
    return _cylinder(_at(p, 0.05), 0.10, 0.05, r=0.005)


def _cube(p):
    return _box(_at(p, 0.08), (0.08, 0.08, 0.08))


def _ditto(p):  # a blob: smooth union of a body and two lobes
    body = _ellipsoid(_at(p, 0.045), (0.11, 0.085, 0.065))
    lobe1 = _ellipsoid(p - np.array([0.06, 0.04, 0.06]), (0.05, 0.045, 0.04))
    lobe2 = _ellipsoid(p - np.array([-0.065, -0.03, 0.055]), (0.045, 0.05, 0.035))
    return _smin(_smin(body, lobe1, 0.03), lobe2, 0.03)


def _ham(p):  # rounded loaf
    return _round_box(_at(p, 0.055), (0.12, 0.075, 0.055), 0.03)


def _potato(p):  # ellipsoid with a low-frequency bumpy surface
    q = _at(p, 0.06)
    bump = 0.006 * np.sin(31 * q[:, 0]) * np.cos(27 * q[:, 1]) + 0.004 * np.sin(23 * q[:, 2] + 17 * q[:, 0])
    return _ellipsoid(q, (0.12, 0.08, 0.07)) + bump


def _donut(p):
    return _torus(_at(p, 0.04), 0.085, 0.04)


def _burger(p):  # bottom bun, patty, dome-topped bun
    bottom = _cylinder(_at(p, 0.02), 0.10, 0.02, r=0.01)
    patty = _cylinder(_at(p, 0.055), 0.107, 0.016, r=0.008)
    top = _ellipsoid(_at(p, 0.07), (0.10, 0.10, 0.065))
    top = np.maximum(top, -(p[:, 2] - 0.071))  # keep the dome above the patty
    return np.minimum(np.minimum(bottom, patty), top)


def _sushi(p):  # rice block with an ellipsoidal slice of fish on top
    rice = _round_box(_at(p, 0.035), (0.085, 0.045, 0.035), 0.015)
    fish = _ellipsoid(_at(p, 0.07), (0.11, 0.055, 0.022))
    return _smin(rice, fish, 0.01)


def _steak(p):  # flat slab with an irregular outline and rounded rim
    q = _at(p, 0.025)
    th = np.arctan2(q[:, 1] / 0.09, q[:, 0] / 0.13)
    wobble = 1.0 + 0.08 * np.sin(3 * th + 0.4) + 0.05 * np.cos(5 * th)
    rxy = np.linalg.norm(q[:, :2] / np.array([0.13, 0.09]), axis=-1)
    d2 = (rxy - wobble) * 0.09  # approximate planar distance (scaled by the short radius)
    d = np.stack([d2 + 0.01, np.abs(q[:, 2]) - 0.015], -1)
    return np.linalg.norm(np.maximum(d, 0.0), axis=-1) + np.minimum(d.max(-1), 0.0) - 0.01


def _tomato(p):  # a slightly flattened sphere
    return _ellipsoid(_at(p, 0.078), (0.1, 0.1, 0.085))


_SHAPES = {"cake": _cake, "cube": _cube, "ditto": _ditto, "ham": _ham, "potato": _potato, "donut": _donut,
           "burger": _burger, "sushi": _sushi, "steak": _steak, "tomato": _tomato}
# local bounding half-extent in x/y and height, for the sampling lattice (generous)
_EXTENT = {"cake": (0.11, 0.11), "cube": (0.12, 0.17), "ditto": (0.13, 0.13), "ham": (0.13, 0.12),
           "potato": (0.14, 0.15), "donut": (0.13, 0.09), "burger": (0.12, 0.14), "sushi": (0.12, 0.1),
           "steak": (0.16, 0.06), "tomato": (0.11, 0.17)}


def _check_name(name: str) -> None:
    if name not in _SHAPES:
        raise KeyError(f"unknown object {name!r}; valid: {', '.join(OBJECTS)}")


def object_sdf(name: str, points, pose: ObjectPose | None = None, board_z: float = BOARD_Z) -> np.ndarray:
    """Signed distance (N,) of world points (N,3) to the posed object (negative inside)."""
    _check_name(name)
    pose = pose or ObjectPose()
    p = np.asarray(points, np.float64).reshape(-1, 3) - np.array([pose.x, pose.y, board_z])  # N,3
    c, s = np.cos(pose.yaw), np.sin(pose.yaw)
    local = np.stack([c * p[:, 0] + s * p[:, 1], -s * p[:, 0] + c * p[:, 1], p[:, 2]], -1) / pose.scale
    d = _SHAPES[name](local)
    return np.maximum(d, -local[:, 2]) * pose.scale  # flat bottom on the board


def sample_sdf(sdf, lo, hi, spacing: float, skin_thickness: float = 0.01, seed: int = 0, jitter: float = 0.25):
    """Jittered-lattice particles inside ``sdf`` within the box [lo, hi].

    The lattice starts half a spacing inside ``lo`` so a body whose bottom is
    at lo[2] gets particles from lo[2] + spacing/2.  Each point moves by a
    uniform jitter of ± jitter*spacing per axis.  Returns (points (N,3) f32,
    material (N,) i32) with material SKIN where sdf > -skin_thickness.
    """
    if spacing <= 0:
        raise ValueError(f"spacing must be > 0, got {spacing}")
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    axes = [np.arange(lo[d] + spacing / 2, hi[d], spacing) for d in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)  # M,3
    rng = np.random.default_rng(seed)
    grid = grid + rng.uniform(-jitter * spacing, jitter * spacing, grid.shape)
    grid[:, 2] = np.maximum(grid[:, 2], lo[2] + 1e-6)
    d = sdf(grid)
    inside = d < 0
    pts = grid[inside].astype(np.float32)
    material = np.where(d[inside] > -skin_thickness, SKIN, CORE).astype(np.int32)
    return pts, material


def sample_object(name: str, pose: ObjectPose | None = None, spacing: float = 0.008, skin_thickness: float = 0.01,
                  seed: int = 0, board_z: float = BOARD_Z):
    """Particles (N,3) f32 and materials (N,) i32 of the posed object resting on z = board_z."""
    _check_name(name)
    pose = pose or ObjectPose()
    rxy, h = _EXTENT[name]
    r = rxy * pose.scale * np.sqrt(2.0)  # any yaw stays inside
    lo = np.array([pose.x - r, pose.y - r, board_z])
    hi = np.array([pose.x + r, pose.y + r, board_z + h * pose.scale])
    return sample_sdf(lambda q: object_sdf(name, q, pose, board_z), lo, hi, spacing, skin_thickness, seed)

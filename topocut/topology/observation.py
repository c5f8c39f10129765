"""What the robot sees: noisy depth views of the particles -> a reconstructed solid -> M labelled points.

mode "particles": FPS over the ground-truth particles (privileged observation).
mode "depth": the paper assumes only noisy surface observations, so
  1. render a depth image per camera (particles splatted as discs into a z-buffer),
  2. add Gaussian depth noise and back-project the pixels to a surface point cloud,
  3. reconstruct a closed solid by space carving: a voxel above the board is free if some
     camera sees through it (its pixel shows background, or a surface farther away than the voxel
     by more than the noise margin); what no camera sees through is solid (bounded by the board),
  4. sample points in the solid (interior and boundary), farthest-point sample M of them,
  5. label each point with the cluster id of the nearest ground-truth particle.
Pure numpy/scipy (no Warp): cheap enough to run on every step.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

MODES = ("particles", "depth")


@dataclass
class ObservationConfig:
    mode: str = "particles"  # "particles" | "depth"
    num_points: int = 2048  # M
    image_width: int = 160
    image_height: int = 120
    fov_deg: float = 50.0  # vertical field of view of the pinhole camera
    noise_std: float = 0.001  # Gaussian depth noise (scene units)
    views: int = 4  # cameras on a circle around the board (plus one on top if top_view)
    top_view: bool = True
    elevation_deg: float = 55.0
    camera_distance: float = 0.6
    target: list = field(default_factory=lambda: [0.5, 0.5, 0.08])  # point the cameras look at
    splat_radius: float = 0.0  # disc radius of a particle; 0: 0.75 x median particle spacing
    voxel_size: float = 0.004  # space-carving grid
    noise_margin: float = 3.0  # free-space test tolerance, in noise_std (+ half a voxel)
    board_z: float = 0.05

    def validate(self) -> ObservationConfig:
        if self.mode not in MODES:
            raise ValueError(f"observation.mode {self.mode!r} unknown; valid: {', '.join(MODES)}")
        if self.num_points < 1:
            raise ValueError(f"observation.num_points must be >= 1, got {self.num_points}")
        if self.mode == "depth" and self.views + int(self.top_view) < 1:
            raise ValueError("observation.views (+ top_view) must give at least one camera")
        if self.voxel_size <= 0 or self.noise_std < 0:
            raise ValueError("observation.voxel_size must be > 0 and observation.noise_std >= 0")
        return self


# --- farthest point sampling -----------------------------------------------------------------------
def _fps(points: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """Farthest point sampling -> indices (min(n, N),); topocut.metrics.fps when present."""
    n = min(int(n), len(points))
    try:
        from topocut.metrics import fps  # the project-wide implementation
    except ImportError:
        return _fps_numpy(points, n, seed)
    return np.asarray(fps(points, n, seed=seed), np.int64)


def _fps_numpy(points: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """Fallback FPS, starting from a seeded random point."""
    pts = np.asarray(points, np.float64)
    n = min(int(n), len(pts))
    idx = np.empty(n, np.int64)
    idx[0] = np.random.default_rng(seed).integers(len(pts))
    d = np.linalg.norm(pts - pts[idx[0]], axis=1)
    for i in range(1, n):
        idx[i] = int(np.argmax(d))
        d = np.minimum(d, np.linalg.norm(pts - pts[idx[i]], axis=1))
    return idx


# --- cameras ---------------------------------------------------------------------------------------
@dataclass
class Camera:
    R: np.ndarray  # 3,3 world -> camera rotation (rows: right, down, forward)
    t: np.ndarray  # 3, camera centre in world
    f: float  # focal length in pixels
    width: int
    height: int

    def project(self, pts):  # N,3 -> (u, v, depth) each N,
        c = (np.asarray(pts, np.float64) - self.t) @ self.R.T
        z = c[:, 2]
        zs = np.where(z > 1e-9, z, np.nan)
        return self.f * c[:, 0] / zs + self.width / 2.0, self.f * c[:, 1] / zs + self.height / 2.0, z

    def unproject(self, u, v, depth):  # pixel centres + depth -> N,3 world
        c = np.stack([(u - self.width / 2.0) * depth / self.f, (v - self.height / 2.0) * depth / self.f, depth], 1)
        return c @ self.R + self.t


def _look_at(eye, target, width, height, fov_deg) -> Camera:
    fwd = np.asarray(target, float) - eye
    fwd /= np.linalg.norm(fwd)
    up = np.array([0.0, 0.0, 1.0]) if abs(fwd[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    f = (height / 2.0) / np.tan(np.radians(fov_deg) / 2.0)
    return Camera(np.stack([right, down, fwd]), np.asarray(eye, float), float(f), width, height)


def make_cameras(cfg: ObservationConfig) -> list[Camera]:
    tgt = np.asarray(cfg.target, float)
    eyes = []
    el = np.radians(cfg.elevation_deg)
    for k in range(cfg.views):
        az = 2 * np.pi * k / max(cfg.views, 1) + np.pi / 4
        eyes.append(tgt + cfg.camera_distance * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]))
    if cfg.top_view:
        eyes.append(tgt + np.array([0.0, 0.0, cfg.camera_distance]))
    return [_look_at(e, tgt, cfg.image_width, cfg.image_height, cfg.fov_deg) for e in eyes]


# --- rendering ---------------------------------------------------------------------------------------
def render_depth(x: np.ndarray, cam: Camera, radius: float) -> np.ndarray:
    """Depth image (H,W) of particles splatted as discs of ``radius``; np.inf = background."""
    u, v, z = cam.project(x)
    ok = np.isfinite(u) & (z > radius)
    u, v, z = u[ok], v[ok], z[ok]
    if not len(z):  # nothing in front of the camera
        return np.full((cam.height, cam.width), np.inf)
    rp = np.maximum(cam.f * radius / z, 0.5)  # N, disc radius in pixels (at least half a pixel: no holes)
    reach = int(np.ceil(rp.max()))
    img = np.full(cam.height * cam.width, np.inf)
    front = z - radius  # the sphere's near side
    for du in range(-reach, reach + 1):
        for dv in range(-reach, reach + 1):
            pu, pv = np.floor(u).astype(np.int64) + du, np.floor(v).astype(np.int64) + dv
            hit = ((pu + 0.5 - u) ** 2 + (pv + 0.5 - v) ** 2 <= rp ** 2) & (pu >= 0) & (pu < cam.width) \
                & (pv >= 0) & (pv < cam.height)
            np.minimum.at(img, pv[hit] * cam.width + pu[hit], front[hit])
    return img.reshape(cam.height, cam.width)


def _spacing(x: np.ndarray) -> float:
    sample = x[np.linspace(0, len(x) - 1, min(len(x), 5000)).astype(np.int64)]
    d, _ = cKDTree(x).query(sample, k=2)
    return float(np.median(d[:, 1]))


def carve_solid(depths: list, cams: list, cfg: ObservationConfig) -> np.ndarray:
    """Voxel centres (K,3) of the solid that no camera sees through (space carving on the board)."""
    surf = []
    for img, cam in zip(depths, cams):
        pv, pu = np.nonzero(np.isfinite(img))
        if len(pu):
            surf.append(cam.unproject(pu + 0.5, pv + 0.5, img[pv, pu]))
    if not surf:
        return np.zeros((0, 3))
    surf = np.concatenate(surf)  # S,3 back-projected surface points
    h = cfg.voxel_size
    lo = surf.min(0) - 2 * h
    hi = surf.max(0) + 2 * h
    lo[2] = cfg.board_z
    axes = [np.arange(a + h / 2, b, h) for a, b in zip(lo, hi)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)  # K,3
    solid = np.ones(len(centres), bool)
    margin = cfg.noise_margin * cfg.noise_std + 0.5 * h
    for img, cam in zip(depths, cams):
        u, v, z = cam.project(centres)
        pu, pv = np.floor(np.nan_to_num(u, nan=-1)).astype(np.int64), np.floor(np.nan_to_num(v, nan=-1)).astype(np.int64)
        seen = (pu >= 0) & (pu < cam.width) & (pv >= 0) & (pv < cam.height) & (z > 0)
        d = np.full(len(centres), -np.inf)
        d[seen] = img[pv[seen], pu[seen]]
        solid &= ~(seen & (z < d - margin))  # background (inf) or a surface behind the voxel: free space
    return centres[solid]


def observe_scenes(positions: list, labels: list, cfg: ObservationConfig | None = None, seeds=None,
                   device: str = "cpu") -> list[tuple]:
    """``observe`` of several scenes, [(points, labels)]: in mode "particles" on a CUDA ``device`` every scene's FPS
    in one launch (topocut.metrics.fps_clouds: the same points bit for bit); otherwise scene by scene."""
    cfg = (cfg or ObservationConfig()).validate()
    seeds = [0] * len(positions) if seeds is None else list(seeds)
    xs = [np.asarray(x, np.float64).reshape(-1, 3) for x in positions]  # N_i,3
    if cfg.mode != "particles" or not str(device).startswith("cuda") or not all(len(x) for x in xs):
        return [observe(x, lab, cfg, s) for x, lab, s in zip(xs, labels, seeds)]
    from topocut.metrics import fps_clouds

    out = []
    for x, lab, idx in zip(xs, labels, fps_clouds(xs, cfg.num_points, device)):
        lab = np.asarray(lab).reshape(-1)
        if lab.shape[0] != len(x):
            raise ValueError(f"labels has {lab.shape[0]} entries, positions has {len(x)}")
        out.append((x[idx].astype(np.float32), lab[idx].astype(np.int32)))
    return out


def observe(positions, labels, cfg: ObservationConfig | None = None, seed: int = 0):
    """-> (points (M,3) f32, labels (M,) i32); M = min(num_points, available)."""
    cfg = (cfg or ObservationConfig()).validate()
    x = np.asarray(positions, np.float64).reshape(-1, 3)  # N,3
    lab = np.asarray(labels).reshape(-1)
    if lab.shape[0] != len(x):
        raise ValueError(f"labels has {lab.shape[0]} entries, positions has {len(x)}")
    empty = np.zeros((0, 3), np.float32), np.zeros(0, np.int32)
    if not len(x):
        return empty
    if cfg.mode == "particles":
        idx = _fps(x, cfg.num_points, seed)
        return x[idx].astype(np.float32), lab[idx].astype(np.int32)
    rng = np.random.default_rng(seed)
    radius = cfg.splat_radius if cfg.splat_radius > 0 else 0.75 * _spacing(x)
    if not np.isfinite(radius):  # one particle has no spacing to size its splat: nothing a camera would resolve
        return empty
    cams = make_cameras(cfg)
    depths = []
    for cam in cams:
        img = render_depth(x, cam, radius)
        fin = np.isfinite(img)
        img[fin] += rng.normal(0.0, cfg.noise_std, int(fin.sum()))
        depths.append(img)
    centres = carve_solid(depths, cams, cfg)
    if len(centres) == 0:
        return np.zeros((0, 3), np.float32), np.zeros(0, np.int32)
    # jitter within the voxel so repeated observations do not share a lattice; cap the FPS input size
    pts = centres + rng.uniform(-0.5, 0.5, centres.shape) * cfg.voxel_size
    if len(pts) > 8 * cfg.num_points:
        pts = pts[rng.choice(len(pts), 8 * cfg.num_points, replace=False)]
    pts = pts[_fps(pts, cfg.num_points, seed)]
    _, j = cKDTree(x).query(pts)
    return pts.astype(np.float32), lab[j].astype(np.int32)

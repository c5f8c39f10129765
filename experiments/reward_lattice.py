"""The reward on lattice pieces (docs/reward.md): pose invariance along a cutting trajectory and the distance
matrix over a gallery of slices, sticks and dice.  ``python experiments/reward_figures.py pose_invariance`` /
``loss_matrix`` draws them."""
from __future__ import annotations

import numpy as np

from topocut.reward.config import RewardConfig
from topocut.reward.matching import spectral_reward

H = 0.008  # lattice spacing in scene units (the simulator's default particle spacing)


def lattice_box(nx: int, ny: int, nz: int, h: float = H, surface: bool = False, jitter: float = 0.0,
                seed: int = 0) -> np.ndarray:
    """Particles of an nx x ny x nz lattice block (N,3); surface=True keeps only the boundary layer.

    jitter moves each particle by U(-jitter, jitter) * h per axis, as topocut.sim.objects does.
    """
    g = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"), -1).reshape(-1, 3)
    if surface:
        g = g[((g == 0) | (g == np.array([nx, ny, nz]) - 1)).any(1)]
    g = g + np.random.default_rng(seed).uniform(-jitter, jitter, g.shape)
    return (g * h).astype(np.float64)


def yaw_pose(points: np.ndarray, yaw: float, offset=(0.5, 0.5, 0.05)) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    return (points - points.mean(0)) @ R.T + np.asarray(offset)


def pose_invariance(cfg: RewardConfig | None = None, yaws_deg=(0, 20, 45, 70, 110),
                    lengths=(64, 56, 48, 40, 36, 32, 28, 24, 16), jitter: float = 0.25) -> dict:
    """Reward vs step for a 5x5xL bar truncated step by step toward the ideal 5x5x32 stick.

    Each yaw rotates the fragment (not the goal); dense and surface-only particles.  With
    jitter = 0 (an exact lattice) FPS meets exact distance ties that rotation breaks differently,
    so the resampled subsets, and the rewards, differ slightly; jittered particles have no ties.
    Returns {"lengths", "yaws_deg", "dense": (Y,S), "surface": (Y,S)}.
    """
    cfg = cfg or RewardConfig()
    out = {"lengths": list(lengths), "yaws_deg": list(yaws_deg)}
    for mode in ("dense", "surface"):
        goal = lattice_box(5, 5, 32, surface=mode == "surface", jitter=jitter, seed=1)
        R = np.zeros((len(yaws_deg), len(lengths)))
        for i, yaw in enumerate(yaws_deg):
            for j, L in enumerate(lengths):
                bar = lattice_box(5, 5, L, surface=mode == "surface", jitter=jitter)  # cut from one end: same particles
                frag = yaw_pose(bar[:, [2, 0, 1]], np.deg2rad(yaw))
                R[i, j] = spectral_reward([frag], [goal], cfg).per_goal[0]  # R(d) of the piece
        out[mode] = R
    return out


def shape_gallery(h: float = H) -> dict:
    """Named pieces (lattice units x h): slices of 3/4/6 layers, sticks, dice, a sphere and a cube."""
    g = np.stack(np.meshgrid(*[np.arange(-8, 9)] * 3, indexing="ij"), -1).reshape(-1, 3)
    sphere = g[np.linalg.norm(g, axis=1) <= 7.5] * h
    return {"slice3": lattice_box(3, 20, 14, h), "slice4": lattice_box(4, 20, 14, h),
            "slice6": lattice_box(6, 20, 14, h), "stick4": lattice_box(4, 4, 14, h),
            "stick5": yaw_pose(lattice_box(5, 5, 14, h), 0.6), "die4": lattice_box(4, 4, 4, h),
            "die5": yaw_pose(lattice_box(5, 5, 5, h), 1.0), "cube12": lattice_box(12, 12, 12, h), "sphere": sphere}


def loss_matrix(cfg: RewardConfig | None = None) -> tuple[list[str], np.ndarray]:
    """Pairwise d(row, column) = d_spec + d_size over the gallery (the distance R sees; column = goal)."""
    from topocut.reward.distance import piece_distance

    shapes = shape_gallery()
    names = list(shapes)
    D = np.array([[piece_distance(shapes[a], shapes[b], cfg) for b in names] for a in names])
    return names, D



def draw_pose_invariance(res: dict, out: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6), sharey=True)
    steps = np.arange(len(res["lengths"]))
    for ax, mode in zip(axes, ("dense", "surface")):
        for i, yaw in enumerate(res["yaws_deg"]):
            ax.plot(steps, res[mode][i], marker="o", ms=3, label=f"yaw {yaw} deg")
        ax.set_xticks(steps, [str(L) for L in res["lengths"]])
        ax.set_xlabel("bar length (particles) along the cutting trajectory; goal 5x5x32")
        ax.set_title(f"{mode} particles: max spread {np.ptp(res[mode], axis=0).max():.1e}")
    axes[0].set_ylabel("R(d) of the piece")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=120)


def draw_loss_matrix(names, D, out: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    fig, ax = plt.subplots(figsize=(6.4, 5.4))
    im = ax.imshow(np.maximum(D, 1e-4), norm=LogNorm(), cmap="viridis")
    ax.set_xticks(range(len(names)), names, rotation=45, ha="right")
    ax.set_yticks(range(len(names)), names)
    ax.set_xlabel("reference piece (sets sigma)")
    for i in range(len(names)):
        for j in range(len(names)):
            ax.text(j, i, f"{D[i, j]:.2g}", ha="center", va="center", fontsize=6, color="w")
    fig.colorbar(im, ax=ax, label="d_spec")
    fig.tight_layout()
    fig.savefig(out, dpi=120)

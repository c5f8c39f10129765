"""Pyramid cutting (paper appendix "Pyramid Cutting Task"; docs/tasks.md): MPPI driven only by the spectral reward.

``python experiments/task_figures.py pyramid --out docs/img/pyramid.png`` starts MPPI from a
plane that misses the goal (shifted, yawed and less tilted than the ideal one), lets it sample
(x, y, yaw, tilt) of one cut, scores every sample by simulating the cut, discovering the pieces
and computing the spectral reward against the corner tetrahedron, and draws the planned plane,
the goal piece and the result; the ideal plane's simulated reward is the reference.

The MPPI cost uses the spectral reward with a gentler tail slope (``--delta``, default 1.1
instead of 10: R(d) reaches 0 at d = 0.9 instead of 0.11) so that samples far from the goal still
rank; every reported number is the reward under the default RewardConfig.
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from experiments.plane_scoring import PlaneScorer, perturbed_plane, pyramid_scene
from topocut.sim.action import KnifeAction


def pyramid_experiment(n_grid: int = 48, num_samples: int = 8, iterations: int = 6, size: float = 0.1,
                       init=(-0.02, 0.35, -0.3), delta: float = 1.1, seed: int = 0, device: str = "cpu",
                       out: str | None = None) -> dict:
    """MPPI over one cut of the cube's corner; returns the numbers and (with ``out``) draws the figure."""
    from topocut.planning.config import MPPIConfig
    from topocut.planning.mppi import MPPI
    from topocut.reward import RewardConfig
    from topocut.topology import TopologyConfig

    t0 = time.perf_counter()
    env, goal = pyramid_scene(n_grid, num_samples, size, device, seed)
    sim = env.cfg
    state = env.get_state(0)
    reward_cfg = RewardConfig()
    scorer = PlaneScorer(env, state, goal, reward_cfg, dataclasses.replace(reward_cfg, delta=delta),
                         TopologyConfig(resolution=64))
    ideal = goal.planes[0]
    start = perturbed_plane(ideal, goal.fragments[0].mean(0), *init, board_z=sim.board_z)
    ref = scorer.run(np.stack([ideal.to_vector(), start.to_vector()]))
    mcfg = MPPIConfig(num_samples=num_samples, horizon=1, iterations=iterations,
                      noise_sigma=[0.012, 0.012, 0.2, 0.15], sampled_dims=["x", "y", "yaw", "tilt"],
                      temperature=0.1, control_penalty=0.0, tilt_max=1.2)
    mppi = MPPI(mcfg, scorer.rollout, np.random.default_rng(seed))
    mean, info = mppi.plan(start.to_vector()[None].astype(np.float64))
    # the rollouts saw float32 vectors: re-executing float64 ones moves the plane by ~1e-8, which at a
    # cut that grazes a lattice layer can change the pieces (docs/tasks.md: the reward is that sensitive)
    best = KnifeAction.from_vector(info["best_sequence"][0].astype(np.float32))
    mean_plane = KnifeAction.from_vector(mean[0].astype(np.float32))
    final = scorer.run(np.stack([best.to_vector(), mean_plane.to_vector()]))
    n = ideal.normal
    result = {
        "n_grid": n_grid, "particles": int(len(state["x"])), "goal_particles": int(len(goal.fragments[0])),
        "ideal_plane": ideal.asdict(), "start_plane": start.asdict(), "planned_plane": best.asdict(),
        "mean_plane": mean_plane.asdict(),
        "ideal_reward": ref[0]["reward"], "start_reward": ref[1]["reward"], "planned_reward": final[0]["reward"],
        "mean_plane_reward": final[1]["reward"],
        "best_reward_per_iteration": [max(it["rewards"]) for it in scorer.log],
        "best_cost_reward_per_iteration": [max(it["cost_rewards"]) for it in scorer.log],
        "start_cost_reward": ref[1]["cost_reward"], "ideal_cost_reward": ref[0]["cost_reward"],
        "planned_normal_angle_deg": float(np.degrees(np.arccos(np.clip(abs(best.normal @ n), 0, 1)))),
        "planned_offset": float((best.plane_point(sim.board_z) - ideal.plane_point(sim.board_z)) @ n),
        "rollouts": num_samples * iterations + 4, "seconds": round(time.perf_counter() - t0, 1)}
    if out:
        draw_pyramid(out, state["x"], goal, ideal, start, best, final[0], ref[0], result, sim.board_z)
        Path(out).with_suffix(".json").write_text(json.dumps(result, indent=2, default=float))
    return result


def plane_polygon(action: KnifeAction, lo, hi, board_z: float) -> np.ndarray:
    """The plane clipped to the box [lo, hi]: its polygon's corners (m,3), ordered around the centroid."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    p0, n = action.plane_point(board_z), action.normal
    corners = np.array([[hi[i] if (k >> i) & 1 else lo[i] for i in range(3)] for k in range(8)])
    pts = []
    for a in range(8):
        for i in range(3):
            b = a | (1 << i)
            if b == a:
                continue
            da, db = (corners[a] - p0) @ n, (corners[b] - p0) @ n
            if da * db < 0:
                pts.append(corners[a] + da / (da - db) * (corners[b] - corners[a]))
    if len(pts) < 3:
        return np.zeros((0, 3))
    pts = np.array(pts)
    c = pts.mean(0)
    e1 = np.cross(n, [0.0, 0.0, 1.0]) if abs(n[2]) < 0.99 else np.array([1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    ang = np.arctan2((pts - c) @ e2, (pts - c) @ e1)
    return pts[np.argsort(ang)]


def draw_pyramid(path, x0, goal, ideal, start, planned, res, ideal_res, result, board_z) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    from topocut.reward import spectral_reward

    x0 = np.asarray(x0)
    lo, hi = x0.min(0) - 0.01, x0.max(0) + 0.01
    lim = (lo - 0.02, hi + 0.02)
    fig = plt.figure(figsize=(17, 4.6), dpi=100)

    def axis3d(i, title):
        ax = fig.add_subplot(1, 4, i, projection="3d")
        c, r = (lim[0] + lim[1]) / 2, (lim[1] - lim[0]).max() / 2
        for d, setter in enumerate((ax.set_xlim, ax.set_ylim, ax.set_zlim)):
            setter(c[d] - r, c[d] + r)
        ax.view_init(elev=28, azim=50)  # looking at the carved (+x, +y, +z) corner
        ax.set_box_aspect((1, 1, 1))
        ax.set_axis_off()
        ax.set_title(title, fontsize=10)
        return ax

    ax = axis3d(1, "cutting plane planned by MPPI\n(red; dashed: ideal, dotted: MPPI's start)")
    ax.scatter(*x0.T, s=1.5, c="0.7", linewidths=0, alpha=0.5)
    ax.scatter(*goal.fragments[0].T, s=2, c=[(0.95, 0.55, 0.2)], linewidths=0, alpha=0.5)
    for act, fc, ls in ((planned, (0.85, 0.2, 0.2, 0.45), "-"), (ideal, (0, 0, 0, 0), "--"), (start, (0, 0, 0, 0), ":")):
        poly = plane_polygon(act, lo, hi, board_z)
        if len(poly):
            ax.add_collection3d(Poly3DCollection([poly], facecolors=[fc], edgecolors="k", linestyles=ls,
                                                 linewidths=1.2))
    ax = axis3d(2, f"goal: corner tetrahedron\n({len(goal.fragments[0])} particles)")
    ax.scatter(*x0.T, s=1.0, c="0.85", linewidths=0, alpha=0.25)
    ax.scatter(*goal.fragments[0].T, s=6, c=[(0.95, 0.55, 0.2)], linewidths=0)
    for i, (r, name) in enumerate(((res, "MPPI's plane"), (ideal_res, "ideal plane"))):
        x, lab = r["x"], r["labels"]
        ids = [c for c in np.unique(lab) if c >= 0]
        frags = [x[lab == c] for c in ids]
        rr = spectral_reward([f for f in frags if len(f) >= 4], goal.fragments)
        col = np.tile([0.6, 0.6, 0.65], (len(x), 1))
        if rr.matching:  # the piece matched to the goal, drawn 3 cm away from the rest (exploded view)
            big = [c for c, f in zip(ids, frags) if len(f) >= 4]
            piece = lab == big[rr.matching[0][0]]
            col[piece] = (0.95, 0.55, 0.2)
            away = x[piece].mean(0) - x[~piece].mean(0)
            x = x + piece[:, None] * 0.03 * away / (np.linalg.norm(away) + 1e-12)
        ax = axis3d(3 + i, f"executed: {name} (matched piece moved out)\nreward {r['reward']:.3f}, {len(ids)} pieces")
        ax.scatter(*x.T, s=1.5, c=col, linewidths=0)
    fig.suptitle(f"Pyramid cutting, n_grid {result['n_grid']}: MPPI ({result['rollouts']} simulated rollouts) "
                 f"reaches reward {result['planned_reward']:.3f} vs {result['ideal_reward']:.3f} for the ideal plane "
                 f"(start {result['start_reward']:.3f})", fontsize=11, y=1.03)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    fig.savefig(tmp, bbox_inches="tight")
    plt.close(fig)
    tmp.replace(path)
    return path

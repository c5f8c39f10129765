"""Does the reference earn full marks, and does a wrong variant cost?  (issue #54; docs/tasks.md)

Pyramid: the goal's own plane (the task's oracle: the corner tetrahedron's cut) and three wrong planes, each
simulated from the same state in one batch (the four scenes of one CuttingEnv) and scored with today's reward
(experiments/plane_scoring.py's PlaneScorer: topology discovery, then the spectral reward against the goal):

* deeper: the plane moved 2 cm into the cube along its normal (a bigger corner);
* yawed: turned 15° about the vertical through the goal face's centre;
* tilted: turned 15° steeper about the goal face's centre.

    python experiments/reference_check.py pyramid --n-grid 48                 # CPU, ~30 s (the smoke scale)
    python experiments/reference_check.py pyramid --n-grid 128 --device cuda  # the documented scale

Prints one line per plane (reward, N_C, pieces) and, with ``--json``, writes them.  The other tasks' checks:
``experiments/reference_writing.py`` (cream writing) and ``experiments/reference_scooping.py`` (scooping).  The cube sits at the
nominal pose (the task's own corner geometry; the protocol's poses are the oracle audit's business).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a file: `experiments` from the repository root

from experiments.reference_cli import add_json_option, save_json  # noqa: E402

VARIANTS = {  # name: (offset along the normal [units], yaw [deg], tilt [deg]) about the goal face's centre
    "reference": (0.0, 0.0, 0.0),
    "deeper 2 cm": (-0.02, 0.0, 0.0),
    "yawed 15°": (0.0, 15.0, 0.0),
    "tilted 15°": (0.0, 0.0, 15.0),
}


def pyramid(n_grid: int = 48, size: float = 0.1, device: str = "cpu", seed: int = 0) -> dict:
    """The four planes' rewards: {"rows": [{"plane", "reward", "pieces"}], and the settings}."""
    from experiments.plane_scoring import PlaneScorer, perturbed_plane, pyramid_scene
    from topocut.reward import RewardConfig
    from topocut.topology import TopologyConfig

    t0 = time.perf_counter()
    env, goal = pyramid_scene(n_grid, len(VARIANTS), size, device, seed)
    sim = env.cfg
    particles = int(env.n)
    reward = RewardConfig() if device == "cpu" else RewardConfig(backend="torch", device=device)
    scorer = PlaneScorer(env, env.get_state(0), goal, reward, reward, TopologyConfig(resolution=64))
    ideal, pivot = goal.planes[0], goal.fragments[0].mean(0)
    planes = [perturbed_plane(ideal, pivot, off, np.radians(yaw), np.radians(tilt), sim.board_z)
              for off, yaw, tilt in VARIANTS.values()]
    rows = []
    for name, res in zip(VARIANTS, scorer.run(np.stack([p.to_vector() for p in planes]))):
        frags = scorer.scorer.fragments(res["x"], res["labels"])
        rows.append({"plane": name, "reward": round(float(res["reward"]), 4), "pieces": len(frags)})
    return {"task": "pyramid", "n_grid": n_grid, "size": size, "device": device,
            "goal_particles": int(len(goal.fragments[0])), "particles": particles,
            "rows": rows, "seconds": round(time.perf_counter() - t0, 1)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="task", required=True)
    q = sub.add_parser("pyramid", help="the goal's own plane against three wrong planes")
    q.add_argument("--n-grid", type=int, default=48)
    q.add_argument("--size", type=float, default=0.1, help="the tetrahedron's leg [units] (task.size)")
    q.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    add_json_option(q)
    args = p.parse_args(argv)
    out = pyramid(args.n_grid, args.size, args.device)
    print(f"pyramid, cube, n_grid {out['n_grid']}, leg {out['size']} ({out['goal_particles']} goal particles of "
          f"{out['particles']}), {out['seconds']} s:")
    for r in out["rows"]:
        print(f"  {r['plane']:<12} reward {r['reward']:.3f}  pieces {r['pieces']}")
    return save_json(out, args.json)


if __name__ == "__main__":
    sys.exit(main())

"""The reward's figures (docs/reward.md): pose invariance, the spectral-loss matrix, Q1 with hand-cut pieces and Q1
in the simulator.  The experiments live beside it (experiments/reward_lattice.py, reward_q1_hand.py,
reward_q1_sim.py); this is their command line.

    python experiments/reward_figures.py pose_invariance --out docs/img/reward_pose_invariance.png
    python experiments/reward_figures.py loss_matrix --out docs/img/reward_loss_matrix.png
    python experiments/reward_figures.py q1_hand --out docs/img/reward_q1.png
    python experiments/reward_figures.py q1 --n-grid 64 --out docs/img/reward_q1_sim.png   (simulator, ~3 min on CPU)
"""
import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a file: `experiments` from the repository root
from experiments.reward_lattice import draw_loss_matrix, draw_pose_invariance, loss_matrix, pose_invariance  # noqa: E402
from experiments.reward_q1_hand import draw_q1_hand, q1_hand, thickness_sweep  # noqa: E402
from experiments.reward_q1_sim import draw_q1_sequence, q1_sequence  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("experiment", choices=["pose_invariance", "loss_matrix", "q1", "q1_hand"])
    ap.add_argument("--n-grid", type=int, default=64, help="q1: simulator grid")
    ap.add_argument("--push", action="store_true", help="q1: push pieces apart after each cut")
    ap.add_argument("--wrong", default="yaw", choices=["yaw", "shift"], help="q1: kind of wrong 4th cut")
    ap.add_argument("--error", type=float, default=30.0, help="q1: wrong cut's yaw (deg) or shift (m)")
    ap.add_argument("--out", required=True, help="figure path (.png); numbers go to the same path with .json")
    args = ap.parse_args(argv)
    if args.experiment == "pose_invariance":
        res = pose_invariance()
        draw_pose_invariance(res, args.out)
        exact = pose_invariance(jitter=0.0)
        summary = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in res.items()}
        summary.update({f"{m}_exact_lattice": exact[m].tolist() for m in ("dense", "surface")})
        summary["max_spread"] = {m: float(np.ptp(r[m], axis=0).max()) for r, m in
                                 ((res, "dense"), (res, "surface"))}
        summary["max_spread_exact_lattice"] = {m: float(np.ptp(exact[m], axis=0).max()) for m in ("dense", "surface")}
    elif args.experiment == "q1_hand":
        res, sweep = q1_hand(), thickness_sweep()
        draw_q1_hand(res, sweep, args.out)
        summary = {"q1": res, "sweep": sweep}
    elif args.experiment == "q1":
        res = q1_sequence(n_grid=args.n_grid, push=args.push, wrong=args.wrong, error=args.error)
        draw_q1_sequence(res, args.out)
        summary = {k: v for k, v in res.items() if not k.startswith("_")}
    else:
        names, D = loss_matrix()
        draw_loss_matrix(names, D, args.out)
        summary = {"names": names, "d_spec": D.tolist()}
    with open(args.out.rsplit(".", 1)[0] + ".json", "w") as f:
        json.dump(summary, f, indent=1)
    print(json.dumps(summary)[:2000])


if __name__ == "__main__":
    main()

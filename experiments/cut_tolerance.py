"""How far may a cut miss and still count? The goal's first cut shifted along its normal, scored by the reward.

    python experiments/cut_tolerance.py [--objects cake cube] [--tasks slice] [--offsets-mm -8 -4 -2 0 2 4 8]

Every offset is one scene of one batched simulation (the Gymnasium vector env: the same cut, push and discovery as
the evaluation), the object at its nominal pose (pose randomisation off; scene b samples its particles with seed
b, the only difference between scenes).  Prints, per task and object, the reward R and the cut count N_C after
the shifted first cut, and writes them as JSON (--out).  docs/results.md reads it beside the open-loop plane gaps.
Slice is the task whose first cut makes a goal piece; stick's and dice's need later cuts (their R stays 0 here).
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np

from topocut.data.store import write_json_atomic
from topocut.envs import CuttingVectorEnv
from topocut.eval.config import EvalConfig
from topocut.sim.config import SimConfig
from topocut.tasks import Cut, piece_sizes, task_config


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", nargs="+", default=["cake", "cube"])
    ap.add_argument("--tasks", nargs="+", default=["slice"])
    ap.add_argument("--offsets-mm", nargs="+", type=float, default=[-8, -4, -2, 0, 2, 4, 8])
    ap.add_argument("--piece", type=float, default=0.05, help="thickness / width / size of the goal pieces (m)")
    ap.add_argument("--n-grid", type=int, default=64)
    ap.add_argument("--out", default="cut_tolerance.json")
    args = ap.parse_args(argv)
    eval_cfg = EvalConfig(randomize_pose=False)
    rows = []
    for task in args.tasks:
        task_cfg = task_config(task, **piece_sizes(task, args.piece),
                               push=task != "slice")  # conf/task: stick and dice push after each cut
        env = CuttingVectorEnv(task=task, objects=args.objects[0], num_envs=len(args.offsets_mm),
                               sim_cfg=SimConfig(n_grid=args.n_grid), task_cfg=task_cfg, eval_cfg=eval_cfg,
                               max_cuts=1, num_points=256, num_goal_points=256)
        for obj in args.objects:
            t0 = time.perf_counter()
            env.reset(seed=0, options={"object": obj})
            cut = next(s for s in env.engine.goals[0].steps if isinstance(s, Cut)).action
            actions = np.stack([cut.shifted(d / 1000.0).to_vector() for d in args.offsets_mm])  # B,4
            _, _, _, _, info = env.step(actions)
            for b, d in enumerate(args.offsets_mm):
                rows.append({"task": task, "object": obj, "offset_mm": d, "reward": float(info["reward_total"][b]),
                             "cut_count": int(info["cut_count"][b]), "num_pieces": int(info["num_pieces"][b])})
            print(f"{task} {obj} ({time.perf_counter() - t0:.0f} s): " + ", ".join(
                f"{r['offset_mm']:+g} mm R={r['reward']:.2f} N_C={r['cut_count']}" for r in rows[-len(args.offsets_mm):]),
                flush=True)
        env.close()
    write_json_atomic(Path(args.out), {"piece_m": args.piece, "n_grid": args.n_grid, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())

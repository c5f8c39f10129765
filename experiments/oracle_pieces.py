"""The oracle's pieces: the goal's own steps executed exactly, scored against the goal pieces (docs/sim.md).

For each object and task, the goal's steps (cuts, pushes, the Turn that lays a wide slab flat) run in the
simulator; every goal piece is then matched to the simulator's pieces (``CuttingEnv.piece``) and to the
pieces topology discovery finds, by intersection over union of particle sets (the goal's fragments are the
same particles as the scene's, in their initial positions).

    python experiments/oracle_pieces.py --device cuda --n-grid 128 --save /tmp/out/oracle   # states, no Warp needed
    python experiments/oracle_pieces.py --load /tmp/out/oracle                               # discover + table (CPU)
    python experiments/oracle_pieces.py --device cpu --n-grid 64                             # both in one go
"""
import argparse
import json
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

CASES = [("cube", "slice"), ("cube", "stick"), ("cake", "slice"), ("cake", "stick")]


def simulate(obj, task, n_grid, device):
    from topocut.sim.config import SimConfig
    from topocut.sim.env import CuttingEnv
    from topocut.sim.objects import ObjectPose
    from topocut.tasks import Cut, get_task, task_config

    cfg = SimConfig(n_grid=n_grid, arch=device)
    pose = ObjectPose(x=0.5, y=0.5, yaw=0.0, scale=1.0)
    env = CuttingEnv(cfg, batch_size=1)
    x0 = env.reset(obj, pose).x[0].astype(np.float64)
    # push=False: the plan this experiment's recorded runs cut (docs/sim.md), whatever the task's own push
    goal = get_task(task).make_goal(task_config(task, push=False), obj, pose, spacing=cfg.spacing,
                                    board_z=cfg.board_z)
    pts = np.concatenate(goal.fragments)
    owner = np.concatenate([np.full(len(f), i) for i, f in enumerate(goal.fragments)])
    dist, nn = cKDTree(pts).query(x0)
    goal_of = np.where(dist <= 1e-3 * cfg.spacing, owner[nn], -1)  # N: goal piece of each particle, -1 none
    steps, t = [], time.perf_counter()
    for step in goal.steps:
        if isinstance(step, Cut):
            env.cut(step.action)
            env.push()
        else:
            env.turn(step)
        st = env.state()
        steps.append({"x": st.x[0], "damage": st.damage[0], "sweeps": [w.asdict() for w in st.sweeps[0]],
                      "kind": step.kind})
    return {"x0": x0, "goal_of": goal_of, "piece": env.piece[0].copy(), "steps": steps, "n_grid": n_grid,
            "device": device, "seconds": time.perf_counter() - t, "spacing": cfg.spacing}


def best_iou(want, labels):
    return max(len(np.intersect1d(want, np.flatnonzero(labels == k))) / len(np.union1d(want, np.flatnonzero(labels == k)))
               for k in np.unique(labels[labels >= 0]))


def score(run, discover=True):
    """Per goal piece: IoU with the best simulator piece and (if ``discover``) the best discovered piece."""
    from topocut.sim.action import KnifeSweep

    found = None
    if discover:
        from topocut.topology.discover import discover as disc

        labels, nid = None, None
        for s in run["steps"]:
            res = disc(s["x"], s["damage"], [KnifeSweep.fromdict(w) for w in s["sweeps"]],
                       previous_labels=labels, next_id=nid)
            labels, nid = res.labels, res.next_id
        found = labels
    goal_of = run["goal_of"]
    rows = []
    for i in range(goal_of.max() + 1):
        want = np.flatnonzero(goal_of == i)
        rows.append({"sim": best_iou(want, run["piece"]), "discovered": best_iou(want, found) if discover else None})
    return rows


def table(results):
    lines = ["| object | task | grid | goal pieces | min IoU (simulator pieces) | min IoU (discovered) | sim time [s] |",
             "|---|---|---|---|---|---|---|"]
    for (obj, task), (run, rows) in results.items():
        disc = min(r["discovered"] for r in rows) if rows[0]["discovered"] is not None else float("nan")
        lines.append(f"| {obj} | {task} | {run['n_grid']}³ ({run['device']}) | {len(rows)} | "
                     f"{min(r['sim'] for r in rows):.3f} | {disc:.3f} | {run['seconds']:.1f} |")
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--n-grid", type=int, default=64)
    ap.add_argument("--save", type=Path, help="simulate and save the states here (no discovery)")
    ap.add_argument("--load", type=Path, help="discover and score states saved by --save")
    args = ap.parse_args()
    import pickle

    results = {}
    if args.load:
        for f in sorted(args.load.glob("*.pkl")):
            run = pickle.loads(f.read_bytes())
            obj, task = f.stem.split("-")[:2]
            results[(obj, task)] = (run, score(run))
    else:
        from topocut.sim.runtime import init_taichi

        init_taichi(args.device)
        for obj, task in CASES:
            run = simulate(obj, task, args.n_grid, args.device)
            if args.save:
                args.save.mkdir(parents=True, exist_ok=True)
                (args.save / f"{obj}-{task}-{args.n_grid}.pkl").write_bytes(pickle.dumps(run))
            results[(obj, task)] = (run, score(run, discover=args.save is None))
            print(obj, task, json.dumps([{k: round(v, 3) if v is not None else v for k, v in r.items()}
                                         for r in results[(obj, task)][1]]), flush=True)
    print(table(results))


if __name__ == "__main__":
    main()

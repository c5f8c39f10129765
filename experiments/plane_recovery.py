"""How far the plane PDDP fits to a cut mask turns from the cut that made the mask, when the mask is the
demonstrator's own (no learning involved): the floor of PDDP's plane angle in the open-loop table.

    python experiments/plane_recovery.py [--tasks slice stick dice] [--objects cake cube potato ham ditto]
                                         [--seeds 2] [--points 2048] [--json out.json]

Each (task, object, seed) plans the task's goal at a random yaw; the ideal material is replayed through the plan
(topocut.tasks.ideal.replay) and, before each cut, ``--points`` of its particles are drawn as a policy's observation.
The cut's own mask (topocut.sim.action.cut_mask) is then spoiled three ways and a plane fitted to it (svm and lsq,
free and vertical, topocut.policies.plane):

- ``exact``: the mask as the cut makes it;
- ``boundary``: 30% of the points within 4 mm of the plane flipped (a sampler unsure at the boundary);
- ``scattered``: 2% of all points flipped (isolated wrong labels anywhere).

Prints the mean angle (degrees) between the fitted plane and the cut per task and cut (1, 2, 3+) and writes every
record to ``--json``; ``--methods svm`` keeps the svm fits alone; ``--denoise`` adds a vertical svm fit to the mask
after a 9-nearest-neighbour majority vote.  CPU, about half a minute.
"""
import argparse
import math
import sys

import numpy as np

from topocut.policies.plane import fit_plane
from topocut.sim.action import cut_mask, signed_distance_to_plane
from topocut.sim.objects import ObjectPose, sample_object
from topocut.tasks import get_task, ideal, task_config

FITS = (("svm", False), ("svm", True), ("lsq", False), ("lsq", True))
SPOILS = ("exact", "boundary", "scattered")
MAJORITY_K = 9  # --denoise: each label replaced by the majority of the point's 9 nearest (itself included)


def cut_states(task: str, obj: str, yaw: float, seed: int, spacing: float = 0.008, board_z: float = 0.05):
    """(points before the cut (N,3), the cut's KnifeAction, cut index) for each cut of the task's oracle plan."""
    goal = get_task(task).make_goal(task_config(task), obj, ObjectPose(yaw=yaw), spacing, board_z=board_z, seed=seed)
    pts, _ = sample_object(obj, ObjectPose(yaw=yaw), spacing, skin_thickness=0.01, seed=seed, board_z=board_z)
    x = np.asarray(pts, np.float64)
    for k, (xs, _, step, _) in enumerate(ideal.replay(x, goal.steps, ideal.sim_config_for(spacing, board_z))):
        yield xs.copy(), step.action, k


def spoil(mask, d, how: str, rng):
    """The mask with labels flipped as ``how`` says (d: each point's signed distance to the cut's plane)."""
    if how == "boundary":
        return np.where((np.abs(d) < 0.004) & (rng.random(len(mask)) < 0.3), 1 - mask, mask)
    if how == "scattered":
        return np.where(rng.random(len(mask)) < 0.02, 1 - mask, mask)
    return mask


def angle_deg(n, action) -> float:
    return math.degrees(math.acos(min(1.0, abs(float(np.dot(n, action.normal))))))


def majority(points, mask, k: int = MAJORITY_K):
    """Each label replaced by the majority of its point's k nearest points (itself included)."""
    from scipy.spatial import cKDTree

    idx = cKDTree(points).query(points, k)[1]  # P,k
    return (mask[idx].mean(1) > 0.5).astype(mask.dtype)


def measure(tasks, objects, seeds: int, points: int, board_z: float = 0.05, seed: int = 0,
            methods=("svm", "lsq"), denoise: bool = False) -> list[dict]:
    fits = [(m, v, False) for m, v in FITS if m in methods] + ([("svm", True, True)] if denoise else [])
    rng = np.random.default_rng(seed)
    records = []
    for task in tasks:
        for obj in objects:
            for s in range(seeds):
                yaw = float(rng.uniform(-0.5, 0.5))
                for x, action, k in cut_states(task, obj, yaw, s, board_z=board_z):
                    p = x[rng.choice(len(x), min(points, len(x)), replace=False)]  # P,3
                    mask = cut_mask(p, action, board_z)
                    if min(mask.sum(), len(mask) - mask.sum()) < 3:
                        continue
                    d = signed_distance_to_plane(p, action, board_z)
                    for how in SPOILS:
                        m = spoil(mask, d, how, rng)
                        for method, vertical, vote in fits:
                            fit = fit_plane(p, majority(p, m) if vote else m, method, vertical=vertical)
                            records.append({"task": task, "object": obj, "seed": s, "cut": k, "spoil": how,
                                            "method": method, "vertical": vertical, "majority": vote,
                                            "angle_deg": angle_deg(fit[0], action) if fit else math.nan})
    return records


def table(records) -> str:
    fits = sorted({(r["method"], r["vertical"], r["majority"]) for r in records},
                  key=lambda f: (f[0] != "svm", f[2], f[1]))
    cols = [(how, *f) for how in SPOILS for f in fits]
    head = "| task | cut | cuts | " + " | ".join(
        f"{h}, {m} {'vertical' if v else 'free'}{f' majority-{MAJORITY_K}' if w else ''}" for h, m, v, w in cols) + " |"
    lines = [head, "|" + "---|" * (len(cols) + 3)]
    groups = sorted({(r["task"], min(r["cut"], 2)) for r in records})
    for task, c in groups:
        sel = [r for r in records if r["task"] == task and min(r["cut"], 2) == c]
        n = len({(r["object"], r["seed"], r["cut"]) for r in sel})
        cells = []
        for how, m, v, w in cols:
            a = [r["angle_deg"] for r in sel if (r["spoil"], r["method"], r["vertical"], r["majority"]) == (how, m, v, w)]
            cells.append(f"{np.nanmean(a):.1f}")
        lines.append(f"| {task} | {('1', '2', '3+')[c]} | {n} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tasks", nargs="+", default=["slice", "stick", "dice"])
    ap.add_argument("--objects", nargs="+", default=["cake", "cube", "potato", "ham", "ditto"])
    ap.add_argument("--seeds", type=int, default=2, help="episodes (object seed and yaw) per task and object")
    ap.add_argument("--points", type=int, default=2048, help="observation points per state")
    ap.add_argument("--methods", nargs="+", choices=("svm", "lsq"), default=["svm", "lsq"])
    ap.add_argument("--denoise", action="store_true", help="also a vertical svm fit after a majority vote")
    ap.add_argument("--json", default="", help="write every record here")
    args = ap.parse_args(argv)
    try:
        for t in args.tasks:
            task_config(t)
    except (KeyError, ValueError) as e:
        print(f"error: --tasks: {e}", file=sys.stderr)
        return 2
    records = measure(args.tasks, args.objects, args.seeds, args.points, methods=args.methods, denoise=args.denoise)
    print(table(records))
    if args.json:
        from topocut.data.store import write_json_atomic

        write_json_atomic(args.json, records)
    return 0


if __name__ == "__main__":
    sys.exit(main())

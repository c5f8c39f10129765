"""Does the scripted scoop earn full marks, and does a wrong scoop cost?  (issue #54, scooping; docs/tasks.md)

Each variant runs the whole episode (topocut.tasks.scooping_scene.scoop_episode: every scoop of task.spoon.scoops,
settle, topology discovery) and is scored against the task's own targets (``chunk_targets``: the block's particles
at rest inside the bowl's mid-sphere) by topocut.tasks.scooping_reward (the cup's pieces matched to the targets,
the block not waste, spilled material charged):

* reference: the task's primitive (scoop_keyframes with the task's depth, poured at the cup);
* 2 cm short (wrong): every scoop stops 2 cm short of the task's depth (the bowl dips depth - 2 cm into the block), so
  it brings up a shallower chunk;
* poured 2 cm short (a control, not wrong): the pour point 2 cm short of the reference's, towards the block.  The cup
  (20 cm across) still catches the chunk, so this is not a wrong scoop and should score as the reference does;
  neither is a placement 2 cm off on the block (the reward does not see where a full chunk came from).

    python experiments/reference_scooping.py --n-grid 48      # CPU, ~8 min (the smoke scale, the task's 2 scoops)
    python experiments/reference_scooping.py --n-grid 32 --scoop=-0.03,0 --variant reference --variant "2 cm short"
                                                              # CPU, ~40 s: tests/test_reference_scooping.py
    python experiments/reference_scooping.py --rules <run>/states.npz   # the target rule against a run's chunks

Prints one line per variant (reward, reward per chunk, pieces in the cup, spilled particles) and, with ``--json``,
writes them.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a file: `experiments` from the repository root

from experiments.reference_cli import add_json_option, save_json  # noqa: E402

SHORT = 0.02  # [units]: the "the scoop 2 cm short"


VARIANTS = {  # name: (wrong?, the scoop_keyframes keyword arguments of every scoop, from the task's spoon)
    "reference": (False, lambda spoon: {}),
    "2 cm short": (True, lambda spoon: {"depth": spoon.depth - SHORT}),
    "poured 2 cm short": (False, lambda spoon: {"pour_dx": -SHORT}),
}


def scooping(n_grid: int = 48, device: str = "cpu", seed: int = 0, scoops=None, names=None, keep: bool = False) -> dict:
    """The variants' scores: {"rows": [{"variant", "wrong", "reward", "per_chunk", ...}], and the settings}.
    scoops: the placements (list of (x, y) offsets from the block centre; None: the task's); names: the variants to
    run (None: all of VARIANTS); keep: also each variant's whole episode (scoop_episode's result, its arrays
    included) under "episodes", by variant."""
    from topocut.reward import RewardConfig
    from topocut.sim import SimConfig
    from topocut.tasks import task_config
    from topocut.tasks.config import SpoonConfig
    from topocut.tasks.scooping_scene import scoop_episode
    from topocut.topology import TopologyConfig

    t0 = time.perf_counter()
    spoon = SpoonConfig() if scoops is None else SpoonConfig(scoops=[list(map(float, s)) for s in scoops])
    task = task_config("scooping", spoon=spoon).validate()
    sim = SimConfig(n_grid=n_grid, arch=device)
    reward = RewardConfig() if device == "cpu" else RewardConfig(backend="torch", device=device)
    unknown = sorted(set(names or ()) - set(VARIANTS))
    if unknown:
        raise ValueError(f"variant {unknown[0]!r} is not one of {', '.join(VARIANTS)}")
    rows, episodes = [], {}
    for name, (wrong, primitive) in VARIANTS.items():
        if names is not None and name not in names:
            continue
        res = scoop_episode(sim, task, TopologyConfig(resolution=64), seed=seed, reward_cfg=reward,
                            primitive=primitive(spoon))
        if keep:
            episodes[name] = res
        rows.append({"variant": name, "wrong": wrong, "reward": round(res["reward"], 4),
                     "per_chunk": [round(r, 4) for r in res["per_chunk"]],
                     "held": [s["held"] for s in res["scoops"]], "cup_pieces": res["cup_piece_sizes"],
                     "spilled": res["spilled"], "distances": [[round(d, 4) for d in row] for row in res["distances"]],
                     "seconds": round(res["seconds"], 1)})
    out = {"task": "scooping", "n_grid": n_grid, "device": device, "seed": seed, "scoops": spoon.scoops,
           "particles": res["particles"], "target_points": res["target_points"], "rows": rows,
           "seconds": round(time.perf_counter() - t0, 1)}
    return {**out, "episodes": episodes} if keep else out


def target_rules(states: str) -> list[dict]:
    """How near each candidate target rule comes to the chunks a run made (its states.npz: x_0, x, labels, chunk,
    spacing; the task's default spoon): per scoop, the rule's particle count, its overlap with chunk i (Jaccard, by
    particle) and R(d) of chunk i's cup piece against it (the task's distance: the size terms at the block's particle
    spacing).  The rules: the mid-sphere cap (chunk_targets), the inner sphere's cap, and the inner sphere swept
    along the advance (the target before issue #54).  Then, per scoop, chunk i at rest, as lifted (x_lift_i) and in
    the cup against the target: d, its d_size part, the volume N s^3 with s estimated from the positions (the
    median 4-NN distance / 0.97, topocut.reward.size.particle_spacing; what the size terms read before they took
    the spacing) [cm^3], and the chunk's mean det F (J_lift_i, J; the material's own volume change).  And where the
    chunk's particles crowd: by their distance r from the bowl's centre as lifted, their count and mean 4-NN distance
    as lifted and at rest [spacings], and how many lay beyond the bowl's inner radius at rest (from the sphere where
    the advance starts) and as lifted."""
    import numpy as np

    from topocut.reward import RewardConfig, piece_distance, piecewise_reward, size_descriptor, spectral_distance
    from topocut.tasks.config import SpoonConfig
    from topocut.tasks.scooping_scene import chunk_masks

    f = np.load(states)
    x0, x, lab, chunk = f["x_0"], f["x"], f["labels"], f["chunk"]
    if "spacing" not in f.files:
        raise SystemExit(f"{states} has no 'spacing' (written before the size terms took it): simulate it again")
    s = float(f["spacing"])
    sp = SpoonConfig()
    top = float(x0[:, 2].max())
    rows = []
    for i, (ox, oy) in enumerate(sp.scoops):
        c = np.array([sp.block_center[0] + ox, sp.block_center[1] + oy, top - sp.depth + sp.radius])
        q = x0 - c  # N,3
        along = np.clip(q[:, 0], 0.0, sp.advance)[:, None] * np.array([1.0, 0.0, 0.0])  # nearest centre on the advance
        rules = {"mid-sphere cap (the target)": chunk_masks(x0, sp)[i],
                 "inner-sphere cap": np.linalg.norm(q, axis=1) <= sp.radius,
                 "inner sphere swept 2 cm (before)": np.linalg.norm(q - along, axis=1) <= sp.radius}
        held = chunk == i + 1
        ids, cnt = np.unique(lab[held], return_counts=True)
        piece = x[lab == ids[cnt.argmax()]]
        for name, m in rules.items():
            d = piece_distance(piece, x0[m], spacing=s)
            rows.append({"scoop": i + 1, "rule": name, "particles": int(m.sum()), "held": int(held.sum()),
                         "jaccard": round(float((m & held).sum() / (m | held).sum()), 3), "d": round(d, 4),
                         "R": round(float(piecewise_reward(d)), 3)})
        rows += crowding(i + 1, x0[held], f[f"x_lift_{i + 1}"][held], c, sp, s)
        target = x0[rules["mid-sphere cap (the target)"]]
        stages = {"at rest": (x0[held], 1.0), "as lifted": (f[f"x_lift_{i + 1}"][held], f[f"J_lift_{i + 1}"][held]),
                  "in the cup": (piece, f["J"][lab == ids[cnt.argmax()]])}
        for name, (pts, J) in stages.items():
            d = piece_distance(pts, target, spacing=s)
            rows.append({"scoop": i + 1, "chunk": name, "d": round(d, 4),
                         "d_size": round(d - spectral_distance(pts, target, RewardConfig()), 4),
                         "volume_estimate_cm3": round(float(size_descriptor(pts)[3]) * 1e6, 1),
                         "volume_cm3": round(len(pts) * s ** 3 * 1e6, 1), "mean_J": round(float(np.mean(J)), 4)})
    return rows


def crowding(scoop: int, rest, lifted, c_rest, sp, s: float) -> list[dict]:
    """Rows of target_rules: chunk ``scoop``'s particles (rest (n,3), lifted (n,3)) binned by their distance from the
    bowl's centre as lifted (the spoon's pose at the end of its lift, scoop_keyframes from the block's top; the
    bowl's inner radius is sp.radius): count, mean 4-NN distance as lifted and at rest [spacings s]; and the
    particles beyond sp.radius at rest (from the sphere's centre c_rest where the advance starts) and as lifted."""
    import numpy as np
    from scipy.spatial import cKDTree

    from topocut.sim import SimConfig
    from topocut.sim.spoon import scoop_keyframes

    top = c_rest[2] - sp.radius + sp.depth
    path = scoop_keyframes(sp, (c_rest[0], c_rest[1]), top, SimConfig().board_z + sp.cup_height)
    c_lift = path.pose(next(k.t for k in path.keys if k.phase == "lift"))[0]
    r = np.linalg.norm(lifted - c_lift, axis=1)
    nn = {name: cKDTree(p).query(p, 5)[0][:, 1:].mean(1) / s for name, p in (("lifted", lifted), ("rest", rest))}
    rows = [{"scoop": scoop, "beyond_radius_at_rest": int((np.linalg.norm(rest - c_rest, axis=1) > sp.radius).sum()),
             "beyond_radius_as_lifted": int((r > sp.radius + 1e-3).sum())}]
    for lo, hi in ((0.0, 0.05), (0.05, 0.055), (0.055, 0.059), (0.059, 0.061), (0.061, 1.0)):
        m = (r >= lo) & (r < hi)
        rows.append({"scoop": scoop, "r_cm": [round(lo * 100, 1), round(hi * 100, 1)], "particles": int(m.sum()),
                     "nn_lifted": round(float(nn["lifted"][m].mean()), 3) if m.any() else None,
                     "nn_rest": round(float(nn["rest"][m].mean()), 3) if m.any() else None})
    return rows


def _placement(text: str) -> list[float]:
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--scoop wants x,y (offsets from the block centre), got {text!r}") from None
    return [x, y]


def _print(out: dict) -> None:
    print(f"scooping, n_grid {out['n_grid']}, {len(out['scoops'])} scoop(s), targets {out['target_points']} of "
          f"{out['particles']} particles, {out['seconds']} s:")
    for r in out["rows"]:
        chunks = ", ".join(f"{v:.3f}" for v in r["per_chunk"])
        print(f"  {r['variant']:<18} {'wrong' if r['wrong'] else '     '} reward {r['reward']:.3f}  per chunk {chunks}  "
              f"cup pieces {r['cup_pieces']}  spilled {r['spilled']}  ({r['seconds']} s)")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n-grid", type=int, default=48)
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--scoop", type=_placement, action="append", default=None,
                   help="a placement x,y (repeat for several; default: the task's two)")
    p.add_argument("--variant", action="append", choices=VARIANTS, default=None,
                   help="a variant to run (repeat for several; default: all)")
    p.add_argument("--rules", default="", metavar="STATES",
                   help="instead: the candidate target rules against a run's chunks (<run>/states.npz)")
    add_json_option(p)
    args = p.parse_args(argv)
    if args.rules:
        out = target_rules(args.rules)
        for r in out:
            if "beyond_radius_at_rest" in r:
                print(f"  scoop {r['scoop']}  chunk particles beyond the bowl's inner radius: {r['beyond_radius_at_rest']} "
                      f"at rest, {r['beyond_radius_as_lifted']} as lifted")
            elif "r_cm" in r:
                if r["particles"]:
                    print(f"  scoop {r['scoop']}  r {r['r_cm'][0]:.1f}-{r['r_cm'][1]:.1f} cm as lifted: {r['particles']:4d} "
                          f"particles, mean 4-NN distance {r['nn_lifted']:.3f} s (at rest {r['nn_rest']:.3f} s)")
            elif "rule" in r:
                print(f"  scoop {r['scoop']}  {r['rule']:<33} {r['particles']:4d} particles (held {r['held']})  "
                      f"Jaccard {r['jaccard']:.2f}  d {r['d']:.3f}  R {r['R']:.3f}")
            else:
                print(f"  scoop {r['scoop']}  chunk {r['chunk']:<10} against the target: d {r['d']:.3f} "
                      f"(d_size {r['d_size']:.3f}), volume N s^3 {r['volume_cm3']} cm^3, from the positions' spacing "
                      f"{r['volume_estimate_cm3']} cm^3, mean det F {r['mean_J']:.4f}")
    else:
        out = scooping(args.n_grid, args.device, args.seed, args.scoop, args.variant)
        _print(out)
    return save_json(out, args.json)


if __name__ == "__main__":
    sys.exit(main())

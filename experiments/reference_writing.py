"""Does the scripted writer earn full marks, and does a wrong stroke cost?  (issue #54; docs/tasks.md#cream-writing)

Cream writing, the task's word (CORL): the scripted writer (the task's reference) and two wrong variants, all
written by the same pen from the same start in the same scene and scored by the task's own letter_rewards
(each letter against its stroke, d = d_spec + d_size + handedness, the word by the geometric mean):

* one letter mirrored: the R's stroke mirrored about its own vertical axis (Я).  Of C, O, R, L only R and L are
  chiral: O has two mirror axes, C a horizontal one, so a mirrored C is a C turned 180° (a proper motion on the
  board, which no yaw-invariant score can charge);
* one letter missing: the R not written (the pen skips from the O to the L).

The reference and the mirrored R extrude alike (same segment lengths, same substeps), so they run as two scenes
of one pen; the missing letter extrudes less and runs on its own.

    python experiments/reference_writing.py --n-grid 48                 # CPU, ~30 s: the task's scale
    python experiments/reference_writing.py --n-grid 48 --json out.json

Prints one line per variant (total, reward per letter, particles) and, with ``--json``, writes them.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a file: `experiments` from the repository root

from experiments.reference_cli import add_json_option, save_json  # noqa: E402

WRONG_LETTER = "R"  # chiral (see the module docstring); the letter both wrong variants change


def mirrored(poly: np.ndarray) -> np.ndarray:
    """poly (m,2) mirrored about the vertical line through the middle of its own bounding box, same order."""
    out = np.array(poly, np.float64)
    out[:, 0] = out[:, 0].min() + out[:, 0].max() - out[:, 0]
    return out


def variants(word: str, strokes: list) -> dict:
    """{name: the polylines the pen writes (None: that letter is not written)}."""
    i = word.upper().index(WRONG_LETTER)
    mirror = [mirrored(p) if j == i else p for j, p in enumerate(strokes)]
    missing = [None if j == i else p for j, p in enumerate(strokes)]
    return {"reference": list(strokes), f"one letter mirrored ({WRONG_LETTER})": mirror,
            f"one letter missing ({WRONG_LETTER})": missing}


def write_batch(sim, pen_cfg, start, batch: list[list]) -> tuple[np.ndarray, np.ndarray]:
    """Write each scene's polylines (same letters present in every scene, same segment lengths) with one pen of
    len(batch) scenes; returns positions (B,n,3) and stroke ids (n,) after settling."""
    from topocut.sim.pen import CreamPen
    from topocut.tasks.writing_scene import execute, segment_splits, stroke_actions

    pen = CreamPen(sim, pen_cfg, len(batch), start=start)
    present = [[p for p in polys if p is not None] for polys in batch]
    # the first scene's moves set the substeps of every scene: extrusion must agree across the batch
    splits = segment_splits(present[0], start, pen_cfg.step)
    acts = np.stack([stroke_actions(p, start, pen_cfg.step, splits) for p in present])  # B,T,3
    execute(pen, acts)
    pen.settle()
    return pen.particles()


def writing(n_grid: int = 48, device: str = "cpu", seed: int = 0, word: str = "CORL") -> dict:
    """The variants' rewards: {"rows": [{"variant", "reward", "per_letter", "particles"}], and the settings}.
    ``seed`` is recorded only: the writer and the pen draw no random numbers."""
    from topocut.reward import RewardConfig
    from topocut.sim import SimConfig, init_taichi
    from topocut.tasks import task_config
    from topocut.tasks.writing_scene import letter_rewards, writing_scene

    t0 = time.perf_counter()
    init_taichi(device, cpu_threads=1 if device == "cpu" else None)
    sim, task = SimConfig(n_grid=n_grid, arch=device), task_config("cream_writing", word=word).validate()
    goals, strokes, start, _ = writing_scene(sim, task)
    reward = RewardConfig() if device == "cpu" else RewardConfig(backend="torch", device=device)
    groups: dict[tuple, list[str]] = {}  # the letters present -> the variants that write them (one pen each)
    todo = variants(word, strokes)
    for name, polys in todo.items():
        groups.setdefault(tuple(p is not None for p in polys), []).append(name)
    rows = {}
    for names in groups.values():
        x, stroke = write_batch(sim, task.pen, start, [todo[n] for n in names])
        for b, name in enumerate(names):
            res = letter_rewards(x[b], stroke, goals, reward, spacing=sim.spacing)
            rows[name] = {"variant": name, "reward": round(res["total"], 4),
                          "per_letter": [round(r, 4) for r in res["per_letter"]],
                          "distance": [round(d, 4) for d in res["distance"]],
                          "handedness": [round(h, 4) for h in res["handedness"]], "particles": int(len(stroke))}
    return {"task": "cream_writing", "word": word, "n_grid": n_grid, "device": device, "seed": seed,
            "goal_particles": [int(len(g)) for g in goals], "rows": [rows[n] for n in todo],
            "seconds": round(time.perf_counter() - t0, 1)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n-grid", type=int, default=48)
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    p.add_argument("--word", default="CORL", help=f"task.word; must contain {WRONG_LETTER}")
    add_json_option(p)
    args = p.parse_args(argv)
    if WRONG_LETTER not in args.word.upper():
        p.error(f"--word={args.word!r} has no {WRONG_LETTER}: the wrong variants mirror and drop the {WRONG_LETTER}")
    out = writing(args.n_grid, args.device, word=args.word)
    print(f"cream writing {out['word']}, n_grid {out['n_grid']} (goal particles per letter {out['goal_particles']}), "
          f"{out['seconds']} s:")
    for r in out["rows"]:
        per = ", ".join(f"{v:.2f}" for v in r["per_letter"])
        print(f"  {r['variant']:<26} reward {r['reward']:.3f}  per letter {per}  particles {r['particles']}")
    return save_json(out, args.json)


if __name__ == "__main__":
    sys.exit(main())

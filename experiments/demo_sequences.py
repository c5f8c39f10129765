"""The demonstrations' cutting sequences (docs/data.md): a row per task (one episode of one object each), columns
the initial state, the goal, then each cut (the knife at the end of its stroke, the board, the fragments coloured by
their cluster id after the cut, the step's reward), read back from a merged dataset, so on the CPU.

    python experiments/demo_sequences.py --root outputs [--version latest] [--object cake] [--out seq.png]
"""
import argparse
from pathlib import Path

from topocut.data.episodes import EpisodeDataset
from topocut.data.store import ArtifactStore
from topocut.sim.action import KnifeAction
from topocut.sim.render import goal_colors, render_sequences


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default="outputs", help="artifact store root (outputs_root)")
    ap.add_argument("--dataset", default="demos", help="a merged dataset (data.dataset)")
    ap.add_argument("--version", default="latest")
    ap.add_argument("--tasks", nargs="*", default=["slice", "stick", "dice"])
    ap.add_argument("--object", default="cake")
    ap.add_argument("--index", type=int, default=0, help="which episode of that task and object (0: the first)")
    ap.add_argument("--board-z", type=float, default=0.05)
    ap.add_argument("--out", default="demo_sequences.png")
    args = ap.parse_args(argv)
    path = ArtifactStore(Path(args.root)).resolve("dataset", args.dataset, args.version)
    ds = EpisodeDataset(path / "data.zarr")
    rows = []
    for task in args.tasks:
        found = [e for e in range(ds.num_episodes)
                 if ds.meta(e).get("task") == task and ds.meta(e).get("object") == args.object]
        if len(found) <= args.index:
            raise SystemExit(f"--index {args.index}: {path} holds {len(found)} episodes of {task} on {args.object}")
        steps = ds.episode(found[args.index])
        first = steps[0]
        panels = [(first["x_t"], first["f_t"], None, "initial"),
                  (first["goal"], goal_colors(first["goal_labels"]), None, "goal")]  # 0: not a goal piece, grey
        for i, s in enumerate(steps):  # action: (x, y, yaw, tilt) of the blade plane (docs/contracts.md)
            panels.append((s["x_t1"], s["f_t1"], KnifeAction(*map(float, s["action"][:4])),
                           f"cut {i + 1}: R {float(s['reward']):.2f}"))
        rows.append((f"{task}: {args.object}", panels))
    print(render_sequences(rows, args.out, board_z=args.board_z))


if __name__ == "__main__":
    main()

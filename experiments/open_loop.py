"""Open-loop imitation error of trained policies on their held-out demonstration episodes (topocut.eval.open_loop).

    python experiments/open_loop.py --root outputs --policy pddp_noperc dp3 3dda [--max-episodes 40] [--out DIR]
                                    [--tilt auto|free|zero]

Each checkpoint (every committed version of checkpoint/<policy>, one per training seed, or --checkpoints DIR ...)
acts on the states of the validation episodes it did not train on (its metrics.json split); its cut is compared
with the demonstrator's.  Writes open_loop.md (per task and cut: plane angle, partition error, plane gap in mm, the
previous cut's partition error as a floor; mean [95% bootstrap interval over episodes]) and open_loop.json (every
record, with both actions).
"""
import argparse
import json
import sys
import time
from pathlib import Path

from rich.progress import Progress

from topocut.data.episodes import EpisodeDataset
from topocut.data.store import ArtifactStore, write_json_atomic
from topocut.eval.open_loop import markdown, open_loop, summarize
from topocut.policies import registry
from topocut.policies.config import PLANE_TILTS, SamplerConfig


def _checkpoints(store: ArtifactStore, name: str) -> list[Path]:
    base = store.root / "checkpoint" / name
    found = sorted(p for p in base.glob("v[0-9]*") if (p / "model.ckpt").is_file() and (p / "metrics.json").is_file())
    if not found:
        raise ValueError(f"{base}: no committed checkpoint (vNNN/model.ckpt with metrics.json); train it with stage=bc")
    return found


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default="outputs", help="artifact store root (outputs_root)")
    ap.add_argument("--dataset", default="demos")
    ap.add_argument("--version", default="latest", help="the dataset version the checkpoints trained on")
    ap.add_argument("--policy", nargs="+", required=True, help=f"learned policies: {', '.join(registry.learned())}")
    ap.add_argument("--checkpoints", nargs="*", help="checkpoint directories (vNNN) of a single --policy")
    ap.add_argument("--max-episodes", type=int, default=0, help="the first N validation episodes a checkpoint (0: all)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--board-z", type=float, default=0.05)
    ap.add_argument("--tilt", choices=PLANE_TILTS, default="auto",
                    help="PDDP's plane fit (policy.sampler.tilt): auto | free | zero (docs/policy.md)")
    ap.add_argument("--out", default="open_loop", help="directory for open_loop.md / open_loop.json")
    args = ap.parse_args(argv)
    try:
        for name in args.policy:
            if name not in registry.learned():
                raise ValueError(f"--policy {name!r}: one of {', '.join(registry.learned())}")
        if args.checkpoints and len(args.policy) != 1:
            raise ValueError("--checkpoints needs exactly one --policy")
        store = ArtifactStore(Path(args.root))
        ds = EpisodeDataset(store.resolve("dataset", args.dataset, args.version) / "data.zarr")
        plan = {name: ([Path(c) for c in args.checkpoints] if args.checkpoints else _checkpoints(store, name))
                for name in args.policy}
    except (ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    records, rows = {}, {}
    with Progress() as bar:
        for name, ckpts in plan.items():
            records[name] = []
            for ckpt in ckpts:
                val = json.loads((ckpt / "metrics.json").read_text())["split"]["val"]
                val = val[: args.max_episodes] if args.max_episodes else val
                steps = [ds[i] for e in val for i in range(*ds.episode_range(e))]
                policy = registry.load_learned(name, ckpt / "model.ckpt", device=args.device, board_z=args.board_z,
                                               sampler=SamplerConfig(tilt=args.tilt))
                task = bar.add_task(f"{name} {ckpt.name}", total=len(steps))
                t0 = time.perf_counter()
                recs = open_loop(policy, steps, board_z=args.board_z, progress=lambda t=task: bar.advance(t))
                records[name] += [{**r, "checkpoint": str(ckpt)} for r in recs]
                bar.console.log(f"{name} {ckpt}: {len(val)} episodes, {len(steps)} steps in "
                                f"{time.perf_counter() - t0:.0f} s")
            rows[name] = summarize(records[name], label=name)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "open_loop.json", {"records": records, "rows": rows})
    text = ("Open loop: each checkpoint's cut on the states of its held-out demonstration episodes against the "
            "demonstrator's; mean [95% bootstrap interval over episodes].\n\n" + markdown(rows))
    tmp = out / "open_loop.md.partial"
    tmp.write_text(text)
    tmp.replace(out / "open_loop.md")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

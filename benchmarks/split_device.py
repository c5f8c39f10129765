"""A cut's split on the host (pieces.split: scipy) against the device (pieces_device.split_batch: Taichi kernels).

One particle set (the cake at the grid's particle spacing: ~70k particles at 128³), cut by B different planes
after an earlier cut (the previous labels), timed in the same process both ways:

- host, as CuttingEnv._split runs it: one neighbour search (P.bonds) shared by the scenes holding the same
  particles (MPPI's rollouts from one state), then P.split per scene in threads;
- device: split_batch of all B scenes in one pass (no sharing: every scene its own cell list), including the
  uploads and the download of the labels.

Checks that both give the same labels, then prints the median wall time of ``--repeats`` runs (after a warm-up
that compiles the kernels, printed apart) and the ratio host / device, for B = 1 and B = ``--batch``.

    python benchmarks/split_device.py --device cpu --n-grid 64      # a smoke run
    python benchmarks/split_device.py --device cuda                 # 128³, B = 1 and 16
"""
import argparse
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from topocut.sim import pieces as P
from topocut.sim.action import KnifeAction
from topocut.sim.config import SimConfig
from topocut.sim.objects import ObjectPose, sample_object
from topocut.sim.runtime import init_taichi
from topocut.utils.runtime import host_threads


def host(x, piece, sweeps, spacing):
    pairs = P.bonds(x, spacing)  # shared: every scene holds the same particles
    with ThreadPoolExecutor(max_workers=max(1, min(len(sweeps), host_threads()))) as pool:
        return np.stack(list(pool.map(lambda sw: P.split(x, piece, sw, spacing, pairs), sweeps)))


def device(x, piece, sweeps, spacing):
    from topocut.sim.pieces_device import split_batch

    B = len(sweeps)
    xs = np.broadcast_to(x, (B, *x.shape))  # what CuttingEnv hands over: a (B,n,3) array
    return split_batch(xs, [len(x)] * B, np.broadcast_to(piece, (B, len(piece))), sweeps, spacing)


def timed(fn, repeats):
    out, times = None, []
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return out, float(np.median(times)), min(times), max(times)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda", choices=["cpu", "cuda"])
    ap.add_argument("--n-grid", type=int, default=128)
    ap.add_argument("--object", default="cake")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    init_taichi(args.device)
    cfg = SimConfig(n_grid=args.n_grid)
    x = sample_object(args.object, ObjectPose(0.5, 0.5, yaw=0.1, scale=1.0), spacing=cfg.spacing)[0].astype(np.float64)
    piece = P.split(x, np.zeros(len(x), np.int32), P.blade_sweep(KnifeAction(x=0.47, y=0.5), x, cfg)[0], cfg.spacing)
    rng = np.random.default_rng(args.seed)
    acts = [KnifeAction(x=0.5 + rng.uniform(-0.04, 0.04), y=0.5 + rng.uniform(-0.04, 0.04), yaw=rng.uniform(-1.5, 1.5),
                        tilt=rng.uniform(-0.3, 0.3)) for _ in range(args.batch)]
    sweeps = [P.blade_sweep(a.canonical(), x, cfg)[0] for a in acts]
    print(f"{args.object} at {args.n_grid}^3 spacing: {len(x)} particles, {len(P.bonds(x, cfg.spacing))} bonds; "
          f"device {args.device}, host threads {host_threads()}")
    for B in sorted({1, args.batch}):
        sw = sweeps[:B]
        t = time.perf_counter()
        device(x, piece, sw, cfg.spacing)
        warm = time.perf_counter() - t
        want, th, th_lo, th_hi = timed(lambda sw=sw: host(x, piece, sw, cfg.spacing), args.repeats)
        got, td, td_lo, td_hi = timed(lambda sw=sw: device(x, piece, sw, cfg.spacing), args.repeats)
        same = bool(np.array_equal(got, want))
        print(f"B={B:3d}  host {1e3 * th:8.1f} ms [{1e3 * th_lo:.1f}, {1e3 * th_hi:.1f}]  device {1e3 * td:8.1f} ms "
              f"[{1e3 * td_lo:.1f}, {1e3 * td_hi:.1f}] (first call {1e3 * warm:.0f} ms)  host/device {th / td:5.2f}x  "
              f"pieces {int(want.max()) + 1}  labels equal: {same}")
        if not same:
            raise SystemExit(f"B={B}: device labels differ from the host's at {int((got != want).sum())} particles")


if __name__ == "__main__":
    main()

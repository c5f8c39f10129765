"""A cut's split on the host (pieces.split: scipy) against the device (pieces_device + fields_device: Taichi kernels).

One particle set (the cake at the grid's particle spacing: ~53k particles at 128³), cut by B different planes
after an earlier cut (the previous labels), timed in the same process both ways, the pieces and their velocity
fields as CuttingEnv._split finds them:

- host: one neighbour search (P.bonds) shared by the scenes holding the same particles (MPPI's rollouts from one
  state), then per scene in threads P.split, P.colour, P.cut_off_side and P.field_sides;
- device: the split of all B scenes in one pass (no sharing: every scene its own cell list), then
  fields_device.colour_batch (per-piece summaries, the colouring on the host, each particle's field written
  on the device), including the uploads and the download of the labels.

Checks that both give the same labels and fields, then prints the median wall time of ``--repeats`` runs (after a warm-up
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


def host(x, piece, sweeps, cfg):
    pairs = P.bonds(x, cfg.spacing)  # shared: every scene holds the same particles
    reach = _reach(cfg)

    def one(sw):
        after = P.split(x, piece, sw, cfg.spacing, pairs)
        field = P.colour(x, after, cfg.n_grid, cfg.fields, sw, reach)[0]
        P.cut_off_side(x, piece, after, sw), P.field_sides(x, field, cfg.fields, sw, reach)
        return after, field

    with ThreadPoolExecutor(max_workers=max(1, min(len(sweeps), host_threads()))) as pool:
        return tuple(np.stack(a) for a in zip(*pool.map(one, sweeps)))


def _reach(cfg):
    return cfg.knife_half_thickness + cfg.margin + 2 * cfg.dx  # CuttingEnv._split's


_BODY = {}


def device(x, piece, sweeps, cfg):
    import taichi as ti

    from topocut.sim.fields_device import colour_batch
    from topocut.sim.pieces_device import device_split

    B, n = len(sweeps), len(x)
    ds = device_split(B, n)
    if B not in _BODY:  # the solver's body field (B, rows)
        _BODY[B] = ti.field(ti.i32, shape=(B, ds.n))
    xs, ps = np.zeros((B, ds.n, 3)), np.zeros((B, ds.n), np.int32)
    xs[:, :n], ps[:, :n] = x, piece  # what the solver holds: (B, rows, 3) particles
    labels = ds.run(xs, [n] * B, ps, sweeps, cfg.spacing)[:, :n]
    if colour_batch(ds, _BODY[B], labels, ps[:, :n], cfg.n_grid, cfg.fields, _reach(cfg)) is None:
        raise SystemExit("a label past 64: the host colours this batch")
    return labels, _BODY[B].to_numpy()[:, :n]


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
        device(x, piece, sw, cfg)
        warm = time.perf_counter() - t
        want, th, th_lo, th_hi = timed(lambda sw=sw: host(x, piece, sw, cfg), args.repeats)
        got, td, td_lo, td_hi = timed(lambda sw=sw: device(x, piece, sw, cfg), args.repeats)
        same = all(np.array_equal(g, w) for g, w in zip(got, want))
        print(f"B={B:3d}  host {1e3 * th:8.1f} ms [{1e3 * th_lo:.1f}, {1e3 * th_hi:.1f}]  device {1e3 * td:8.1f} ms "
              f"[{1e3 * td_lo:.1f}, {1e3 * td_hi:.1f}] (first call {1e3 * warm:.0f} ms)  host/device {th / td:5.2f}x  "
              f"pieces {int(want[0].max()) + 1}  labels and fields equal: {same}")
        if not same:
            raise SystemExit(f"B={B}: the device's labels / fields differ from the host's at "
                             f"{[int((g != w).sum()) for g, w in zip(got, want)]} particles")


if __name__ == "__main__":
    main()

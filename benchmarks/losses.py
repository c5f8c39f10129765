"""Position-loss timing: exact EMD (scipy Hungarian on the host) vs the device auction, same process.

python benchmarks/losses.py [--device cpu|cuda] [--batch 16 32] [--points 256] [--tol 0.01] [--warm 150] [--dtype float64] [--repeat 3]
Prints per batch: exact and auction EMD times, their ratio, the auction's rounds and its largest relative
error against the exact cost (bounded by tol, topocut/models/point_losses.py), and Chamfer + Hausdorff times.
"""
from __future__ import annotations

import argparse
import time

import torch

from topocut.metrics import emd as exact_emd
from topocut.models.point_losses import auction_assignment, chamfer, emd_auction, hausdorff


def timeit(fn, repeat: int, device: str, *args, **kw) -> float:
    fn(*args, **kw)  # warm-up
    if device == "cuda":
        torch.cuda.synchronize()
    t = time.perf_counter()
    for _ in range(repeat):
        fn(*args, **kw)
    if device == "cuda":
        torch.cuda.synchronize()
    return (time.perf_counter() - t) / repeat


def both(a, b):
    return chamfer(a, b), hausdorff(a, b)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--batch", type=int, nargs="+", default=[16, 32])
    ap.add_argument("--points", type=int, default=256)
    ap.add_argument("--tol", type=float, nargs="+", default=[0.01])
    ap.add_argument("--dtype", default="float64", choices=["float32", "float64"])
    ap.add_argument("--warm", type=int, nargs="+", default=[150], help="Sinkhorn warm-start iterations (0: none)")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    dt = getattr(torch, args.dtype)
    print(f"device={args.device} ({torch.cuda.get_device_name() if args.device == 'cuda' else 'cpu'}, "
          f"{torch.get_num_threads()} threads) dtype={args.dtype} points={args.points}")
    for B in args.batch:
        g = torch.Generator().manual_seed(B)
        a = torch.rand(B, args.points, 3, generator=g, dtype=dt).to(args.device)
        b = (a + 0.1 * torch.rand(B, args.points, 3, generator=g, dtype=dt).to(args.device)).roll(7, 1)
        ref = exact_emd(a, b)
        t_ex = timeit(exact_emd, args.repeat, args.device, a, b)
        t_cd = timeit(both, args.repeat, args.device, a, b)
        for tol, warm in ((t, w) for t in args.tol for w in args.warm):
            got = emd_auction(a, b, tol=tol, warm_iters=warm)
            rounds = auction_assignment.last_rounds
            err = float(((got - ref) / ref).max())
            t_au = timeit(emd_auction, args.repeat, args.device, a, b, tol=tol,
                          warm_iters=warm)
            print(f"B={B:3d} tol={tol:g} warm={warm}: exact {t_ex * 1e3:8.1f} ms  auction {t_au * 1e3:8.1f} ms  "
                  f"exact/auction {t_ex / t_au:6.2f}  rounds {rounds:5d}  max rel err {err:.2e}  "
                  f"chamfer+hausdorff {t_cd * 1e3:6.2f} ms")


if __name__ == "__main__":
    main()

"""Spectral reward timing: scipy path vs a dense-eigh reference, and the batched torch path with each eigensolver.

python benchmarks/reward.py [--device cpu|cuda] [--batches 16 64 128] [--repeat 5]
Targets: <= 50 ms per 512-point fragment on CPU (scipy); <= 5 ms per fragment batched on a GPU.
"""
from __future__ import annotations

import argparse
import contextlib
import functools
import time

import numpy as np

from topocut.reward import RewardConfig, spectral_descriptors
from topocut.reward.spectral import descriptor, hks_signature, laplacian, resample, smallest_eigenpairs


def cloud(seed: int, n: int = 4000) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.random((n, 3)) * np.array([0.03, 0.15, 0.1])  # a slice-like fragment


def timeit(fn, repeat: int) -> float:
    fn()  # warm-up (imports, allocations, GPU kernels)
    t = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - t) / repeat


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--batches", type=int, nargs="+", default=[16, 64, 128])
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    cfg = RewardConfig()
    p = resample(cloud(0), cfg)  # 512,3
    sigma = 0.01

    def reference():  # dense LAPACK eigh with subset_by_index
        L = laplacian(p, sigma, cfg.knn)
        w, v = smallest_eigenpairs(L, cfg.num_eig + 1, method="eigh")
        return w[1:], hks_signature(w[1:], v[:, 1:], cfg)

    t_ref = timeit(reference, args.repeat)
    t_fast = timeit(lambda: descriptor(p, sigma, cfg), args.repeat)
    w_ref, _ = reference()
    w_fast, _ = descriptor(p, sigma, cfg)
    print(f"one fragment, n={len(p)}, k={cfg.knn}, K={cfg.num_eig}")
    print(f"  scipy eigsh (shift-invert): {1e3 * t_fast:7.2f} ms   (target <= 50 ms)")
    print(f"  scipy eigh subset (ref):    {1e3 * t_ref:7.2f} ms   ratio ref/fast = {t_ref / t_fast:.2f}x"
          f"   max |dlambda| = {np.abs(w_ref - w_fast).max():.1e}")
    t_fps = timeit(lambda: resample(cloud(1, 20000), cfg), args.repeat)
    print(f"  FPS 20000 -> 512 points:    {1e3 * t_fps:7.2f} ms")

    import torch

    if args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda requested but torch.cuda.is_available() is False")
    import dataclasses

    w0, _ = descriptor(resample(cloud(0), cfg), sigma, cfg)
    # subspace-a2: the subspace solver with A^-2 steps (its design before 2026-11-30), against today's A^-4
    solvers = ["device", "subspace-a2", "subspace", "host"] if args.device == "cuda" else \
        ["host", "subspace-a2", "subspace", "device"]
    print(f"batched torch ({args.device}): the reward's eigensolvers (reward.eig_solver), the first the reference")
    for B in args.batches:
        batch = torch.tensor(np.stack([resample(cloud(s), cfg) for s in range(B)]), device=args.device)
        ref = None
        for solver in solvers:
            c = dataclasses.replace(cfg, eig_solver=solver.split("-")[0])
            power = 2 if solver == "subspace-a2" else 4

            def batched(c=c, batch=batch, power=power):
                with steps_of(power):
                    w, s = spectral_descriptors(batch, c, sigma=sigma)
                if args.device == "cuda":
                    torch.cuda.synchronize()
                return w

            t_b = timeit(batched, args.repeat)
            ref = ref or t_b
            wb = batched()[0].cpu().numpy()
            print(f"  B={B:4d} {solver:9s}: {1e3 * t_b:8.1f} ms total, {1e3 * t_b / B:6.2f} ms/fragment, "
                  f"{ref / t_b:5.2f}x the {solvers[0]} solver; vs scipy per fragment {t_fast * B / t_b:6.2f}x; "
                  f"max |dlambda| vs scipy = {np.abs(wb - w0).max():.1e}")


@contextlib.contextmanager
def steps_of(power: int):
    """The reward's subspace solver with A^-power steps for the duration (spectral imports it at each call)."""
    from topocut.reward import eigen

    solver = eigen.smallest_eigenpairs_subspace
    eigen.smallest_eigenpairs_subspace = functools.partial(solver, power=power)
    try:
        yield
    finally:
        eigen.smallest_eigenpairs_subspace = solver


if __name__ == "__main__":
    main()

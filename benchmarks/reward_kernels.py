"""The reward's two Warp kernels against the tensor code they replace, in one process, the reference first.

python benchmarks/reward_kernels.py [--device cpu|cuda] [--repeat 5] [--parts fps sizes]

fps: farthest point sampling.  Two batches of padded fragments shaped like an MPPI cut's (16 rollout scenes' pieces),
each resampled to 512 points by ``fps_torch``:

  64^3    48 clouds of 600-6,000 points
  128^3   48 clouds of 2,000-50,000 points

Methods, in one process, the first the reference: on CUDA the pick loop replayed from one captured CUDA graph a pick
(``fps_torch``'s CUDA path until 2026-12-01, its code kept below), then the loop launched op by op
(``method="loop"``), then the kernel (``method="kernel"``, the default) at several threads a cloud.  Every method's
picks are checked against the reference's, and the reference's against numpy's ``fps`` of each cloud alone.

sizes: every fragment's size descriptor (``topocut.reward.size_batch.fragment_sizes``: the spacing's 5 nearest
neighbours of up to 8,192 particles a fragment, the bodies' neighbour counts and nearest core particle), its
neighbour queries by tensor blocks (``near_method="tensor"``, the reference) and by the Warp kernel (the default):
32 jittered-lattice fragments, 16 scenes of two pieces, ~53k particles a scene at 128^3 and ~6.6k at 64^3.
"""
from __future__ import annotations

import argparse
import contextlib
import time

import numpy as np
import torch

import topocut.metrics.fps_kernel as fk
from topocut.metrics.sampling import fps, fps_torch

CASES = {"64^3": (600, 6000), "128^3": (2000, 50000)}


def batch(lo: int, hi: int, device: str, clouds: int = 48):
    rng = np.random.default_rng(3)
    sizes = rng.integers(lo, hi, clouds)
    pts = [rng.random((int(s), 3)) * [0.03, 0.15, 0.1] for s in sizes]  # slice-like fragments
    P, M = np.zeros((clouds, int(sizes.max()), 3)), np.zeros((clouds, int(sizes.max())), bool)
    for b, c in enumerate(pts):
        P[b, :len(c)], M[b, :len(c)] = c, True
    return pts, torch.tensor(P, device=device), torch.tensor(M, device=device)


def graph_loop(p, dist, top, start, n: int, block_dim=None):
    """``fps_torch``'s CUDA pick loop until 2026-12-01 (the reference; ``fps_picks``'s arguments): ~8 tensor kernels
    a pick captured once in a CUDA graph and replayed n times.  ``top`` and ``block_dim`` are unused."""
    B = p.shape[0]
    ar = torch.arange(B, device=p.device)
    idx = torch.zeros(B, n, dtype=torch.long, device=p.device)
    at = torch.zeros(B, 1, dtype=torch.long, device=p.device)
    cur, dist = start.clone(), dist.clone()

    def step():  # the squared distances as fps_torch's loop sums them: (dx^2 + dy^2) + dz^2
        idx.scatter_(1, at, cur[:, None])
        sq = (p - p[ar, cur][:, None, :]).square_()  # B,N,3
        torch.minimum(dist, sq[..., 0] + sq[..., 1] + sq[..., 2], out=dist)
        torch.argmax(dist, 1, out=cur)
        at.add_(1)

    saved = cur.clone(), dist.clone()
    side = torch.cuda.Stream(device=p.device)
    side.wait_stream(torch.cuda.current_stream(p.device))
    with torch.cuda.stream(side):  # warm-up outside the capture, then undone
        step()
    torch.cuda.current_stream(p.device).wait_stream(side)
    cur.copy_(saved[0])
    dist.copy_(saved[1])
    at.zero_()
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph, capture_error_mode="thread_local"):
        step()
    for _ in range(n):
        graph.replay()
    return idx


@contextlib.contextmanager
def reference_kernels():
    """The reward as before 2026-12-01 for the duration: FPS's picks by the captured graph (on CUDA; the tensor loop
    on the CPU) and ``near`` by tensor blocks."""
    import functools

    import topocut.reward.size_batch as size_batch
    from topocut.metrics import sampling

    saved = fk.fps_picks, size_batch.fragment_sizes, sampling.fps_torch
    if torch.cuda.is_available():
        fk.fps_picks = graph_loop
    else:
        sampling.fps_torch = functools.partial(saved[2], method="loop")
    size_batch.fragment_sizes = functools.partial(saved[1], near_method="tensor")
    try:
        yield
    finally:
        fk.fps_picks, size_batch.fragment_sizes, sampling.fps_torch = saved


def graph_fps(p, m):
    with reference_kernels():
        return fps_torch(p, 512, m)


def timed(fn, repeat: int, device: str):
    def run():
        out = fn()
        if device == "cuda":
            torch.cuda.synchronize()
        return out

    out = run()  # warm-up: compilation, allocations
    t = time.perf_counter()
    for _ in range(repeat):
        run()
    return (time.perf_counter() - t) / repeat, out.cpu().numpy()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--blocks", type=int, nargs="+", default=[128, 256, 512, 1024])
    ap.add_argument("--parts", nargs="+", default=["fps", "sizes"], choices=["fps", "sizes"])
    args = ap.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda requested but torch.cuda.is_available() is False")
    if args.device == "cpu":
        args.blocks = [1]  # Warp runs one thread a block on the CPU
    if "sizes" in args.parts:
        bench_sizes(args)
    for name, (lo, hi) in CASES.items() if "fps" in args.parts else ():
        pts, p, m = batch(lo, hi, args.device)
        methods = [("CUDA graph a pick (reference)", lambda p=p, m=m: graph_fps(p, m))] if args.device == "cuda" else []
        methods.append(("loop", lambda p=p, m=m: fps_torch(p, 512, m, method="loop")))
        for bd in args.blocks:
            def kernel(bd=bd, p=p, m=m):
                fk.BLOCK_DIM = bd
                return fps_torch(p, 512, m)
            methods.append((f"kernel, {bd} threads a cloud", kernel))
        print(f"{name}: {len(pts)} clouds of {lo:,}-{hi:,} points -> 512 ({args.device}, mean of {args.repeat})")
        ref_t, ref = None, None
        for label, fn in methods:
            t, idx = timed(fn, args.repeat, args.device)
            if ref is None:
                ref_t, ref = t, idx
                same = sum(int(np.array_equal(idx[b], fps(c, 512))) for b, c in enumerate(pts))
                check = f"picks equal numpy's fps for {same}/{len(pts)} clouds"
            else:
                check = "picks equal the reference's" if np.array_equal(idx, ref) else "PICKS DIFFER"
            print(f"  {label:32s} {1e3 * t:8.2f} ms  {ref_t / t:6.2f}x   {check}")


def lattice(shape, rng, h: float = 0.004):
    """The simulator's jittered lattice (+-0.25 spacing an axis), turned at random."""
    g = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1).reshape(-1, 3) * h
    g = g + rng.uniform(-0.25, 0.25, g.shape) * h
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return g @ q.T


def bench_sizes(args) -> None:
    from topocut.reward import RewardConfig
    from topocut.reward.size import size_descriptor
    from topocut.reward.size_batch import fragment_sizes

    cfg = RewardConfig(backend="torch", size_solver="device", device=args.device)
    for name, side in (("64^3", 19), ("128^3", 38)):  # a scene ~ side^3 particles, cut into two pieces
        rng = np.random.default_rng(5)
        goal = np.array([size_descriptor(lattice((side, side // 3, side), rng))])
        items = []
        for _ in range(16):
            k = int(rng.integers(side // 5, side // 2))
            items += [(lattice((side, k, side), rng), goal), (lattice((side, side - k, side), rng), goal)]
        P = sum(len(p) for p, _ in items)
        ref_t, ref = None, None
        print(f"sizes {name}: {len(items)} fragments, {P:,} particles ({args.device}, mean of {args.repeat})")
        for label, method in (("tensor blocks (reference)", "tensor"), ("kernel", "kernel")):
            def run(method=method, items=items):
                out = fragment_sizes(items, cfg, near_method=method)
                if args.device == "cuda":
                    torch.cuda.synchronize()
                return out

            run()
            t = time.perf_counter()
            for _ in range(args.repeat):
                out = run()
            t = (time.perf_counter() - t) / args.repeat
            desc = np.stack([d for d, _ in out])
            if ref is None:
                ref_t, ref, check = t, desc, ""
            else:
                m = ~np.isnan(ref)
                err = float(np.abs(desc[m] - ref[m]).max() / np.abs(ref[m]).max())
                same = np.array_equal(np.isnan(desc), np.isnan(ref))
                check = f"descriptors within {err:.1e} of the reference's" + ("" if same else ", NaN PATTERN DIFFERS")
            print(f"  {label:32s} {1e3 * t:8.2f} ms  {ref_t / t:6.2f}x   {check}")


if __name__ == "__main__":
    main()

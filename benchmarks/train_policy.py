"""PDDP throughput: training samples/s and sampling latency per action for T in {8, 32, 128}.

    python benchmarks/train_policy.py --device cpu|cuda [--blocks 12] [--batch 32] [--points 256]

Ratios are printed against reference runs in the same process: training against a 2-block
model, sampling latency against T = 8.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from topocut.policies.config import PDDPConfig, PolicyTrainConfig
from topocut.policies.module import PDDPModule, num_parameters
from topocut.policies.plane import action_from_mask


def sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize()


def synthetic_batch(B, N, G, device, seed=0):
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand(B, N, 3, generator=g) * 0.3 + 0.35
    return {"points": pts.to(device), "labels": torch.randint(-1, 4, (B, N), generator=g).to(device),
            "mask": (pts[..., 0] > 0.5).long().to(device), "history": torch.zeros(B, 21, device=device),
            "goal": (torch.rand(B, G, 3, generator=g) * 0.3 + 0.35).to(device)}


def train_rate(blocks, args, device) -> tuple[float, int]:
    module = PDDPModule(PDDPConfig(n_blocks=blocks), args.encoder, args.ckpt,
                        PolicyTrainConfig(num_points=args.points)).to(device)
    opt = module.configure_optimizers()["optimizer"]
    batch = synthetic_batch(args.batch, args.points, args.goal_points, device)

    def step():
        loss = module.loss(batch)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        module.ema.update_parameters(module.model)

    for _ in range(args.warmup):
        step()
    sync(device)
    t0 = time.perf_counter()
    for _ in range(args.iters):
        step()
    sync(device)
    return args.batch * args.iters / (time.perf_counter() - t0), num_parameters(module.model)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--blocks", type=int, default=12)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--points", type=int, default=256)
    ap.add_argument("--goal-points", type=int, default=256)
    ap.add_argument("--iters", type=int, default=5)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--encoder", default="none", choices=["none", "graphconv", "pretrained"])
    ap.add_argument("--ckpt", default=None, help="pretrain checkpoint for --encoder pretrained")
    ap.add_argument("--steps", type=int, nargs="+", default=[8, 32, 128])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    device = torch.device(args.device)
    torch.manual_seed(0)

    ref, _ = train_rate(2, args, device)
    rate, n_params = train_rate(args.blocks, args, device)
    print(f"device={args.device} encoder={args.encoder} batch={args.batch} points={args.points}")
    print(f"train  {args.blocks} blocks ({n_params / 1e6:.2f} M params): {rate:8.1f} samples/s  "
          f"(2-block reference {ref:8.1f} samples/s, ratio {rate / ref:.2f})")

    module = PDDPModule(PDDPConfig(n_blocks=args.blocks), args.encoder, args.ckpt,
                        PolicyTrainConfig(num_points=args.points)).to(device).eval()
    batch = synthetic_batch(1, args.points, args.goal_points, device, seed=1)
    gen = torch.Generator(device=device).manual_seed(0)
    module.sample_masks(batch, steps=2, generator=gen)  # warm up kernels
    base = None
    for T in args.steps:
        times = []
        for _ in range(args.repeats):
            sync(device)
            t0 = time.perf_counter()
            module.sample_masks(batch, steps=T, generator=gen)
            sync(device)
            times.append(time.perf_counter() - t0)
        lat = float(np.median(times))
        base = base or lat
        print(f"sample T={T:4d}: {lat * 1e3:9.1f} ms/action  (ratio to T={args.steps[0]}: {lat / base:.2f})")
    pts = batch["points"][0].cpu().numpy()
    m = (pts[:, 0] > 0.5).astype(np.uint8)
    for method in ("svm", "lsq"):
        t0 = time.perf_counter()
        for _ in range(args.repeats):
            action_from_mask(pts, m, method)
        print(f"plane fit ({method}): {(time.perf_counter() - t0) / args.repeats * 1e3:.1f} ms")


if __name__ == "__main__":
    main()

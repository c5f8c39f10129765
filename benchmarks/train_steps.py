"""Where a training step of F goes on a real dataset, against synthetic box cuts in the same process.

    python benchmarks/train_steps.py --dataset <outputs>/dataset/demos/v001/data.zarr --device cuda \
        [--steps 300 --batch 64 --amp --workers 4 --emd-tol 0.01 --emd-method auto --emd-rounds 0]

`benchmarks/train.py` times F on synthetic box-cut transitions from an untrained model; `make paper`'s
pretraining ran ~8x slower a sample than it.  This script trains F for --steps steps (AdamW with the module's
settings and warm-up) on batches of the dataset's training split (EpisodeDataModule, its loader and workers), and, as the
reference, on synthetic transitions with the same options, timing every part of a step with a device sync
between them: the batch's fetch, the forward pass, chamfer + Hausdorff, the EMD (its auction rounds), the
Hungarian cluster loss, backward + optimiser step.  Printed per window of steps, so that the cost of the EMD
as the predictions approach their targets shows.  Lightning's own overheads: ``trainer.profiler=simple``.
"""
from __future__ import annotations

import argparse
import contextlib
import itertools
import time

import torch

from topocut.models import DynamicsModule, EpisodeDataModule
from topocut.models.config import DynamicsConfig
from topocut.models.datamodule import TransitionDataset, synthetic_steps
from topocut.models.losses import hungarian_cluster_loss, masked_targets
from topocut.models.point_losses import auction_assignment, chamfer, emd, exact_rows, hausdorff

PARTS = ("fetch", "forward", "cd+hd", "emd", "topo", "backward+step")


def loaders(args, cfg: DynamicsConfig):
    """(name, endless iterator of batches) of the dataset and of the synthetic reference."""
    dm = EpisodeDataModule.from_config(args.dataset, cfg, batch_size=args.batch, num_workers=args.workers)
    dm.setup()
    syn = TransitionDataset(synthetic_steps(max(4 * args.batch, 256), 2048, seed=0), noise_std=cfg.noise_std,
                            train=True, num_points=cfg.num_points, sort=cfg.sort, num_labels=cfg.num_labels)
    dl = torch.utils.data.DataLoader(syn, batch_size=args.batch, shuffle=True, drop_last=True)
    print(f"dataset: {len(dm.train_set)} training steps ({args.dataset}); synthetic: {len(syn)}")
    return [("dataset", itertools.chain.from_iterable(itertools.repeat(dm.train_dataloader()))),
            ("synthetic", itertools.chain.from_iterable(itertools.repeat(dl)))]


def train(batches, cfg: DynamicsConfig, args) -> list[dict]:
    """Per step: seconds of each part and the auction's rounds."""
    dev = torch.device(args.device)
    torch.manual_seed(0)
    module = DynamicsModule(cfg).to(dev)
    opt = torch.optim.AdamW(module.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)  # the module's, with
    warm = torch.optim.lr_scheduler.LambdaLR(opt, lambda k: min(1.0, (k + 1) / cfg.warmup_steps))  # its warm-up
    amp = torch.autocast("cuda", dtype=torch.bfloat16) if args.amp and dev.type == "cuda" else contextlib.nullcontext()
    rows, t = [], time.perf_counter()

    def lap(row, key):
        nonlocal t
        if dev.type == "cuda":
            torch.cuda.synchronize()
        now = time.perf_counter()
        row[key], t = now - t, now

    for _ in range(args.steps):
        row = {}
        t = time.perf_counter()
        b = {k: v.to(dev, non_blocking=True) for k, v in next(batches).items()}
        lap(row, "fetch")
        with amp:
            pred, logits = module(b)
        lap(row, "forward")
        v = b["valid"]
        c = b["x_t1"].mean(1, keepdim=True)
        p, q = ((pred.float() - c) / cfg.pos_scale).double(), ((b["x_t1"] - c) / cfg.pos_scale).double()
        cd_hd = chamfer(p, q, v).mean() + hausdorff(p, q, v).mean()
        lap(row, "cd+hd")
        e = emd(p, q, v, args.emd_method, args.emd_tol, args.emd_rounds).mean()
        row["rounds"] = getattr(auction_assignment, "last_rounds", 0)
        row["host"] = getattr(exact_rows, "last_items", 0)
        lap(row, "emd")
        topo = hungarian_cluster_loss(logits.float(), masked_targets(b["f_t1"].long(), v))
        lap(row, "topo")
        loss = cfg.lambda_pos * (cd_hd + e).float() + cfg.lambda_topo * topo
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        warm.step()
        lap(row, "backward+step")
        rows.append(row)
    return rows


def report(name: str, rows: list[dict], batch: int, window: int) -> float:
    print(f"\n{name}: ms a step by part (mean over each window), the auction's rounds (mean / max), the items a step "
          "solved on the host past --emd-rounds (mean)")
    print(f"{'steps':>9} " + " ".join(f"{p:>13}" for p in PARTS) + f" {'total':>8} {'samples/s':>9} {'rounds':>11} "
          f"{'host':>5}")
    for lo in range(0, len(rows), window):
        w = rows[lo:lo + window]
        ms = {p: 1e3 * sum(r[p] for r in w) / len(w) for p in PARTS}
        total = sum(ms.values())
        rounds = [r["rounds"] for r in w]
        print(f"{lo:>4}-{lo + len(w) - 1:<4} " + " ".join(f"{ms[p]:>13.1f}" for p in PARTS) +
              f" {total:>8.1f} {1e3 * batch / total:>9.0f} {sum(rounds) / len(w):>6.0f}/{max(rounds):<4} "
              f"{sum(r['host'] for r in w) / len(w):>5.1f}")
    steady = rows[len(rows) // 2:]
    return sum(sum(r[p] for p in PARTS) for r in steady) / len(steady)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", required=True, help="an episode dataset's data.zarr")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--workers", type=int, default=4)
    ap.add_argument("--window", type=int, default=50)
    ap.add_argument("--amp", action="store_true", help="bf16 autocast of the forward pass (trainer=gpu's bf16-mixed)")
    ap.add_argument("--emd-tol", type=float, default=DynamicsConfig.emd_tol)
    ap.add_argument("--emd-method", default=DynamicsConfig.emd_method, choices=["auto", "exact", "auction"])
    ap.add_argument("--emd-rounds", type=int, default=DynamicsConfig.emd_rounds,
                    help="the auction's round budget (model.emd_rounds; 0: none)")
    args = ap.parse_args(argv)
    cfg = DynamicsConfig().validate()
    steady = {}
    for name, batches in loaders(args, cfg):
        steady[name] = report(name, train(batches, cfg, args), args.batch, args.window)
    print(f"\nsecond half of the steps: dataset {1e3 * steady['dataset']:.1f} ms a step, synthetic "
          f"{1e3 * steady['synthetic']:.1f} ms: dataset / synthetic = {steady['dataset'] / steady['synthetic']:.2f}x")


if __name__ == "__main__":
    main()

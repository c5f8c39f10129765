"""Training / inference throughput of the dynamics model F: graph transformer vs PointNet (Table 2).

    python benchmarks/train.py --device cuda [--batch 16 --points 256 --steps 10]
    python benchmarks/train.py --device cuda --batches 16 64 256 [--amp]

For each model choice: parameter counts (whole F and the encoder Φ), training samples/s (forward,
loss = CD + EMD + HD + Hungarian cluster loss, backward, AdamW step) and inference samples/s, measured
on the CPU (reference, same process, at --batch in float32) and on --device; prints device/CPU and
pointnet/graph ratios.  With --batches the device run sweeps those batch sizes and, with --amp, each
also under bf16 autocast (CUDA; the losses are taken in float32 on the model's outputs), printing
samples/s and the ratio to the device's own --batch float32 run measured in the same process.
The loss runs with the module's options (the batch's ``valid`` rows, ``emd_method`` auto: the device
auction EMD on CUDA, scipy's exact one on the CPU); "CD+EMD+HD ms" times the position losses alone.
Data: synthetic box-cut transitions (topocut.models.datamodule.synthetic_steps), pre-batched.
"""
from __future__ import annotations

import argparse
import contextlib
import time

import torch

from topocut.models.config import DynamicsConfig
from topocut.models.datamodule import TransitionDataset, synthetic_steps
from topocut.models.losses import dynamics_loss, position_losses
from topocut.models.pointnet import build_model

MODELS = ("graph_transformer", "pointnet")


def make_batch(batch: int, points: int, device: str) -> dict:
    ds = TransitionDataset(synthetic_steps(batch, max(2 * points, 512), seed=0), num_points=points, sort=True)
    items = [ds[i] for i in range(batch)]
    return {k: torch.stack([it[k] for it in items]).to(device) for k in items[0]}


def sub_batch(batch: dict, size: int, device: str) -> dict:
    """The first ``size`` samples of a (larger) batch on ``device``: synthetic_steps draws its steps in sequence,
    so they equal make_batch(size, ...)."""
    return {k: v[:size].to(device) for k, v in batch.items()}


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def timed(fn, device: str, steps: int, warmup: int = 2) -> float:
    """Seconds per call of fn, after warm-up."""
    for _ in range(warmup):
        fn()
    sync(device)
    t0 = time.perf_counter()
    for _ in range(steps):
        fn()
    sync(device)
    return (time.perf_counter() - t0) / steps


def autocast(device: str, amp: bool):
    """bf16 autocast on CUDA when ``amp``, else a no-op context."""
    if amp and not device.startswith("cuda"):
        raise ValueError("--amp (bf16 autocast) is measured on CUDA only")
    return torch.autocast("cuda", dtype=torch.bfloat16) if amp else contextlib.nullcontext()


def measure(name: str, device: str, batch: dict, steps: int, amp: bool = False, loss_only: bool = True) -> dict:
    torch.manual_seed(0)
    cfg = DynamicsConfig(model=name, num_points=batch["x_t"].shape[1])
    model = build_model(cfg).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr)
    x, f, m, valid = batch["x_t"], batch["f_t"], batch["mask"], batch.get("valid")
    B = x.shape[0]

    def train_step():
        with autocast(device, amp):
            pred, logits = model(x, f, x, m)
        loss = dynamics_loss(pred.float(), logits.float(), batch["x_t1"], batch["f_t1"], cfg, valid)["loss"]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    @torch.no_grad()
    def infer():
        with autocast(device, amp):
            model(x, f, x, m)

    @torch.no_grad()
    def pos_only():
        position_losses(x, batch["x_t1"], cfg.pos_scale, valid, cfg.emd_method, cfg.emd_tol, cfg.emd_rounds)

    model.train()
    t_train = timed(train_step, device, steps)
    model.eval()
    t_infer = timed(infer, device, steps)
    t_loss = timed(pos_only, device, steps) if loss_only else float("nan")
    return {"params": sum(p.numel() for p in model.parameters()),
            "enc_params": sum(p.numel() for p in model.encoder.parameters()),
            "train_sps": B / t_train, "infer_sps": B / t_infer, "pos_loss_ms": 1e3 * t_loss}


def fit_accuracy(name: str, device: str, batch: int, points: int, steps: int) -> dict:
    """Train F for ``steps`` AdamW steps on synthetic box cuts; cluster accuracy / Chamfer on unseen cuts."""
    from topocut.metrics import chamfer
    from topocut.models.losses import cluster_accuracy

    torch.manual_seed(0)
    cfg = DynamicsConfig(model=name, num_points=points)
    model = build_model(cfg).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    train = TransitionDataset(synthetic_steps(256, 2 * points, seed=1), points, noise_std=cfg.noise_std, train=True)
    val = TransitionDataset(synthetic_steps(64, 2 * points, seed=2), points)
    loader = torch.utils.data.DataLoader(train, batch_size=batch, shuffle=True, drop_last=True)
    done, t0 = 0, time.perf_counter()
    while done < steps:
        for b in loader:
            b = {k: v.to(device) for k, v in b.items()}
            pred, logits = model(b["x_t"], b["f_t"], b["x_t"], b["mask"])
            loss = dynamics_loss(pred, logits, b["x_t1"], b["f_t1"], cfg)["loss"]
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            done += 1
            if done == steps:
                break
    model.eval()
    vb = {k: torch.stack([val[i][k] for i in range(len(val))]).to(device) for k in val[0]}
    with torch.no_grad():
        pred, logits = model(vb["x_t"], vb["f_t"], vb["x_t"], vb["mask"])
    return {"acc": cluster_accuracy(logits.argmax(-1), vb["f_t1"]).mean().item(),
            "chamfer": chamfer(pred, vb["x_t1"]).mean().item(), "seconds": time.perf_counter() - t0}


def sweep(name: str, device: str, data: dict, ref: dict, batches: list[int], amp: bool, steps: int) -> list[tuple]:
    """(batch, precision, result) per batch size (and bf16 under ``amp``); ``ref`` is the batch-reference fp32 run."""
    rows = []
    for b in batches:
        for precision in ("fp32", "bf16") if amp else ("fp32",):
            if b == ref["batch"] and precision == "fp32":
                rows.append((b, precision, ref))
                continue
            r = measure(name, device, sub_batch(data, b, device), steps, amp=precision == "bf16", loss_only=False)
            rows.append((b, precision, r))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--batch", type=int, default=16, help="reference batch size (CPU run and the ratios' base)")
    ap.add_argument("--batches", type=int, nargs="+", default=None,
                    help="batch sizes swept on --device (e.g. 16 64 256); default: --batch only")
    ap.add_argument("--amp", action="store_true", help="also measure each batch size under bf16 autocast (CUDA)")
    ap.add_argument("--points", type=int, default=256)
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--cpu-steps", type=int, default=3, help="timed steps of the CPU reference run")
    ap.add_argument("--fit-steps", type=int, default=0,
                    help="also train each model this many steps on synthetic cuts and report held-out accuracy")
    ap.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    args = ap.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda requested but torch.cuda.is_available() is False")
    if args.amp and args.device != "cuda":
        raise SystemExit("--amp (bf16 autocast) needs --device cuda")
    batches = args.batches or [args.batch]
    if min(batches) < 1 or args.batch < 1:
        raise SystemExit("batch sizes must be >= 1")

    print(f"batch {args.batch}" + (f" (sweep {' '.join(map(str, batches))}{', fp32 + bf16 autocast' if args.amp else ''})"
                                   if args.batches or args.amp else "") +
          f", {args.points} points, torch {torch.__version__}, {torch.get_num_threads()} CPU threads"
          + (f", {torch.cuda.get_device_name()}" if args.device == "cuda" else ""))
    data = make_batch(max([args.batch, *batches]), args.points, "cpu")
    results = {}
    for name in args.models:
        ref = measure(name, "cpu", sub_batch(data, args.batch, "cpu"), args.cpu_steps)
        dev = ref if args.device == "cpu" else measure(name, args.device, sub_batch(data, args.batch, args.device),
                                                       args.steps)
        dev["batch"] = args.batch
        results[name] = (ref, dev)
        print(f"\n{name}: {ref['params']:,} parameters (encoder Φ {ref['enc_params']:,})")
        print(f"  {'':10s} {'train samples/s':>16s} {'infer samples/s':>16s} {'CD+EMD+HD ms':>13s}   (batch {args.batch})")
        print(f"  {'cpu':10s} {ref['train_sps']:16.1f} {ref['infer_sps']:16.1f} {ref['pos_loss_ms']:13.1f}")
        if args.device != "cpu":
            print(f"  {args.device:10s} {dev['train_sps']:16.1f} {dev['infer_sps']:16.1f} {dev['pos_loss_ms']:13.1f}")
        print(f"  {args.device}/cpu ratio: train {dev['train_sps'] / ref['train_sps']:.2f}x, "
              f"infer {dev['infer_sps'] / ref['infer_sps']:.2f}x")
        if args.batches or args.amp:
            print(f"  on {args.device}, ratios to batch {args.batch} fp32 ({dev['train_sps']:.1f} train samples/s):")
            print(f"  {'batch':>7s} {'precision':>9s} {'train samples/s':>16s} {'ratio':>7s} {'infer samples/s':>16s}")
            for b, precision, r in sweep(name, args.device, data, dev, batches, args.amp,
                                         args.steps if args.device != "cpu" else args.cpu_steps):
                print(f"  {b:7d} {precision:>9s} {r['train_sps']:16.1f} {r['train_sps'] / dev['train_sps']:6.2f}x "
                      f"{r['infer_sps']:16.1f}")
    if len(results) == len(MODELS):
        (g_ref, g_dev), (p_ref, p_dev) = results["graph_transformer"], results["pointnet"]
        print(f"\npointnet / graph_transformer: parameters {p_ref['params'] / g_ref['params']:.2f}x, "
              f"train time {g_dev['train_sps'] / p_dev['train_sps']:.2f}x, "
              f"inference time {g_dev['infer_sps'] / p_dev['infer_sps']:.2f}x  (on {args.device})")
    if args.fit_steps:
        print(f"\nsynthetic box cuts, {args.fit_steps} steps on {args.device}: held-out cluster accuracy / Chamfer")
        for name in args.models:
            r = fit_accuracy(name, args.device, args.batch, args.points, args.fit_steps)
            print(f"  {name:18s} acc {r['acc']:.3f}  chamfer {r['chamfer']:.5f}  ({r['seconds']:.0f} s)")


if __name__ == "__main__":
    main()

"""Lightning wrapper of the dynamics model F and the loader of its perception encoder Φ.

``DynamicsModule(cfg)`` trains F on batches of ``TransitionDataset`` (x_t, f_t, mask, x_t1, f_t1, seen) with
L = λ_pos (CD + EMD + HD) + λ_topo L_topo, AdamW and a linear-warmup cosine schedule.  Only the
plain-typed fields of ``DynamicsConfig`` are saved as hyperparameters, so a checkpoint loads without
unpickling project classes (``torch.load(weights_only=True)``).
Logged: train/loss, train/loss_pos, train/loss_topo, val/loss, val/cluster_acc, val/chamfer and, when
the batch holds them, val/cluster_acc_seen and val/cluster_acc_unseen (held-out objects).  Beside them,
val/mask_rule_acc{,_seen,_unseen}: the accuracy of a rule with no learning, "each input cluster splits
along the cut mask" (ids f_t * 2 + mask), the floor a learned F has to beat (docs/perception.md).
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import lightning as L
import torch

from topocut.models.config import DynamicsConfig
from topocut.models.losses import cluster_accuracy, dynamics_loss
from topocut.models.pointnet import build_model


def _as_config(cfg) -> DynamicsConfig:
    if cfg is None:
        return DynamicsConfig()
    if isinstance(cfg, DynamicsConfig):
        return cfg
    valid = {f.name for f in dataclasses.fields(DynamicsConfig)}
    bad = [k for k in dict(cfg) if k not in valid]
    if bad:
        raise KeyError(f"unknown DynamicsConfig field {bad[0]!r}; valid: {', '.join(sorted(valid))}")
    return DynamicsConfig(**dict(cfg))


class DynamicsModule(L.LightningModule):
    def __init__(self, cfg: DynamicsConfig | dict | None = None):
        super().__init__()
        self.cfg = _as_config(cfg).validate()
        self.save_hyperparameters({"cfg": dataclasses.asdict(self.cfg)})
        self.model = build_model(self.cfg)

    @property
    def encoder(self):
        """Φ: the TopoEncoder (``t_graph_encoder``) of the graph model, PointNetEncoder of the pointnet one."""
        return self.model.encoder

    def forward(self, batch: dict):
        x_t, mask = batch["x_t"], batch["mask"].long()
        return self.model(x_t, batch["f_t"].long(), x_t, mask)  # the action cloud is x_t with the cut mask

    def _step(self, batch: dict):
        pred_x, logits = self(batch)
        losses = dynamics_loss(pred_x, logits, batch["x_t1"], batch["f_t1"].long(), self.cfg)
        return pred_x, logits, losses

    def training_step(self, batch: dict, batch_idx: int):
        _, _, losses = self._step(batch)
        bs = batch["x_t"].shape[0]
        for k in ("loss", "loss_pos", "loss_topo"):
            self.log(f"train/{k}", losses[k], prog_bar=k == "loss", batch_size=bs)
        return losses["loss"]

    def validation_step(self, batch: dict, batch_idx: int):
        from topocut.metrics import chamfer

        pred_x, logits, losses = self._step(batch)
        bs = batch["x_t"].shape[0]
        acc = cluster_accuracy(logits.argmax(-1), batch["f_t1"].long()).float()  # B
        rule = cluster_accuracy(batch["f_t"].long() * 2 + batch["mask"].long(), batch["f_t1"].long()).float()  # B
        self.log("val/loss", losses["loss"], batch_size=bs)
        self.log("val/cluster_acc", acc.nanmean(), prog_bar=True, batch_size=bs)
        self.log("val/chamfer", chamfer(pred_x, batch["x_t1"]).mean(), batch_size=bs)  # scene units
        seen = batch.get("seen", torch.ones(bs, dtype=torch.bool, device=acc.device)).bool()
        self.log("val/mask_rule_acc", rule.nanmean(), batch_size=bs)
        for name, sel in (("seen", seen), ("unseen", ~seen)):
            if sel.any():
                self.log(f"val/cluster_acc_{name}", acc[sel].nanmean(), batch_size=int(sel.sum()))
                self.log(f"val/mask_rule_acc_{name}", rule[sel].nanmean(), batch_size=int(sel.sum()))

    def configure_optimizers(self):
        opt = torch.optim.AdamW(self.parameters(), lr=self.cfg.lr, weight_decay=self.cfg.weight_decay)
        total = self.trainer.estimated_stepping_batches if self.trainer is not None else 10_000
        total = int(total) if math.isfinite(total) else 10_000
        warm, floor = min(self.cfg.warmup_steps, max(total // 10, 1)), self.cfg.min_lr_ratio

        def factor(step: int) -> float:
            if step < warm:
                return (step + 1) / warm
            t = min((step - warm) / max(total - warm, 1), 1.0)
            return floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * t))

        sched = torch.optim.lr_scheduler.LambdaLR(opt, factor)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}


def load_dynamics(ckpt_path) -> DynamicsModule:
    """The DynamicsModule saved in a Lightning checkpoint (CPU); clear errors naming the file."""
    path = Path(ckpt_path)
    if not path.is_file():
        raise FileNotFoundError(f"perception checkpoint {path} does not exist")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - truncated zip, pickle or unsafe-type errors all mean "unreadable"
        raise ValueError(f"perception checkpoint {path} is unreadable or corrupt: {type(e).__name__}: {e}") from e
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt or "cfg" not in ckpt.get("hyper_parameters", {}):
        keys = ", ".join(map(str, ckpt)) if isinstance(ckpt, dict) else type(ckpt).__name__
        raise ValueError(f"perception checkpoint {path} is not a DynamicsModule checkpoint: it needs 'state_dict' and "
                         f"'hyper_parameters.cfg', found {keys}")
    module = DynamicsModule(ckpt["hyper_parameters"]["cfg"])
    try:
        module.load_state_dict(ckpt["state_dict"])
    except RuntimeError as e:
        raise ValueError(f"perception checkpoint {path} does not match its own config: {e}") from e
    return module


def load_encoder(ckpt_path):
    """Φ from a pretrain checkpoint, frozen (no grad) and in eval mode."""
    enc = load_dynamics(ckpt_path).encoder
    enc.eval()
    enc.requires_grad_(False)
    return enc

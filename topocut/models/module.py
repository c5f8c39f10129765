"""Lightning wrapper of the dynamics model F and the loader of its perception encoder Φ.

``DynamicsModule(cfg)`` trains F on batches of ``TransitionDataset`` (x_t, f_t, mask, x_t1, f_t1, seen) with
L = λ_pos (CD + EMD + HD) + λ_topo L_topo, AdamW and a linear-warmup cosine schedule.  Only the
plain-typed fields of ``DynamicsConfig`` are saved as hyperparameters, so a checkpoint loads without
unpickling project classes (``torch.load(weights_only=True)``).
Logged: train/loss, train/loss_pos, train/loss_topo (per step and as epoch means), val/loss, val/cluster_acc,
val/chamfer and, when the epoch held them, val/cluster_acc_seen and val/cluster_acc_unseen (held-out objects).
Beside them, val/mask_rule_acc{,_seen,_unseen}: the accuracy of a rule with no learning, "each input cluster
splits along the cut mask" (ids f_t * 2 + mask), the floor a learned F has to beat (docs/perception.md), and what
F adds to it: val/cluster_acc_rule_wrong{,_seen,_unseen}, F's cluster accuracy on the points where the rule is
wrong (the rule scores 0 there; pooled over those points), and val/cluster_err_reduction{,_seen,_unseen},
1 - (1 - cluster_acc) / (1 - mask_rule_acc) of the epoch means: 0 = the rule's errors, 1 = none, < 0 = worse.
Validation values are means over the epoch's samples on all DDP ranks (``EpochMeans``), and a batch's
``valid`` rows (TransitionDataset: padding copies excluded) are the only ones any loss or metric counts.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import lightning as L
import torch

from topocut.models.config import DynamicsConfig
from topocut.models.losses import dynamics_loss, error_reduction, masked_targets, matched_correct, per_sample
from topocut.models.pointnet import build_model
from topocut.utils.training import EpochMeans

SPLITS = ("", "_seen", "_unseen")
VAL_KEYS = ("val/loss", "val/chamfer",
            *(f"val/{k}{s}" for s in SPLITS for k in ("cluster_acc", "mask_rule_acc", "cluster_acc_rule_wrong")))
DERIVED_KEYS = tuple(f"val/cluster_err_reduction{s}" for s in SPLITS)  # from the epoch means, at epoch end



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
        self.val_means = EpochMeans(VAL_KEYS)  # no persistent state: checkpoints hold the model only

    @property
    def encoder(self):
        """Φ: the TopoEncoder (``t_graph_encoder``) of the graph model, PointNetEncoder of the pointnet one."""
        return self.model.encoder

    def forward(self, batch: dict):
        x_t, mask = batch["x_t"], batch["mask"].long()
        return self.model(x_t, batch["f_t"].long(), x_t, mask)  # the action cloud is x_t with the cut mask

    def _step(self, batch: dict):
        pred_x, logits = self(batch)
        losses = dynamics_loss(pred_x, logits, batch["x_t1"], batch["f_t1"].long(), self.cfg, batch.get("valid"))
        return pred_x, logits, losses

    def training_step(self, batch: dict, batch_idx: int):
        _, _, losses = self._step(batch)
        bs = batch["x_t"].shape[0]
        for k in ("loss", "loss_pos", "loss_topo"):  # epoch means for MetricHistory (loss.png, history.json)
            self.log(f"train/{k}", losses[k], prog_bar=k == "loss", batch_size=bs, on_step=True, on_epoch=True,
                     sync_dist=True)
        return losses["loss"]

    def validation_step(self, batch: dict, batch_idx: int):
        from topocut.metrics import chamfer

        pred_x, logits, losses = self._step(batch)
        bs, valid = batch["x_t"].shape[0], batch.get("valid")
        target = masked_targets(batch["f_t1"].long(), valid)
        labelled = (target >= 0).to(logits.device)
        ok = matched_correct(logits.argmax(-1), target).to(logits.device)  # B,N
        rule_ok = matched_correct(batch["f_t"].long() * 2 + batch["mask"].long(), target).to(logits.device)

        def frac(hit, of):  # B; NaN where a sample has none of ``of``
            k = of.sum(1)
            return torch.where(k > 0, (hit & of).sum(1) / k.clamp(min=1), torch.full(k.shape, float("nan"),
                                                                                    device=k.device))

        acc, rule = frac(ok, labelled), frac(rule_ok, labelled)  # B (NaN: no labelled point)
        wrong = labelled & ~rule_ok  # where the rule is wrong
        on_wrong, n_wrong = frac(ok, wrong), wrong.sum(1).float()
        c = batch["x_t1"].mean(dim=1, keepdim=True)  # float64 around the centroid, as in position_losses
        cd = per_sample(chamfer, (pred_x - c).double(), (batch["x_t1"] - c).double(), valid)  # B, scene units
        seen = batch.get("seen", torch.ones(bs, dtype=torch.bool, device=acc.device)).bool().to(acc.device)
        m = self.val_means
        m.update("val/loss", losses["loss"], weight=bs)
        m.update("val/cluster_acc", acc)
        m.update("val/chamfer", cd)
        m.update("val/mask_rule_acc", rule)
        m.update("val/cluster_acc_rule_wrong", on_wrong, weight=n_wrong)  # pooled over the rule's wrong points
        for name, sel in (("seen", seen), ("unseen", ~seen)):  # every step, empty or not (DDP sync)
            m.update(f"val/cluster_acc_{name}", acc[sel])
            m.update(f"val/mask_rule_acc_{name}", rule[sel])
            m.update(f"val/cluster_acc_rule_wrong_{name}", on_wrong[sel], weight=n_wrong[sel])

    def on_validation_epoch_end(self) -> None:
        values = self.val_means.compute()  # the same on every rank
        for split in SPLITS:
            acc, rule = values.get(f"val/cluster_acc{split}"), values.get(f"val/mask_rule_acc{split}")
            red = None if acc is None or rule is None else error_reduction(acc, rule)
            if red is not None:
                values[f"val/cluster_err_reduction{split}"] = torch.tensor(red)
        for name, value in values.items():  # already global: sync_dist only keeps Lightning's DDP check quiet
            self.log(name, value, prog_bar=name in ("val/cluster_acc", "val/cluster_err_reduction"), sync_dist=True)

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

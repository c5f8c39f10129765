"""Training of the PDDP policy: PDDPModule (a LightningModule) over PolicyModel (encoder + score network).

Its data is ``topocut.policies.dataset`` (PolicyDataset: FPS-sampled step dicts, the mask target the pose-consistent
label of ``topocut.policies.actions``); its deployment is ``topocut.policies.deploy`` (PDDPPolicy). Both stay
importable from here.
"""
from __future__ import annotations

import dataclasses

import lightning as L
import torch
import torch.nn as nn
from torch.optim.swa_utils import AveragedModel

from topocut.policies.config import PDDPConfig, PolicyTrainConfig
from topocut.policies.dataset import PolicyDataset, sample_batch, subsample, to_tensors  # noqa: F401 - importable from here too
from topocut.policies.diffusion import build_noise, get_loss, sample
from topocut.policies.encoders import build_encoder
from topocut.policies.pddp import PDDPNet
from topocut.utils.lazy import lazy_exports
from topocut.utils.training import EpochMeans

# the deployed policy (topocut.policies.deploy imports this module): importable from here on first use
__getattr__ = lazy_exports(__name__, dict.fromkeys(("PDDPPolicy", "_encoder_overrides", "_mask_action"),
                                                   "topocut.policies.deploy"))


def _as(cls, value):
    if value is None:
        return cls()
    if isinstance(value, dict):
        return cls(**value)
    return value


def ema_decay_at(decay: float, n: int) -> float:
    """EMA decay after n updates: min(decay, (1 + n) / (10 + n)).

    A fixed 0.999 keeps the average at the initial weights for the first thousand steps, so a short
    fit (small datasets, smoke runs) would evaluate an untrained network; the warm-up follows the
    usual diffusion-policy EMA schedule."""
    return min(decay, (1.0 + n) / (10.0 + n))


def ema_with_warmup(decay: float):
    def update(ema_params, params, num_averaged):
        d = ema_decay_at(decay, int(num_averaged))
        torch._foreach_lerp_(ema_params, params, 1.0 - d)

    return update


class PolicyModel(nn.Module):
    """Encoder + score network: context(batch) once per observation, forward(x_t, sigma, ctx) per step.

    The observation and (``goal_input="phi"``) the goal go through the same encoder: z_t = Φ(X_t, F_t),
    z_g = Φ(X_g, F_g) with F_g the goal's piece labels (topocut.policies.inputs.goal_feature)."""

    def __init__(self, cfg: PDDPConfig, encoder: nn.Module):
        super().__init__()
        self.cfg, self.encoder, self.net = cfg, encoder, PDDPNet(cfg)

    def context(self, points, labels, goal, history, goal_labels=None, goal_valid=None) -> dict:
        """points B,N,3 ; labels B,N ; goal B,G,3 ; history B,21 or B,3,7 ; goal_labels B,G (None: all 0) ;
        goal_valid B,G bool (None: every row)."""
        if self.cfg.center_points:
            c = points.mean(1, keepdim=True)  # B,1,3
            points, goal = points - c, goal - c
        z = self.encoder(points, labels)  # B,N,obs_dim
        if self.cfg.goal_input == "phi":
            if goal_labels is None:
                goal_labels = torch.zeros(goal.shape[:2], dtype=torch.long, device=goal.device)
            g = self.encoder(goal, goal_labels.long())  # B,G,obs_dim: z_g = Φ(X_g, F_g)
        else:
            g = goal
        return self.net.context(z, g, history.reshape(history.shape[0], -1), goal_valid)

    def forward(self, x_t, sigma, ctx):
        return self.net(x_t, sigma, ctx)


def _legacy_config(cfg):
    """A checkpoint's saved PDDPConfig dict from before ``goal_input`` builds the network it was trained as:
    the task-blind goal encoder over the goal's positions (goal_input="xyz")."""
    if isinstance(cfg, dict) and "goal_input" not in cfg:
        return {**cfg, "goal_input": "xyz"}
    return cfg


VAL_KEYS = ("val/loss", "val/mask_acc", "val/mask_acc_majority", "val/mask_acc_prev_plane")


class PDDPModule(L.LightningModule):
    def __init__(self, cfg: PDDPConfig | dict | None = None, encoder: str = "none", encoder_ckpt: str | None = None,
                 train: PolicyTrainConfig | dict | None = None, encoder_arch: dict | None = None):
        super().__init__()
        cfg, train = _as(PDDPConfig, _legacy_config(cfg)), _as(PolicyTrainConfig, train)
        # encoder_arch (recorded at training): a saved policy rebuilds Φ from it and loads Φ's weights from its own
        # state dict, so the perception checkpoint need not travel with it
        enc = build_encoder(encoder, encoder_ckpt, out_dim=cfg.obs_dim, arch=encoder_arch)
        cfg = dataclasses.replace(cfg, obs_dim=int(enc.out_dim)).validate()
        train = dataclasses.replace(train, encoder=encoder, encoder_ckpt=encoder_ckpt).validate()
        self.cfg, self.train_cfg = cfg, train
        self.save_hyperparameters({"cfg": dataclasses.asdict(cfg), "encoder": encoder, "encoder_ckpt": encoder_ckpt,
                                   "train": dataclasses.asdict(train), "encoder_arch": getattr(enc, "arch", None)})
        self.model = PolicyModel(cfg, enc)
        self.ema = AveragedModel(self.model, multi_avg_fn=ema_with_warmup(train.ema_decay), use_buffers=True)
        self.ema.requires_grad_(False)
        self.graph = self.model.net.graph
        self.noise = build_noise(cfg.noise, cfg.noise_eps, cfg.sigma_min, cfg.sigma_max)
        self.loss_fn = get_loss(train.loss)
        self.val_means = EpochMeans(VAL_KEYS)  # epoch means over all DDP ranks
        # the largest |tilt| of the cuts it trained on (set_demo_tilt; saved in the checkpoint): whether its deployed
        # planes are fitted vertical (SamplerConfig.tilt="auto").  None: not known (a checkpoint from before it)
        self.demo_max_tilt: float | None = None

    @classmethod
    def from_config(cls, cfg: PDDPConfig | None, train: PolicyTrainConfig) -> PDDPModule:
        return cls(cfg, train.encoder, train.encoder_ckpt, train)

    def set_demo_tilt(self, steps) -> None:
        """Record the largest |tilt| of the training steps' actions (dataset step dicts)."""
        from topocut.policies.inputs import step_action

        self.demo_max_tilt = max((abs(float(step_action(s).tilt)) for s in steps), default=None)

    def vertical_planes(self, tilt: str = "auto") -> bool:
        """Whether the planes of its masks are fitted vertical under SamplerConfig.tilt ``tilt``."""
        from topocut.policies.config import VERTICAL_TILT

        if tilt == "auto":
            return self.demo_max_tilt is not None and self.demo_max_tilt <= VERTICAL_TILT
        return tilt == "zero"

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        checkpoint["demo_max_tilt"] = self.demo_max_tilt

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        self.demo_max_tilt = checkpoint.get("demo_max_tilt")

    # -- training -------------------------------------------------------------
    def _context(self, model, batch):
        return model.context(batch["points"], batch["labels"], batch["goal"], batch["history"],
                             batch.get("goal_labels"), batch.get("goal_valid"))

    def loss(self, batch, model=None, t=None, generator=None) -> torch.Tensor:
        """Mean per-sample loss of ``model`` (default: the trained one) on a batch."""
        model = model or self.model
        ctx = self._context(model, batch)
        return self.loss_fn(model, batch["mask"], ctx, self.graph, self.noise, t=t, generator=generator,
                            valid=batch.get("valid")).mean()

    def on_after_batch_transfer(self, batch, dataloader_idx):
        """PolicyDataset(sample="batch") batches: the observation's FPS for the whole batch on its device."""
        return sample_batch(batch, self.train_cfg.num_points)

    def training_step(self, batch, batch_idx):
        loss = self.loss(batch)
        self.log("train/loss", loss, prog_bar=True, batch_size=len(batch["mask"]), on_step=True, on_epoch=True,
                 sync_dist=True)
        return loss

    def on_train_batch_end(self, outputs, batch, batch_idx):
        self.ema.update_parameters(self.model)

    @torch.no_grad()
    def sample_masks(self, batch, steps: int = 32, predictor: str = "analytic", use_ema: bool = True,
                     generator: torch.Generator | list[torch.Generator] | None = None, denoise: bool = True,
                     eps: float = 1e-5) -> torch.Tensor:
        """Masks (B,N) long sampled by the reverse chain (``generator``: one, or one per sample)."""
        model = self.ema.module if use_ema else self.model
        was_training = model.training
        model.eval()
        ctx = self._context(model, batch)
        B, N = batch["points"].shape[:2]
        x = sample(model, self.graph, self.noise, (B, N), cond=ctx, steps=steps, predictor=predictor,
                   denoise=denoise, eps=eps, device=batch["points"].device, generator=generator)
        model.train(was_training)
        return x

    def validation_step(self, batch, batch_idx):
        """val/loss, val/mask_acc (EMA weights, sampled masks) and its floors on the same points
        (docs/policy.md#metrics-and-their-floors): val/mask_acc_majority, the best constant mask of each sample
        (its majority class), and val/mask_acc_prev_plane, the mask of the previous cut's plane (the majority mask
        before a first cut)."""
        B = len(batch["mask"])
        loss = self.loss(batch, model=self.ema.module)
        self.val_means.update("val/loss", loss, weight=B)
        target = batch["mask"].to(loss.device)  # B,N
        valid = batch.get("valid", torch.ones_like(target, dtype=torch.bool)).to(loss.device)  # B,N
        n = valid.sum(1).clamp(min=1)

        def acc(pred):  # B
            return ((pred.to(target.device) == target) & valid).sum(1) / n

        sampled = self.sample_masks(batch, steps=self.train_cfg.val_sample_steps) if self.sample_due() else None
        self.val_means.update("val/mask_acc", acc(sampled) if sampled is not None else torch.empty(0))
        ones = (target.bool() & valid).sum(1) / n
        self.val_means.update("val/mask_acc_majority", torch.maximum(ones, 1 - ones))
        prev = batch.get("prev_mask")
        self.val_means.update("val/mask_acc_prev_plane", acc(prev) if prev is not None else torch.empty(0))

    def sample_due(self) -> bool:
        """Whether this validation samples masks (val/mask_acc): every ``val_sample_every``-th epoch, the last one,
        and outside a fit (a bare module, the sanity check)."""
        k = self.train_cfg.val_sample_every
        trainer = self._trainer
        if k <= 1 or trainer is None or trainer.sanity_checking:
            return True
        epoch, last = self.current_epoch + 1, trainer.max_epochs
        if last is None or last < 0:  # a fit bounded by steps: its last epoch is not known ahead, sample each
            return True
        return epoch % k == 0 or epoch >= last

    def on_validation_epoch_end(self) -> None:
        self.val_means.log(self, prog_bar=("val/loss", "val/mask_acc", "val/mask_acc_majority"))

    def configure_optimizers(self):
        params = [p for p in self.model.parameters() if p.requires_grad]
        opt = torch.optim.AdamW(params, lr=self.train_cfg.lr, weight_decay=self.train_cfg.weight_decay)
        warm = max(1, self.train_cfg.warmup_steps)
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda step: min(1.0, (step + 1) / warm))
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    def configure_gradient_clipping(self, optimizer, gradient_clip_val=None, gradient_clip_algorithm=None):
        clip = self.train_cfg.grad_clip if gradient_clip_val is None else gradient_clip_val
        if clip and clip > 0:
            torch.nn.utils.clip_grad_norm_([p for g in optimizer.param_groups for p in g["params"]], clip)


def num_parameters(module: nn.Module, trainable: bool = True) -> int:
    return sum(p.numel() for p in module.parameters() if p.requires_grad or not trainable)

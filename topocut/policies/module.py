"""Training (PDDPModule, a LightningModule) and deployment (PDDPPolicy) of the PDDP policy.

Batches come from dataset step dicts (docs/contracts.md: x_t, f_t, mask, history, goal, ...),
FPS-sampled to ``num_points`` observation and ``num_goal_points`` goal points by PolicyDataset.
"""
from __future__ import annotations

import dataclasses

import lightning as L
import numpy as np
import torch
import torch.nn as nn
from torch.optim.swa_utils import AveragedModel

from topocut.metrics.sampling import valid_rows
from topocut.policies.base import check_obs
from topocut.policies.config import PDDPConfig, PolicyTrainConfig, SamplerConfig
from topocut.policies.diffusion import build_noise, get_loss, sample
from topocut.policies.encoders import build_encoder
from topocut.policies.pddp import PDDPNet
from topocut.policies.plane import action_from_mask
from topocut.utils.training import EpochMeans


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


def subsample(n_total: int, points, n: int, seed: int) -> np.ndarray:
    """Indices of ``n`` of the points: farthest point sampling, with repeats when there are fewer (the first
    ``n_total`` are then each point once: ``valid_rows`` marks them)."""
    if n_total <= n:
        rng = np.random.default_rng(seed)
        return np.concatenate([np.arange(n_total), rng.integers(0, n_total, n - n_total)])
    from topocut.metrics import fps  # lazy: the metrics package

    return np.asarray(fps(points, n, seed=seed, start="random"))  # random start: a fresh subset per draw


class PolicyDataset(torch.utils.data.Dataset):
    """Step dicts (an EpisodeDataset or a list) -> fixed-size tensors for PDDP.

    Each access draws a fresh FPS start point (seed from ``seed`` and a counter), a mild augmentation.
    """

    def __init__(self, steps, num_points: int = 256, num_goal_points: int = 256, seed: int = 0,
                 indices=None):
        self.steps, self.num_points, self.num_goal_points = steps, num_points, num_goal_points
        self.indices = np.arange(len(steps)) if indices is None else np.asarray(indices)
        self.seed, self._calls = seed, 0

    def __len__(self):
        return len(self.indices)

    def __getitem__(self, i):
        s = self.steps[int(self.indices[i])]
        self._calls += 1
        seed = (self.seed * 1_000_003 + int(self.indices[i]) * 7919 + self._calls) % (2**31)
        x = np.asarray(s["x_t"], np.float32)
        idx = subsample(len(x), x, self.num_points, seed)
        g = np.asarray(s["goal"], np.float32)
        gidx = subsample(len(g), g, self.num_goal_points, seed + 1)
        return {"points": torch.from_numpy(x[idx]), "labels": torch.from_numpy(np.asarray(s["f_t"])[idx]).long(),
                "mask": torch.from_numpy(np.asarray(s["mask"])[idx]).long(),
                "valid": torch.from_numpy(valid_rows(idx)),  # N, False on padding copies (topocut.metrics)
                "history": torch.from_numpy(np.asarray(s["history"], np.float32).reshape(-1)),
                "goal": torch.from_numpy(g[gidx])}


class PolicyModel(nn.Module):
    """Encoder + score network: context(batch) once per observation, forward(x_t, sigma, ctx) per step."""

    def __init__(self, cfg: PDDPConfig, encoder: nn.Module):
        super().__init__()
        self.cfg, self.encoder, self.net = cfg, encoder, PDDPNet(cfg)

    def context(self, points, labels, goal, history) -> dict:  # B,N,3 ; B,N ; B,G,3 ; B,21 or B,3,7
        if self.cfg.center_points:
            c = points.mean(1, keepdim=True)  # B,1,3
            points, goal = points - c, goal - c
        z = self.encoder(points, labels)  # B,N,obs_dim
        return self.net.context(z, goal, history.reshape(history.shape[0], -1))

    def forward(self, x_t, sigma, ctx):
        return self.net(x_t, sigma, ctx)


class PDDPModule(L.LightningModule):
    def __init__(self, cfg: PDDPConfig | dict | None = None, encoder: str = "none", encoder_ckpt: str | None = None,
                 train: PolicyTrainConfig | dict | None = None):
        super().__init__()
        cfg, train = _as(PDDPConfig, cfg), _as(PolicyTrainConfig, train)
        enc = build_encoder(encoder, encoder_ckpt, out_dim=cfg.obs_dim)
        cfg = dataclasses.replace(cfg, obs_dim=int(enc.out_dim)).validate()
        train = dataclasses.replace(train, encoder=encoder, encoder_ckpt=encoder_ckpt).validate()
        self.cfg, self.train_cfg = cfg, train
        self.save_hyperparameters({"cfg": dataclasses.asdict(cfg), "encoder": encoder, "encoder_ckpt": encoder_ckpt,
                                   "train": dataclasses.asdict(train)})
        self.model = PolicyModel(cfg, enc)
        self.ema = AveragedModel(self.model, multi_avg_fn=ema_with_warmup(train.ema_decay), use_buffers=True)
        self.ema.requires_grad_(False)
        self.graph = self.model.net.graph
        self.noise = build_noise(cfg.noise, cfg.noise_eps, cfg.sigma_min, cfg.sigma_max)
        self.loss_fn = get_loss(train.loss)
        self.val_means = EpochMeans(("val/loss", "val/mask_acc"))  # epoch means over all DDP ranks

    @classmethod
    def from_config(cls, cfg: PDDPConfig | None, train: PolicyTrainConfig) -> PDDPModule:
        return cls(cfg, train.encoder, train.encoder_ckpt, train)

    # -- training -------------------------------------------------------------
    def _context(self, model, batch):
        return model.context(batch["points"], batch["labels"], batch["goal"], batch["history"])

    def loss(self, batch, model=None, t=None, generator=None) -> torch.Tensor:
        """Mean per-sample loss of ``model`` (default: the trained one) on a batch."""
        model = model or self.model
        ctx = self._context(model, batch)
        return self.loss_fn(model, batch["mask"], ctx, self.graph, self.noise, t=t, generator=generator,
                            valid=batch.get("valid")).mean()

    def training_step(self, batch, batch_idx):
        loss = self.loss(batch)
        self.log("train/loss", loss, prog_bar=True, batch_size=len(batch["mask"]), on_step=True, on_epoch=True,
                 sync_dist=True)
        return loss

    def on_train_batch_end(self, outputs, batch, batch_idx):
        self.ema.update_parameters(self.model)

    @torch.no_grad()
    def sample_masks(self, batch, steps: int = 32, predictor: str = "analytic", use_ema: bool = True,
                     generator: torch.Generator | None = None, denoise: bool = True,
                     eps: float = 1e-5) -> torch.Tensor:
        """Masks (B,N) long sampled by the reverse chain."""
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
        B = len(batch["mask"])
        loss = self.loss(batch, model=self.ema.module)
        masks = self.sample_masks(batch, steps=self.train_cfg.val_sample_steps)
        self.val_means.update("val/loss", loss, weight=B)
        valid = batch.get("valid", torch.ones_like(masks, dtype=torch.bool)).to(masks.device)  # B,N
        hits = ((masks == batch["mask"]) & valid).sum(1)
        self.val_means.update("val/mask_acc", hits / valid.sum(1).clamp(min=1))  # B

    def on_validation_epoch_end(self) -> None:
        self.val_means.log(self, prog_bar=("val/loss", "val/mask_acc"))

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


class PDDPPolicy:
    """topocut.policies.base.Policy backed by a trained PDDPModule (or its checkpoint path).

    act() returns None ("no cut") when no sampled mask within ``retries`` tries splits the points.
    """

    def __init__(self, module_or_ckpt, sampler: str | SamplerConfig = "analytic", steps: int = 32,
                 device: str = "cpu", plane: str = "svm", seed: int = 0, board_z: float = 0.05, retries: int = 3,
                 use_ema: bool = True):
        # a SamplerConfig (the `policy.sampler` group) carries every sampling setting; a predictor name
        # with steps/plane/retries is the short form
        self.scfg = (sampler if isinstance(sampler, SamplerConfig)
                     else SamplerConfig(predictor=sampler, steps=steps, plane=plane, retries=retries)).validate()
        if isinstance(module_or_ckpt, PDDPModule):
            module = module_or_ckpt
        else:
            module = PDDPModule.load_from_checkpoint(str(module_or_ckpt), map_location=device, weights_only=True)
        self.module = module.to(device).eval()
        self.device, self.board_z, self.use_ema, self.seed = torch.device(device), board_z, use_ema, int(seed)
        self.generator = torch.Generator(device=self.device).manual_seed(self.seed)
        self.goal = None
        self.last_mask = None

    def reset(self, goal, seed: int | None = None) -> None:
        from topocut.policies.base import mix_seed

        self.goal = np.asarray(goal.points if hasattr(goal, "points") else goal, np.float32)
        if seed is not None:  # an episode's masks do not depend on the episodes sampled before it
            self.generator = torch.Generator(device=self.device).manual_seed(mix_seed(self.seed, seed))

    def act(self, obs: dict):
        obs = check_obs(obs)
        mask, action = self.sample((obs["points"], obs["labels"]), obs["goal"], obs["history"])
        self.last_mask = mask
        return action

    def _batch(self, points, labels, goal, history, seed: int) -> dict:
        n_pts, n_goal = self.module.train_cfg.num_points, self.module.train_cfg.num_goal_points
        idx = subsample(len(points), points, n_pts, seed)
        gidx = subsample(len(goal), goal, n_goal, seed + 1)
        t = {"points": points[idx], "labels": labels[idx], "goal": goal[gidx],
             "history": np.asarray(history, np.float32).reshape(1, -1)}
        b = {k: torch.as_tensor(np.asarray(v))[None].to(self.device) for k, v in t.items() if k != "history"}
        b["history"] = torch.as_tensor(t["history"]).to(self.device)
        b["labels"] = b["labels"].long()
        return b, idx

    def sample(self, observation, goal=None, history=None):
        """observation (points (n,3), labels (n,)) -> (mask (n,) uint8 over all n points, KnifeAction | None).

        The network sees an FPS subset; the mask is spread to the other points from their nearest sampled point.
        """
        points, labels = observation
        points, labels = np.asarray(points, np.float32), np.asarray(labels).astype(np.int64)
        goal = self.goal if goal is None else np.asarray(goal, np.float32)
        if goal is None:
            raise ValueError("PDDPPolicy.sample needs a goal: pass goal= or call reset(goal) first")
        history = np.zeros((3, 7), np.float32) if history is None else history
        action, full = None, np.zeros(len(points), np.uint8)
        for _ in range(self.scfg.retries + 1):
            seed = int(torch.randint(0, 2**31 - 1, (1,), generator=self.generator, device=self.device))
            batch, idx = self._batch(points, labels, goal, history, seed)
            mask = self.module.sample_masks(batch, steps=self.scfg.steps, predictor=self.scfg.predictor,
                                            use_ema=self.use_ema, generator=self.generator,
                                            denoise=self.scfg.denoise, eps=self.scfg.eps)[0].cpu().numpy()
            sub = points[idx]
            action = action_from_mask(sub, mask, self.scfg.plane, board_z=self.board_z)
            if len(points) <= len(idx):  # every point was seen (some twice)
                full = np.zeros(len(points), np.uint8)
                full[idx] = mask
            else:
                from scipy.spatial import cKDTree

                full = mask[cKDTree(sub).query(points)[1]].astype(np.uint8)
            if action is not None:
                break
        return full, action


def num_parameters(module: nn.Module, trainable: bool = True) -> int:
    return sum(p.numel() for p in module.parameters() if p.requires_grad or not trainable)

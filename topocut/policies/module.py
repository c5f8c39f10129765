"""Training (PDDPModule, a LightningModule) and deployment (PDDPPolicy) of the PDDP policy.

Batches come from dataset step dicts (docs/contracts.md: x_t, f_t, mask, history, goal, goal_labels, ...) through
``topocut.policies.inputs`` -- the one builder of every learned policy's inputs -- FPS-sampled to ``num_points``
observation and ``num_goal_points`` goal points by PolicyDataset; the mask target is the pose-consistent label of
``topocut.policies.actions``.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import lightning as L
import numpy as np
import torch
import torch.nn as nn
from torch.optim.swa_utils import AveragedModel

from topocut.policies.base import check_obs
from topocut.policies.config import PDDPConfig, PolicyTrainConfig, SamplerConfig
from topocut.policies.diffusion import build_noise, get_loss, sample
from topocut.policies.encoders import build_encoder
from topocut.policies.inputs import goal_inputs, policy_inputs, sample_indices, step_obs, step_targets
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
    """Indices of ``n`` of the points (``topocut.policies.inputs.sample_indices`` with a random FPS start; the
    first ``n_total`` are each point once when there are fewer: ``valid_rows`` marks them)."""
    return sample_indices(np.asarray(points)[:n_total], n, seed, start="random")


class PolicyDataset(torch.utils.data.Dataset):
    """Step dicts (an EpisodeDataset or a list) -> fixed-size tensors for PDDP (``topocut.policies.inputs``).

    Each access draws a fresh FPS start point for the observation (seed from ``seed`` and a counter), a mild
    augmentation; the goal fields are the deterministic ones every policy receives (cached per step).
    ``mask_label``: the target mask (PolicyTrainConfig.mask_label).  Fields: points, labels, valid, history, goal,
    goal_labels, goal_valid, mask, prev_mask (the plane-from-previous-cut floor), has_prev.
    """

    def __init__(self, steps, num_points: int = 256, num_goal_points: int = 256, seed: int = 0,
                 indices=None, mask_label: str = "goal_side", board_z: float = 0.05):
        self.steps, self.num_points, self.num_goal_points = steps, num_points, num_goal_points
        self.indices = np.arange(len(steps)) if indices is None else np.asarray(indices)
        self.seed, self._calls, self.mask_label, self.board_z = seed, 0, mask_label, board_z
        self._goals: dict[int, dict] = {}

    def __len__(self):
        return len(self.indices)

    def __getitem__(self, i):
        j = int(self.indices[i])
        s = self.steps[j]
        self._calls += 1
        seed = (self.seed * 1_000_003 + j * 7919 + self._calls) % (2**31)
        obs = step_obs(s)
        if j not in self._goals:
            self._goals[j] = goal_inputs(obs["goal"], obs["goal_labels"], self.num_goal_points)
        inp = policy_inputs(obs, self.num_points, self.num_goal_points, seed, goal=self._goals[j])
        inp.update(step_targets(s, inp["index"], self.board_z, self.mask_label))
        return to_tensors(inp)


def to_tensors(inp: dict) -> dict:
    """``policy_inputs`` (+ targets) as tensors: history flat (h*7,), ids long, masks bool."""
    out = {}
    for k in ("points", "labels", "valid", "goal", "goal_labels", "goal_valid", "mask", "prev_mask", "has_prev"):
        if k in inp:
            out[k] = torch.as_tensor(np.asarray(inp[k]))
    for k in ("labels", "goal_labels", "mask", "prev_mask"):
        if k in out:
            out[k] = out[k].long()
    out["history"] = torch.as_tensor(np.asarray(inp["history"], np.float32).reshape(-1))
    return out


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


def _encoder_overrides(ckpt_path) -> dict:
    """Where a PDDP checkpoint from before ``encoder_arch`` finds its perception checkpoint.

    Such a checkpoint names Φ's file by the absolute path it was trained with (e.g. /tmp/o/checkpoint/perception/
    v001/model.ckpt on the GPU machine). Artifact stores move between machines, so when that path is missing the
    same version is looked up in the store this checkpoint lives in (<root>/checkpoint/pddp/vNNN/model.ckpt →
    <root>/checkpoint/perception/vNNN/model.ckpt); neither there → one error naming both."""
    hp = torch.load(str(ckpt_path), map_location="cpu", weights_only=True).get("hyper_parameters", {})
    recorded = hp.get("encoder_ckpt")
    if hp.get("encoder") != "pretrained" or hp.get("encoder_arch") or not recorded or Path(recorded).is_file():
        return {}
    rel = Path(*Path(recorded).parts[-4:])  # checkpoint/<name>/vNNN/model.ckpt: the store's layout
    here = Path(ckpt_path).parents[3] / rel  # the root of the store holding <root>/checkpoint/pddp/vNNN/model.ckpt
    if here.is_file():
        return {"encoder_ckpt": str(here)}
    raise FileNotFoundError(f"{ckpt_path} was trained on the perception checkpoint {recorded}, which does not exist "
                            f"here, nor does {here} (the same version in this checkpoint's artifact store): copy that "
                            f"checkpoint/perception version beside it")


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

    @classmethod
    def from_config(cls, cfg: PDDPConfig | None, train: PolicyTrainConfig) -> PDDPModule:
        return cls(cfg, train.encoder, train.encoder_ckpt, train)

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
            load = dict(map_location=device, weights_only=True)
            try:
                module = PDDPModule.load_from_checkpoint(str(module_or_ckpt), **load)
            except FileNotFoundError:  # a checkpoint from before encoder_arch whose Φ file is not where it was
                module = PDDPModule.load_from_checkpoint(str(module_or_ckpt), **load,
                                                         **_encoder_overrides(module_or_ckpt))
        self.module = module.to(device).eval()
        self.history_len = int(module.cfg.history_len)  # policy.net.history_len: the engine's observations hold it
        self.device, self.board_z, self.use_ema, self.seed = torch.device(device), board_z, use_ema, int(seed)
        self.generator = torch.Generator(device=self.device).manual_seed(self.seed)
        self.goal, self.goal_labels = None, None
        self.last_mask = None

    def reset(self, goal, seed: int | None = None) -> None:
        from topocut.policies.base import mix_seed

        self.goal = np.asarray(goal.points if hasattr(goal, "points") else goal, np.float32)
        labels = getattr(goal, "labels", None)
        self.goal_labels = None if labels is None else np.asarray(labels)
        if seed is not None:  # an episode's masks do not depend on the episodes sampled before it
            self.generator = torch.Generator(device=self.device).manual_seed(mix_seed(self.seed, seed))

    def act(self, obs: dict):
        obs = check_obs(obs)
        mask, action = self.sample((obs["points"], obs["labels"]), obs["goal"], obs["history"], obs["goal_labels"])
        self.last_mask = mask
        return action

    @staticmethod
    def act_batch(policies: list[PDDPPolicy], observations: list[dict]) -> list:
        """``[p.act(o) for p, o in zip(policies, observations)]`` with one network batch per sampling step.

        ``policies``: one copy per episode (``topocut.episode``'s slots) sharing the module and the sampling
        settings, each with its own goal and generator.  Every episode draws its randomness from its own generator
        in the order and shapes act() does (``topocut.policies.diffusion.rng``), so actions, ``last_mask`` and the
        generators' states afterwards are those of the one-at-a-time calls (up to float rounding of the batched
        network, which can in rare cases tip a sampled label).  Policies that do not share a module and settings
        fall back to act() one by one.
        """
        if len(policies) != len(observations):
            raise ValueError(f"act_batch: {len(policies)} policies for {len(observations)} observations")
        if not policies:
            return []
        lead = policies[0]
        if len({id(p) for p in policies}) < len(policies) or \
                not all(p.module is lead.module and p._settings() == lead._settings() for p in policies):
            # one object twice draws its two actions one after the other; other modules need their own batch
            return [p.act(o) for p, o in zip(policies, observations)]
        obs = [check_obs(o) for o in observations]
        prepared = [p._prepare((o["points"], o["labels"]), o["goal"], o["history"], o["goal_labels"])
                    for p, o in zip(policies, obs)]
        results = PDDPPolicy._sample_many(policies, prepared)
        for p, (mask, _) in zip(policies, results):
            p.last_mask = mask
        return [action for _, action in results]

    def _settings(self) -> tuple:
        """What must agree for policies to share one sampling batch."""
        return self.scfg, self.device, self.board_z, self.use_ema

    def inputs(self, obs: dict, seed: int = 0) -> dict:
        """The world-frame input fields (topocut.policies.inputs.policy_inputs) the network gets for ``obs``."""
        tc = self.module.train_cfg
        return policy_inputs(obs, tc.num_points, tc.num_goal_points, seed, start="random")

    def _batch(self, obs: dict, seed: int):
        inp = self.inputs(obs, seed)
        b = {k: v[None].to(self.device) for k, v in to_tensors(inp).items()}
        b["history"] = b["history"].reshape(1, -1)
        return b, inp["index"]

    def _prepare(self, observation, goal=None, history=None, goal_labels=None) -> dict:
        """sample()'s arguments as an observation dict (goal defaults from reset; history None: no cut yet)."""
        points, labels = observation
        points, labels = np.asarray(points, np.float32), np.asarray(labels).astype(np.int64)
        if goal is None:
            goal, goal_labels = self.goal, (self.goal_labels if goal_labels is None else goal_labels)
        if goal is None:
            raise ValueError("PDDPPolicy.sample needs a goal: pass goal= or call reset(goal) first")
        goal = np.asarray(goal, np.float32)
        history = np.zeros((self.history_len, 7), np.float32) if history is None else history
        return {"points": points, "labels": labels, "goal": goal, "goal_labels": goal_labels, "history": history}

    def sample(self, observation, goal=None, history=None, goal_labels=None):
        """observation (points (n,3), labels (n,)) -> (mask (n,) uint8 over all n points, KnifeAction | None).

        ``goal`` / ``goal_labels`` default to the goal of ``reset`` (labels: all 0 when it had none).  The network
        sees an FPS subset; the mask is spread to the other points from their nearest sampled point.
        """
        return PDDPPolicy._sample_many([self], [self._prepare(observation, goal, history, goal_labels)])[0]

    @staticmethod
    def _sample_many(policies: list[PDDPPolicy], observations: list[dict]) -> list[tuple]:
        """(full mask, action | None) of each policy for its prepared observation (``_prepare``).

        A try draws, from each episode's generator, the FPS seed of its subset and then the sampler's noise; the
        episodes whose mask does not split the points (action None) try again, up to ``retries`` times, batched
        among themselves -- so each generator sees the same draws as act() on that episode alone.
        """
        lead = policies[0]
        cfg, results, pending = lead.scfg, [None] * len(policies), list(range(len(policies)))
        for _ in range(cfg.retries + 1):
            seeds = [int(torch.randint(0, 2**31 - 1, (1,), generator=policies[b].generator, device=lead.device))
                     for b in pending]
            built = [policies[b]._batch(observations[b], seed) for b, seed in zip(pending, seeds)]
            batch = {k: torch.cat([one[k] for one, _ in built]) for k in built[0][0]}  # points B,N,3 ; history B,21 ...
            masks = lead.module.sample_masks(batch, steps=cfg.steps, predictor=cfg.predictor, use_ema=lead.use_ema,
                                             generator=[policies[b].generator for b in pending],
                                             denoise=cfg.denoise, eps=cfg.eps).cpu().numpy()  # B,N
            for row, (b, (_, idx)) in enumerate(zip(pending, built)):
                results[b] = _mask_action(observations[b]["points"], idx, masks[row], cfg.plane, lead.board_z)
            pending = [b for b in pending if results[b][1] is None]
            if not pending:
                break
        return results


def _mask_action(points, idx, mask, plane: str, board_z: float) -> tuple:
    """(mask over all points, action | None) from the mask sampled on the rows ``idx`` of ``points``: the action
    from the plane fitted to the sampled points; the other points take the label of their nearest sampled one."""
    sub = points[idx]
    action = action_from_mask(sub, mask, plane, board_z=board_z)
    if len(points) <= len(idx):  # every point was seen (some twice)
        full = np.zeros(len(points), np.uint8)
        full[idx] = mask
    else:
        from scipy.spatial import cKDTree

        full = mask[cKDTree(sub).query(points)[1]].astype(np.uint8)
    return full, action


def num_parameters(module: nn.Module, trainable: bool = True) -> int:
    return sum(p.numel() for p in module.parameters() if p.requires_grad or not trainable)

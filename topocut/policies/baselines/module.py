"""Shared machinery of the pose-diffusion baselines (DP3, 3D Diffuser Actor).

* Action representation: a knife pose [x, y, yaw, tilt] becomes the continuous 6-vector
  [(x-cx)/s, (y-cy)/s, cos 2yaw, sin 2yaw, tilt cos yaw, tilt sin yaw] -- unique per cut plane, since
  (yaw, tilt) and (yaw + pi, -tilt) describe the same plane and give the same vector; (cx, cy) is the
  observation centroid and s = ``pos_scale`` (a typical object size), so poses are object-relative.
* Gaussian diffusion: DDPM training (epsilon prediction, cosine schedule) and DDIM sampling
  (eta = 0 deterministic; eta = 1 with all T steps is DDPM ancestral sampling).
* ``PoseStepDataset``: dataset step dicts (docs/contracts.md) -> FPS'd, centred tensors, built by
  ``topocut.policies.inputs`` (the one builder of every learned policy's inputs: the same goal fields -- the goal
  cloud and its piece labels -- as PDDP), then put in the object-centred frame (``object_frame``).
* ``PoseDiffusionModule`` (LightningModule) and ``PosePolicy`` (the Policy protocol).
"""
from __future__ import annotations

import math

import lightning as L
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from topocut.policies.diffusion import rng
from topocut.policies.inputs import goal_inputs, object_frame, policy_inputs, sample_indices, step_obs
from topocut.policies.registry import pose_kinds
from topocut.sim.action import KnifeAction
from topocut.utils.training import EpochMeans

KINDS = pose_kinds()  # ("dp3", "3dda"): the registry's pose-diffusion baselines
REPR_DIM = 6


# -- action representation ------------------------------------------------------------------------------
def encode_action(vec, center, scale: float) -> np.ndarray:  # (...,4), (...,3) -> (...,6)
    v, c = np.asarray(vec, np.float64), np.asarray(center, np.float64)
    yaw, tilt = v[..., 2], v[..., 3]
    return np.stack([(v[..., 0] - c[..., 0]) / scale, (v[..., 1] - c[..., 1]) / scale, np.cos(2 * yaw),
                     np.sin(2 * yaw), tilt * np.cos(yaw), tilt * np.sin(yaw)], axis=-1).astype(np.float32)


def decode_action(r, center, scale: float) -> KnifeAction:  # (6,), (3,) -> KnifeAction
    r = np.asarray(r, np.float64)
    yaw = 0.5 * math.atan2(r[3], r[2])  # (-pi/2, pi/2]
    tilt = r[4] * math.cos(yaw) + r[5] * math.sin(yaw)
    return KnifeAction(float(center[0] + scale * r[0]), float(center[1] + scale * r[1]), yaw, float(tilt)).canonical()


# -- Gaussian diffusion ---------------------------------------------------------------------------------
def cosine_alphas_cumprod(T: int, s: float = 0.008, max_beta: float = 0.999) -> np.ndarray:
    """Nichol & Dhariwal's schedule: betas from abar(t) = cos^2(((t/T)+s)/(1+s) pi/2), clipped at max_beta."""
    f = lambda t: math.cos((t / T + s) / (1 + s) * math.pi / 2) ** 2  # noqa: E731
    betas = np.array([min(1 - f(i + 1) / f(i), max_beta) for i in range(T)])
    return np.cumprod(1.0 - betas)


class GaussianDiffusion(nn.Module):
    def __init__(self, num_train_steps: int = 100):
        super().__init__()
        self.T = num_train_steps
        self.register_buffer("abar", torch.tensor(cosine_alphas_cumprod(num_train_steps), dtype=torch.float32))

    @property
    def betas(self) -> torch.Tensor:  # T,
        prev = torch.cat([self.abar.new_ones(1), self.abar[:-1]])
        return 1 - self.abar / prev

    def q_sample(self, x0, t, noise):  # x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) eps
        a = self.abar[t].view(-1, *[1] * (x0.dim() - 1))
        return a.sqrt() * x0 + (1 - a).sqrt() * noise

    def loss(self, eps_fn, x0, generator=None):
        t = torch.randint(0, self.T, (x0.shape[0],), device=x0.device, generator=generator)
        noise = torch.randn(x0.shape, device=x0.device, generator=generator)
        return F.mse_loss(eps_fn(self.q_sample(x0, t, noise), t), noise)

    @torch.no_grad()
    def sample(self, eps_fn, shape, steps: int | None = None, eta: float = 0.0, generator=None,
               clip: float | None = 1.0, device=None):
        """DDIM (Song et al. 2021) over ``steps`` evenly spaced timesteps T-ratio, ..., 0 ("leading").

        ``generator``: one, or one per sample (``topocut.policies.diffusion.rng``: sample b then draws the noise
        a batch-1 call with generator b draws, so batched episodes equal their one-at-a-time runs)."""
        steps = steps or self.T
        if not 1 <= steps <= self.T:
            raise ValueError(f"sampling steps={steps} must lie in [1, num_train_steps={self.T}]")
        ratio = self.T // steps
        x = rng.randn(shape, generator, device=device or self.abar.device)  # B,H,A
        for t in reversed(range(0, steps * ratio, ratio)):
            a = self.abar[t]
            a_prev = self.abar[t - ratio] if t - ratio >= 0 else self.abar.new_tensor(1.0)
            eps = eps_fn(x, torch.full((shape[0],), t, device=x.device, dtype=torch.long))
            x0 = (x - (1 - a).sqrt() * eps) / a.sqrt()
            if clip is not None:
                x0 = x0.clamp(-clip, clip)
                eps = (x - a.sqrt() * x0) / (1 - a).sqrt()  # keep eps consistent with the clipped x0
            sigma = eta * ((1 - a_prev) / (1 - a) * (1 - a / a_prev)).clamp(min=0).sqrt()
            x = a_prev.sqrt() * x0 + (1 - a_prev - sigma ** 2).clamp(min=0).sqrt() * eps
            if eta > 0 and t - ratio >= 0:
                x = x + sigma * rng.randn(shape, generator, device=x.device)
        return x


# -- data ---------------------------------------------------------------------------------------------
def _fps_idx(points, n: int, seed: int) -> np.ndarray:
    """The baselines' observation rows: FPS from the point farthest from the centroid (deterministic)."""
    return sample_indices(points, n, seed, start="farthest")


def prepare_inputs(points, labels, goal, goal_labels, history, num_points: int = 256, num_goal_points: int = 256,
                   pos_scale: float = 0.15, board_z: float = 0.05, num_labels: int = 32, seed: int = 0,
                   idx=None, goal_idx=None) -> dict:
    """Observation -> network inputs in the object-centred frame (float32 / int64 numpy): the shared input fields
    (``topocut.policies.inputs.policy_inputs``) through ``object_frame``.  ``goal_idx`` (rows of the goal cloud)
    overrides the shared deterministic goal sampling; left None, the goal fields are those every policy gets."""
    obs = {"points": points, "labels": labels, "goal": goal, "goal_labels": goal_labels, "history": history}
    idx = _fps_idx(np.asarray(points), num_points, seed) if idx is None else idx
    goal_fields = None
    if goal_idx is not None:
        from topocut.metrics.sampling import valid_rows

        g, gl = np.asarray(goal, np.float32), np.asarray(goal_labels).astype(np.int64)
        goal_fields = {"goal": g[goal_idx], "goal_labels": gl[goal_idx], "goal_valid": valid_rows(goal_idx)}
    inp = policy_inputs(obs, num_points, num_goal_points, seed, index=idx, goal=goal_fields)
    return object_frame(inp, pos_scale, board_z, num_labels)


class PoseStepDataset(torch.utils.data.Dataset):
    """Step dicts (x_t, f_t, history, goal, goal_labels, action) -> prepared inputs + action representation.

    FPS indices and goal fields are cached per step, so only the first epoch pays for them.
    """

    def __init__(self, steps, num_points: int = 256, num_goal_points: int = 256, pos_scale: float = 0.15,
                 board_z: float = 0.05, num_labels: int = 32, seed: int = 0):
        self.steps, self.kw = steps, dict(num_points=num_points, num_goal_points=num_goal_points, pos_scale=pos_scale,
                                          board_z=board_z, num_labels=num_labels, seed=seed)
        self._idx: dict[int, tuple] = {}

    def __len__(self) -> int:
        return len(self.steps)

    def __getitem__(self, i: int) -> dict:
        s, kw = self.steps[i], self.kw
        obs = step_obs(s)
        if i not in self._idx:
            self._idx[i] = (_fps_idx(np.asarray(s["x_t"]), kw["num_points"], kw["seed"]),
                            goal_inputs(obs["goal"], obs["goal_labels"], kw["num_goal_points"]))
        idx, goal = self._idx[i]
        inp = policy_inputs(obs, kw["num_points"], kw["num_goal_points"], kw["seed"], index=idx, goal=goal)
        out = object_frame(inp, kw["pos_scale"], kw["board_z"], kw["num_labels"])
        out["action"] = encode_action(s["action"], out["center"], kw["pos_scale"])
        return out


def action_stats(steps, pos_scale: float = 0.15) -> np.ndarray:
    """(M,6) action representations of the steps (for PoseDiffusionModule.set_action_stats)."""
    return np.stack([encode_action(s["action"], np.asarray(s["x_t"], np.float64).mean(0), pos_scale) for s in steps])


# -- LightningModule -----------------------------------------------------------------------------------------
class PoseDiffusionModule(L.LightningModule):
    """DDPM over one knife pose per step with a DP3 or 3D-Diffuser-Actor denoiser."""

    def __init__(self, kind: str = "dp3", num_points: int = 256, num_goal_points: int = 256, num_labels: int = 32,
                 use_labels: bool = True, enc_dim: int = 64, down_dims: tuple = (64, 128, 256), horizon: int = 4,
                 dim: int = 96, heads: int = 4, layers: int = 2, context_layers: int = 1, lr: float = 1e-4,
                 weight_decay: float = 1e-6, num_train_steps: int = 100, num_inference_steps: int | None = None,
                 eta: float | None = None, pos_scale: float = 0.15, board_z: float = 0.05):
        super().__init__()
        if kind not in KINDS:
            raise ValueError(f"kind={kind!r} is not valid; choose one of {', '.join(KINDS)}")
        self.save_hyperparameters()
        if kind == "dp3":
            from topocut.policies.baselines.dp3 import DP3Net

            self.net = DP3Net(REPR_DIM, num_labels, use_labels, enc_dim, tuple(down_dims), horizon)
        else:
            from topocut.policies.baselines.diffuser_actor import DiffuserActorNet

            self.net = DiffuserActorNet(REPR_DIM, num_labels, use_labels, dim, heads, layers, context_layers)
        self.diffusion = GaussianDiffusion(num_train_steps)
        # DP3 samples with 10 deterministic DDIM steps; 3DDA with DDPM ancestral sampling over all T steps
        self.num_inference_steps = num_inference_steps or (10 if kind == "dp3" else num_train_steps)
        self.eta = (0.0 if kind == "dp3" else 1.0) if eta is None else eta
        self.register_buffer("act_mid", torch.zeros(REPR_DIM))  # normalised = (r - mid) / half, in [-1, 1]
        self.register_buffer("act_half", torch.ones(REPR_DIM))
        self.val_means = EpochMeans(("val/loss", "val/pose_err", "val/yaw_err"))  # epoch means over all DDP ranks

    def set_action_stats(self, reprs, min_half: float = 1e-2) -> None:
        r = torch.as_tensor(np.asarray(reprs), dtype=torch.float32)  # M,6
        lo, hi = r.min(0).values, r.max(0).values
        self.act_mid.copy_((lo + hi) / 2)
        self.act_half.copy_(((hi - lo) / 2).clamp(min=min_half))

    def normalize(self, r):
        return (r - self.act_mid) / self.act_half

    def denormalize(self, x):
        return x * self.act_half + self.act_mid

    def _eps_fn(self, cond):
        return lambda x, t: self.net.denoise(x, t, cond, self.denormalize(x))

    def compute_loss(self, batch, generator=None):
        x0 = self.normalize(batch["action"])[:, None].expand(-1, self.net.horizon, -1)  # B,H,6
        return self.diffusion.loss(self._eps_fn(self.net.encode(batch)), x0, generator)

    @torch.no_grad()
    def predict(self, batch, generator=None, steps: int | None = None) -> torch.Tensor:  # -> B,6 representation
        """Sampled action representations; ``generator``: one, or a list with one per sample."""
        B = batch["points"].shape[0]
        x = self.diffusion.sample(self._eps_fn(self.net.encode(batch)), (B, self.net.horizon, REPR_DIM),
                                  steps or self.num_inference_steps, self.eta, generator, device=self.device)
        return self.denormalize(x.mean(dim=1))  # the padded sequence is read as its mean pose

    def training_step(self, batch, batch_idx):
        loss = self.compute_loss(batch)
        self.log("train/loss", loss, prog_bar=True, batch_size=batch["points"].shape[0], on_step=True, on_epoch=True,
                 sync_dist=True)
        return loss

    def validation_step(self, batch, batch_idx):
        B = batch["points"].shape[0]
        self.val_means.update("val/loss", self.compute_loss(batch), weight=B)
        err = pose_errors(self.predict(batch), batch["action"], self.hparams.pos_scale, mean=False)  # B each
        self.val_means.update("val/pose_err", err["xy"])
        self.val_means.update("val/yaw_err", err["yaw"])

    def on_validation_epoch_end(self) -> None:
        self.val_means.log(self, prog_bar=("val/pose_err",))

    def configure_optimizers(self):
        return torch.optim.AdamW(self.parameters(), lr=self.hparams.lr, weight_decay=self.hparams.weight_decay)


def pose_errors(pred, target, pos_scale: float, mean: bool = True) -> dict:
    """Cut-point distance (scene units) and angle between blade lines (rad) of (B,6) representations:
    batch means, or (B,) per sample with ``mean=False``."""
    xy = (pred[:, :2] - target[:, :2]).norm(dim=-1) * pos_scale
    d = 0.5 * (torch.atan2(pred[:, 3], pred[:, 2]) - torch.atan2(target[:, 3], target[:, 2]))
    yaw = torch.atan2(torch.sin(2 * d), torch.cos(2 * d)).abs() / 2  # lines: difference modulo pi
    return {"xy": xy.mean(), "yaw": yaw.mean()} if mean else {"xy": xy, "yaw": yaw}


# -- Policy -----------------------------------------------------------------------------------------------
class PosePolicy:
    """Policy protocol over a trained PoseDiffusionModule: ``reset(goal)``, ``act(obs) -> KnifeAction``.

    Sampling noise comes from a generator re-seeded at every reset (from the policy's seed and the
    episode's), so an episode is reproducible and episodes do not share their noise.
    """

    def __init__(self, module: PoseDiffusionModule, seed: int = 0, device: str = "cpu", steps: int | None = None):
        self.module, self.seed, self.steps = module.to(device).eval(), seed, steps
        self.device = torch.device(device)
        self.goal, self.generator = None, None

    def reset(self, goal, seed: int | None = None) -> None:
        from topocut.policies.base import mix_seed

        self.goal = goal
        self.generator = torch.Generator(self.device).manual_seed(mix_seed(self.seed, seed))

    def inputs(self, obs: dict, seed: int | None = None) -> dict:
        """The world-frame input fields (topocut.policies.inputs.policy_inputs) the network gets for ``obs``; the
        goal from the obs (or the reset's goal)."""
        hp = self.module.hparams
        goal = obs.get("goal", getattr(self.goal, "points", None))
        goal_labels = obs.get("goal_labels", getattr(self.goal, "labels", None))
        if goal is None or goal_labels is None:
            raise KeyError(f"PosePolicy needs obs['goal'] and obs['goal_labels'] (or a goal); obs has {', '.join(obs)}")
        obs = {**obs, "goal": goal, "goal_labels": goal_labels}
        seed = self.seed if seed is None else seed
        idx = _fps_idx(np.asarray(obs["points"]), hp.num_points, seed)
        return policy_inputs(obs, hp.num_points, hp.num_goal_points, seed, index=idx)

    def act(self, obs: dict) -> KnifeAction:
        return PosePolicy.act_batch([self], [obs])[0]

    @staticmethod
    def act_batch(policies: list[PosePolicy], observations: list[dict]) -> list[KnifeAction]:
        """``[p.act(o) for p, o in zip(policies, observations)]`` with one network batch per denoising step.

        ``policies``: one copy per episode sharing the module (``topocut.episode``'s slots), each with its own goal
        and generator; each episode's noise comes from its own generator in the shapes act() draws it
        (``topocut.policies.diffusion.rng``), so the actions and the generators' states afterwards are those of the
        one-at-a-time calls, up to the float rounding of the batched network.  Policies that do not share a module
        and settings fall back to act() one by one."""
        if len(policies) != len(observations):
            raise ValueError(f"act_batch: {len(policies)} policies for {len(observations)} observations")
        if not policies:
            return []
        for p in policies:
            if p.generator is None:
                raise RuntimeError("PosePolicy.act called before reset(goal)")
        lead = policies[0]
        if len(policies) > 1 and (len({id(p) for p in policies}) < len(policies) or not all(
                p.module is lead.module and (p.device, p.steps) == (lead.device, lead.steps) for p in policies)):
            # one object twice draws its two actions one after the other; other modules need their own batch
            return [PosePolicy.act_batch([p], [o])[0] for p, o in zip(policies, observations)]
        hp = lead.module.hparams
        inps = [object_frame(p.inputs(o), hp.pos_scale, hp.board_z, hp.num_labels)
                for p, o in zip(policies, observations)]
        # every field has a fixed size (num_points / num_goal_points rows): stack to points B,N,3 ; history B,h,7 ...
        batch = {k: torch.as_tensor(np.stack([np.asarray(inp[k]) for inp in inps])).to(lead.device) for k in inps[0]}
        r = lead.module.predict(batch, [p.generator for p in policies], lead.steps).cpu().numpy()  # B,6
        return [decode_action(r[b], inp["center"], hp.pos_scale) for b, inp in enumerate(inps)]


def load_pose_policy(path, seed: int = 0, device: str = "cpu", steps: int | None = None) -> PosePolicy:
    module = PoseDiffusionModule.load_from_checkpoint(str(path), map_location=device, weights_only=True)
    return PosePolicy(module, seed, device, steps)

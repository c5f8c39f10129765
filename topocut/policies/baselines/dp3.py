"""DP3 (Ze et al. 2024, "3D Diffusion Policy") reimplemented for one knife pose per step.

As in DP3: a compact point-cloud encoder (per-point MLP 3 -> 64 -> 128 -> 256 with LayerNorm, max-pool,
projection to 64) produces a global feature; with the goal cloud's feature (same encoder design, own weights)
and the action history it conditions, by FiLM, a 1-D temporal UNet (diffusion_policy's ConditionalUnet1D,
small) that predicts the noise of a short action sequence.  Adaptations (docs/evaluation.md): the sequence is
the step's single pose repeated ``horizon`` times (the policy is read as the sequence mean), the points may
carry their topology label as a one-hot next to xyz, and there is no robot state besides the cut history.
"""
from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F


class DP3Encoder(nn.Module):
    """(B,N,in_dim) -> (B,out_dim): per-point MLP with LayerNorm, max-pool over points, projection."""

    def __init__(self, in_dim: int = 3, out_dim: int = 64, widths=(64, 128, 256)):
        super().__init__()
        layers, d = [], in_dim
        for w in widths:
            layers += [nn.Linear(d, w), nn.LayerNorm(w), nn.ReLU()]
            d = w
        self.mlp = nn.Sequential(*layers)
        self.proj = nn.Sequential(nn.Linear(d, out_dim), nn.LayerNorm(out_dim))
        self.out_dim = out_dim

    def forward(self, x):  # B,N,in_dim
        return self.proj(self.mlp(x).max(dim=1).values)  # B,out_dim


class SinusoidalPosEmb(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.dim = dim

    def forward(self, t):  # B, -> B,dim
        half = self.dim // 2
        freqs = torch.exp(torch.arange(half, device=t.device) * (-math.log(10000.0) / (half - 1)))
        ang = t.float()[:, None] * freqs[None]
        return torch.cat([ang.sin(), ang.cos()], dim=-1)


class Conv1dBlock(nn.Sequential):
    def __init__(self, cin: int, cout: int, kernel: int, groups: int = 8):
        super().__init__(nn.Conv1d(cin, cout, kernel, padding=kernel // 2), nn.GroupNorm(groups, cout), nn.Mish())


class CondResBlock1D(nn.Module):
    """Two conv blocks; the second sees the first's output scaled and shifted by the condition (FiLM)."""

    def __init__(self, cin: int, cout: int, cond_dim: int, kernel: int = 3, groups: int = 8):
        super().__init__()
        self.block0, self.block1 = Conv1dBlock(cin, cout, kernel, groups), Conv1dBlock(cout, cout, kernel, groups)
        self.film = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, 2 * cout))
        self.res = nn.Conv1d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x, cond):  # B,C,H ; B,cond_dim
        h = self.block0(x)
        scale, bias = self.film(cond)[..., None].chunk(2, dim=1)  # B,cout,1 each
        return self.block1(scale * h + bias) + self.res(x)


class ConditionalUnet1D(nn.Module):
    """diffusion_policy's ConditionalUnet1D: down (2 res blocks + stride-2 conv), mid, up with skips."""

    def __init__(self, input_dim: int, global_cond_dim: int, step_embed_dim: int = 64,
                 down_dims=(64, 128, 256), kernel: int = 3, groups: int = 8):
        super().__init__()
        self.step_emb = nn.Sequential(SinusoidalPosEmb(step_embed_dim), nn.Linear(step_embed_dim, 4 * step_embed_dim),
                                      nn.Mish(), nn.Linear(4 * step_embed_dim, step_embed_dim))
        cd = step_embed_dim + global_cond_dim
        dims = [input_dim, *down_dims]
        pairs = list(zip(dims[:-1], dims[1:]))
        self.down = nn.ModuleList()
        for i, (a, b) in enumerate(pairs):
            last = i == len(pairs) - 1
            self.down.append(nn.ModuleList([CondResBlock1D(a, b, cd, kernel, groups), CondResBlock1D(b, b, cd, kernel, groups),
                                            nn.Identity() if last else nn.Conv1d(b, b, 3, 2, 1)]))
        mid = down_dims[-1]
        self.mid = nn.ModuleList([CondResBlock1D(mid, mid, cd, kernel, groups), CondResBlock1D(mid, mid, cd, kernel, groups)])
        self.up = nn.ModuleList()
        for a, b in reversed(pairs[1:]):  # every up level doubles H back; the finest skip stays unused (as upstream)
            self.up.append(nn.ModuleList([CondResBlock1D(2 * b, a, cd, kernel, groups), CondResBlock1D(a, a, cd, kernel, groups),
                                          nn.ConvTranspose1d(a, a, 4, 2, 1)]))
        self.final = nn.Sequential(Conv1dBlock(down_dims[0], down_dims[0], kernel, groups),
                                   nn.Conv1d(down_dims[0], input_dim, 1))

    def forward(self, x, t, global_cond):  # B,H,D ; B, ; B,G -> B,H,D
        cond = torch.cat([self.step_emb(t), global_cond], dim=-1)
        h, skips = x.transpose(1, 2), []  # B,D,H
        for res0, res1, down in self.down:
            h = res1(res0(h, cond), cond)
            skips.append(h)
            h = down(h)
        for res in self.mid:
            h = res(h, cond)
        for res0, res1, up in self.up:
            h = torch.cat([h, skips.pop()], dim=1)
            h = up(res1(res0(h, cond), cond))
        return self.final(h).transpose(1, 2)


class DP3Net(nn.Module):
    """encode(batch) -> global condition (B, 3*enc_dim); denoise(x (B,H,A), t (B,), cond) -> noise (B,H,A)."""

    def __init__(self, action_dim: int = 6, num_labels: int = 32, use_labels: bool = True, enc_dim: int = 64,
                 down_dims=(64, 128, 256), horizon: int = 4, history_len: int = 3, pose_dim: int = 7):
        super().__init__()
        if horizon < 2 ** (len(down_dims) - 1):
            raise ValueError(f"dp3 horizon={horizon} must be >= 2**(len(down_dims)-1)={2 ** (len(down_dims) - 1)}")
        self.horizon, self.num_labels, self.use_labels = horizon, num_labels, use_labels
        in_dim = 3 + (num_labels if use_labels else 0)
        self.obs_enc, self.goal_enc = DP3Encoder(in_dim, enc_dim), DP3Encoder(in_dim, enc_dim)
        self.hist_enc = nn.Sequential(nn.Linear(history_len * pose_dim, enc_dim), nn.LayerNorm(enc_dim), nn.ReLU())
        self.unet = ConditionalUnet1D(action_dim, 3 * enc_dim, down_dims=down_dims)

    def _feats(self, pts, labels):  # B,N,3 ; B,N -> B,N,in_dim
        if not self.use_labels:
            return pts
        return torch.cat([pts, F.one_hot(labels, self.num_labels).to(pts.dtype)], dim=-1)

    def encode(self, batch: dict):
        obs = self.obs_enc(self._feats(batch["points"], batch["labels"]))  # B,enc
        goal = self.goal_enc(self._feats(batch["goal"], batch["goal_labels"]))  # B,enc
        hist = self.hist_enc(batch["history"].flatten(1))  # B,enc
        return torch.cat([obs, goal, hist], dim=-1)

    def denoise(self, x, t, cond, x_raw=None):  # x_raw unused: DP3 has no positional attention
        return self.unet(x, t, cond)

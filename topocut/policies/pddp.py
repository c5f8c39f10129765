"""PDDP network: (noisy mask x_t, noise level sigma, condition) -> per-point log-scores.

Paper appendix "Policy Model Architecture - PDDP":
  observation z_t = Phi(X_t, F_t) (B,N,96) from a perception encoder (topocut.policies.encoders)
  + token embedding of the noisy mask state          -> per-point tokens (B,N,96)
  goal z_g = Phi(X_g, F_g) (B,G,96): the goal cloud and its piece labels through the same encoder as the observation
  goal encoder 96 -> 64 -> 96 per goal point          -> pooled (max ‖ mean) into the conditioning, or cross-attended
  (goal_input="xyz", checkpoints from before the goal labels: 3 -> 64 -> 96 on the goal's positions only)
  action history (3 x 7 = 21) -> 128;  sigma: sinusoidal 256 -> 128 -> 128 (SiLU)
  conditioning layer concat(time, history[, goal]) -> 128, feeding adaLN (128 -> 6 x 96) in every block
  12 DDiT blocks (self-attention 96 -> 288 -> 96, MLP 96 -> 384 -> 96, GELU, dropout 0.4)
  output: adaLN final layer, linear 96 -> 2 logits per point of p(clean mask | x_t, condition), turned into
  exact log-scores s_y = log sum_c p(c | x_t) p(y | c)/p(x | c) ("denoiser" parametrisation; or SEDD's
  direct log-scores over the graph's states with the scale_by_sigma baseline, score_param="direct").
The points are a set: no positional or rotary encoding; attention is permutation-equivariant.
"""
from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F

from topocut.policies.config import PDDPConfig
from topocut.policies.diffusion.graph import Graph, build_graph


def modulate(x, shift, scale):  # x B,N,D; shift, scale B,D
    return x * (1.0 + scale[:, None]) + shift[:, None]


class SigmaEmbedder(nn.Module):
    """Sinusoidal features of sigma followed by Linear-SiLU-Linear (256 -> 128 -> 128)."""

    def __init__(self, out_dim: int, freq_dim: int = 256, max_period: float = 10000.0):
        super().__init__()
        self.freq_dim, self.max_period = freq_dim, max_period
        self.mlp = nn.Sequential(nn.Linear(freq_dim, out_dim), nn.SiLU(), nn.Linear(out_dim, out_dim))

    def forward(self, sigma):  # B -> B,out
        half = self.freq_dim // 2
        freqs = torch.exp(-math.log(self.max_period) * torch.arange(half, device=sigma.device) / half)
        args = sigma.float()[:, None] * freqs[None]
        return self.mlp(torch.cat([torch.cos(args), torch.sin(args)], -1))


class Attention(nn.Module):
    """Multi-head attention of queries x (B,N,D) over keys/values y (B,M,D); y = x for self-attention."""

    def __init__(self, dim: int, n_heads: int, cross: bool = False):
        super().__init__()
        self.n_heads = n_heads
        self.q = nn.Linear(dim, dim, bias=False) if cross else None
        self.kv = nn.Linear(dim, 2 * dim if cross else 3 * dim, bias=False)  # self: fused qkv 96 -> 288
        self.out = nn.Linear(dim, dim, bias=False)

    def forward(self, x, y=None, key_mask=None):  # key_mask B,M bool: the keys attended to (None: all)
        B, N, D = x.shape
        if self.q is None:
            q, k, v = self.kv(x).chunk(3, -1)
        else:
            q, (k, v) = self.q(x), self.kv(y).chunk(2, -1)

        def heads(t):  # B,M,D -> B,h,M,D/h
            return t.view(B, t.shape[1], self.n_heads, D // self.n_heads).transpose(1, 2)

        mask = None if key_mask is None else key_mask.bool()[:, None, None, :]  # B,1,1,M
        o = F.scaled_dot_product_attention(heads(q), heads(k), heads(v), attn_mask=mask)  # B,h,N,D/h
        return self.out(o.transpose(1, 2).reshape(B, N, D))


class DDiTBlock(nn.Module):
    def __init__(self, dim: int, n_heads: int, cond_dim: int, mlp_ratio: int = 4, dropout: float = 0.4,
                 cross: bool = False):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, elementwise_affine=False)
        self.attn = Attention(dim, n_heads)
        self.norm2 = nn.LayerNorm(dim, elementwise_affine=False)
        self.mlp = nn.Sequential(nn.Linear(dim, mlp_ratio * dim), nn.GELU(approximate="tanh"),
                                 nn.Linear(mlp_ratio * dim, dim))
        self.drop = nn.Dropout(dropout)
        if cross:
            self.norm_x = nn.LayerNorm(dim)
            self.cross = Attention(dim, n_heads, cross=True)
        else:
            self.cross = None
        # adaLN: 128 -> 6 x 96 (shift, scale, gate for attention and MLP); zero init = identity block at start
        self.ada = nn.Linear(cond_dim, 6 * dim)
        nn.init.zeros_(self.ada.weight)
        nn.init.zeros_(self.ada.bias)

    def forward(self, x, c, goal_tokens=None, goal_mask=None):  # x B,N,D; c B,C; goal_tokens B,G,D; goal_mask B,G
        sh1, sc1, g1, sh2, sc2, g2 = self.ada(c).chunk(6, -1)
        x = x + g1[:, None] * self.drop(self.attn(modulate(self.norm1(x), sh1, sc1)))
        if self.cross is not None:
            x = x + self.drop(self.cross(self.norm_x(x), goal_tokens, goal_mask))
        return x + g2[:, None] * self.drop(self.mlp(modulate(self.norm2(x), sh2, sc2)))


class FinalLayer(nn.Module):
    def __init__(self, dim: int, out_dim: int, cond_dim: int):
        super().__init__()
        self.norm = nn.LayerNorm(dim, elementwise_affine=False)
        self.ada = nn.Linear(cond_dim, 2 * dim)
        self.linear = nn.Linear(dim, out_dim)
        for m in (self.ada, self.linear):  # zero init: log-scores start at the sigma baseline
            nn.init.zeros_(m.weight)
            nn.init.zeros_(m.bias)

    def forward(self, x, c):
        shift, scale = self.ada(c).chunk(2, -1)
        return self.linear(modulate(self.norm(x), shift, scale))


class PDDPNet(nn.Module):
    """Score network.  ``context(z, goal, history)`` once per observation, then ``forward(x_t, sigma, ctx)``."""

    def __init__(self, cfg: PDDPConfig | None = None):
        super().__init__()
        cfg = (cfg or PDDPConfig()).validate()
        self.cfg = cfg
        self.graph: Graph = build_graph(cfg.graph, cfg.num_classes)
        H, C = cfg.hidden, cfg.cond_dim
        self.obs_proj = nn.Linear(cfg.obs_dim, H) if cfg.obs_dim != H else nn.Identity()
        self.token_embed = nn.Embedding(self.graph.dim, H)
        goal_in = cfg.obs_dim if cfg.goal_input == "phi" else 3  # z_g = Phi(X_g, F_g), or legacy xyz
        self.goal_enc = nn.Sequential(nn.Linear(goal_in, cfg.goal_hidden), nn.ReLU(), nn.Linear(cfg.goal_hidden, H))
        self.hist = nn.Linear(cfg.history_len * cfg.pose_dim, C)
        self.sigma_map = SigmaEmbedder(C, cfg.time_freq_dim)
        pooled = 2 * H if cfg.goal_mode == "pool" else 0
        self.cond = nn.Linear(2 * C + pooled, C)  # 256 -> 128 (+ pooled goal in "pool" mode)
        cross = cfg.goal_mode == "cross"
        self.blocks = nn.ModuleList(DDiTBlock(H, cfg.n_heads, C, cfg.mlp_ratio, cfg.dropout, cross)
                                    for _ in range(cfg.n_blocks))
        # "denoiser": logits of p(x_0 | x_t) over the clean classes (the paper's 2 binary logits per point),
        # turned into log-scores exactly; "direct": SEDD's log-scores over all graph states
        n_out = cfg.num_classes if cfg.score_param == "denoiser" else self.graph.dim
        self.out = FinalLayer(H, n_out, C)

    def context(self, z, goal, history, goal_valid=None) -> dict:
        """z (B,N,obs_dim) point embeddings, goal (B,G,obs_dim) goal embeddings z_g (goal_input="xyz": (B,G,3)
        goal points), history (B,h,7), goal_valid (B,G) bool (None: every row; padding copies are left out of
        the pooling and the cross-attention) -> sigma-free context."""
        g = self.goal_enc(goal)  # B,G,H
        ctx = {"z": self.obs_proj(z), "hist": self.hist(history.flatten(1))}  # B,N,H ; B,C
        if self.cfg.goal_mode == "pool":
            if goal_valid is None:
                ctx["goal_vec"] = torch.cat([g.max(1).values, g.mean(1)], -1)  # B,2H
            else:
                w = goal_valid.to(g.dtype)[..., None]  # B,G,1
                gmax = g.masked_fill(w == 0, float("-inf")).max(1).values
                gmean = (g * w).sum(1) / w.sum(1).clamp(min=1.0)
                ctx["goal_vec"] = torch.cat([gmax, gmean], -1)
        else:
            ctx["goal_tokens"] = g
            ctx["goal_mask"] = goal_valid
        return ctx

    def forward(self, x_t, sigma, ctx: dict):
        """x_t (B,N) long noisy mask, sigma (B,) -> log-scores (B,N,d); entry x_t itself is 0 (ratio 1)."""
        h = ctx["z"] + self.token_embed(x_t)  # B,N,H
        parts = [F.silu(self.sigma_map(sigma)), ctx["hist"]]
        if "goal_vec" in ctx:
            parts.append(ctx["goal_vec"])
        c = F.silu(self.cond(torch.cat(parts, -1)))  # B,C
        goal_tokens, goal_mask = ctx.get("goal_tokens"), ctx.get("goal_mask")
        for blk in self.blocks:
            h = blk(h, c, goal_tokens, goal_mask)
        out = self.out(h, c)  # B,N,K or B,N,d
        if self.cfg.score_param == "denoiser":
            log_pi = torch.log_softmax(out.float(), -1)  # B,N,K
            out = self.graph.score_from_denoiser(log_pi, x_t, sigma.float()[:, None])  # B,N,d
        elif self.cfg.scale_by_sigma:
            out = out + self.graph.log_score_offset(sigma.float())[:, None, None].to(out)
        return out.scatter(-1, x_t[..., None], torch.zeros_like(out[..., :1]))

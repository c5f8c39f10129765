"""3D Diffuser Actor (Ke et al. 2024) reimplemented for one knife pose per step, without RGB or language.

The idea kept from 3DDA: every scene point is a token with a 3-D position, and the noisy action token
attends to the scene with *relative* 3-D attention -- rotary position encodings on xyz make the attention
logits depend only on position differences, so the denoiser is translation-equivariant.  Here the scene
tokens are an MLP of (xyz, topology-label one-hot); the goal cloud gives a second token set; the cut history
gives three query tokens next to the action token; the action token sits at the noisy cut point
(x, y, board height) and is re-positioned at every denoising step, as 3DDA places its noisy gripper token.
The denoising step and the history modulate every block by adaptive LayerNorm (FiLM).
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from topocut.policies.baselines.dp3 import SinusoidalPosEmb


class Rotary3D(nn.Module):
    """Rotary encoding on xyz: head_dim splits into 3 axis chunks of ``k`` (cos, sin) pairs.

    Pair i of axis a is rotated by angle pos_a * freq_i, freq_i = base * 2**i, so that
    <rot(q, p_q), rot(k, p_k)> depends on p_k - p_q only.
    """

    def __init__(self, head_dim: int, base: float = 1.0):
        super().__init__()
        if head_dim % 6:
            raise ValueError(f"3dda head_dim={head_dim} must be divisible by 6 (3 axes x cos/sin pairs)")
        self.k = head_dim // 6
        self.register_buffer("freqs", base * 2.0 ** torch.arange(self.k, dtype=torch.float32), persistent=False)

    def forward(self, x, pos):  # x B,h,N,Dh ; pos B,N,3
        ang = pos[..., None] * self.freqs  # B,N,3,k
        cos, sin = ang.cos()[:, None], ang.sin()[:, None]  # B,1,N,3,k
        x = x.unflatten(-1, (3, self.k, 2))  # B,h,N,3,k,2
        x1, x2 = x[..., 0], x[..., 1]
        return torch.stack([x1 * cos - x2 * sin, x1 * sin + x2 * cos], dim=-1).flatten(-3)


class RelativeAttention(nn.Module):
    """Multi-head attention of queries at pos_q over keys at pos_k with 3-D rotary encodings on q and k."""

    def __init__(self, dim: int, heads: int, rope_base: float = 1.0):
        super().__init__()
        if dim % heads:
            raise ValueError(f"3dda dim={dim} must be divisible by heads={heads}")
        self.heads = heads
        self.q, self.kv, self.out = nn.Linear(dim, dim), nn.Linear(dim, 2 * dim), nn.Linear(dim, dim)
        self.rope = Rotary3D(dim // heads, rope_base)

    def forward(self, x, pos_q, ctx, pos_k, key_mask=None):  # B,Nq,D ; B,Nq,3 ; B,Nk,D ; B,Nk,3 ; B,Nk bool
        B, Nq, D = x.shape
        q = self.q(x).view(B, Nq, self.heads, -1).transpose(1, 2)  # B,h,Nq,Dh
        k, v = self.kv(ctx).view(B, ctx.shape[1], 2, self.heads, -1).permute(2, 0, 3, 1, 4)  # B,h,Nk,Dh each
        # padding copies of a point are identical keys: masking all but one attends to each point once
        mask = None if key_mask is None else key_mask.bool()[:, None, None, :]  # B,1,1,Nk
        o = F.scaled_dot_product_attention(self.rope(q, pos_q), self.rope(k, pos_k), v, attn_mask=mask)
        return self.out(o.transpose(1, 2).reshape(B, Nq, D))


class FiLMNorm(nn.Module):
    """LayerNorm without affine, then (1 + scale) * x + shift from the condition (adaLN)."""

    def __init__(self, dim: int, cond_dim: int):
        super().__init__()
        self.norm = nn.LayerNorm(dim, elementwise_affine=False)
        self.mod = nn.Linear(cond_dim, 2 * dim)
        nn.init.zeros_(self.mod.weight)
        nn.init.zeros_(self.mod.bias)

    def forward(self, x, cond):  # B,N,D ; B,C
        scale, shift = self.mod(cond)[:, None].chunk(2, dim=-1)
        return self.norm(x) * (1 + scale) + shift


class QueryBlock(nn.Module):
    """Query tokens: relative cross-attention to scene, to goal, relative self-attention, MLP (pre-norm)."""

    def __init__(self, dim: int, heads: int, cond_dim: int, rope_base: float):
        super().__init__()
        self.norms = nn.ModuleList([FiLMNorm(dim, cond_dim) for _ in range(4)])
        self.scene = RelativeAttention(dim, heads, rope_base)
        self.goal = RelativeAttention(dim, heads, rope_base)
        self.self_attn = RelativeAttention(dim, heads, rope_base)
        self.mlp = nn.Sequential(nn.Linear(dim, 4 * dim), nn.GELU(), nn.Linear(4 * dim, dim))

    def forward(self, q, pos_q, scene, pos_s, goal, pos_g, cond, mask_s=None, mask_g=None):
        q = q + self.scene(self.norms[0](q, cond), pos_q, scene, pos_s, mask_s)
        q = q + self.goal(self.norms[1](q, cond), pos_q, goal, pos_g, mask_g)
        h = self.norms[2](q, cond)
        q = q + self.self_attn(h, pos_q, h, pos_q)
        return q + self.mlp(self.norms[3](q, cond))


class ContextBlock(nn.Module):
    """Relative self-attention among the scene points (lets each point see its piece and neighbours)."""

    def __init__(self, dim: int, heads: int, rope_base: float):
        super().__init__()
        self.n1, self.n2 = nn.LayerNorm(dim), nn.LayerNorm(dim)
        self.attn = RelativeAttention(dim, heads, rope_base)
        self.mlp = nn.Sequential(nn.Linear(dim, 4 * dim), nn.GELU(), nn.Linear(4 * dim, dim))

    def forward(self, x, pos, mask=None):
        h = self.n1(x)
        x = x + self.attn(h, pos, h, pos, mask)
        return x + self.mlp(self.n2(x))


class DiffuserActorNet(nn.Module):
    """encode(batch) -> context tokens; denoise(x (B,1,A), t, ctx, x_raw (B,1,A)) -> noise (B,1,A).

    ``x_raw`` is the noisy action in the centred, scaled frame of the points (module.py's action
    representation): its first two entries are the cut point (x, y), which positions the action token.
    """

    def __init__(self, action_dim: int = 6, num_labels: int = 32, use_labels: bool = True, dim: int = 96,
                 heads: int = 4, layers: int = 2, context_layers: int = 1, history_len: int = 3,
                 pose_dim: int = 7, rope_base: float = 1.0):
        super().__init__()
        self.horizon, self.num_labels, self.use_labels = 1, num_labels, use_labels
        in_dim = 3 + (num_labels if use_labels else 0)
        self.scene_in = nn.Sequential(nn.Linear(in_dim, dim), nn.GELU(), nn.Linear(dim, dim))
        self.goal_in = nn.Sequential(nn.Linear(in_dim, dim), nn.GELU(), nn.Linear(dim, dim))
        self.context = nn.ModuleList([ContextBlock(dim, heads, rope_base) for _ in range(context_layers)])
        self.hist_in = nn.Linear(pose_dim, dim)
        self.hist_pos_emb = nn.Parameter(torch.zeros(history_len, dim))  # which previous cut (oldest first)
        self.action_in = nn.Linear(action_dim, dim)
        self.step_emb = nn.Sequential(SinusoidalPosEmb(dim), nn.Linear(dim, dim), nn.GELU(), nn.Linear(dim, dim))
        self.hist_cond = nn.Linear(history_len * pose_dim, dim)
        self.blocks = nn.ModuleList([QueryBlock(dim, heads, dim, rope_base) for _ in range(layers)])
        self.out_norm = nn.LayerNorm(dim)
        self.out = nn.Linear(dim, action_dim)

    def _feats(self, pts, labels):
        if not self.use_labels:
            return pts
        return torch.cat([pts, F.one_hot(labels, self.num_labels).to(pts.dtype)], dim=-1)

    def encode(self, batch: dict) -> dict:
        pts, goal = batch["points"], batch["goal"]  # B,N,3 ; B,G,3
        scene = self.scene_in(self._feats(pts, batch["labels"]))  # B,N,D
        mask_s, mask_g = batch.get("valid"), batch.get("goal_valid")  # B,N ; B,G  (None: no padding)
        for blk in self.context:
            scene = blk(scene, pts, mask_s)
        hist = batch["history"]  # B,3,7 (positions already in the centred frame)
        return {"scene": scene, "pos_s": pts, "goal": self.goal_in(self._feats(goal, batch["goal_labels"])),
                "pos_g": goal, "hist": self.hist_in(hist) + self.hist_pos_emb, "pos_h": hist[..., :3],
                "hist_cond": self.hist_cond(hist.flatten(1)), "board": batch["board"],  # board: B, board height
                "mask_s": mask_s, "mask_g": mask_g}

    def denoise(self, x, t, ctx: dict, x_raw):  # x B,1,A (normalised) ; x_raw B,1,A (centred frame)
        B = x.shape[0]
        pos_a = torch.cat([x_raw[..., :2], ctx["board"].view(B, 1, 1).expand(B, x.shape[1], 1)], dim=-1)  # B,1,3
        q = torch.cat([self.action_in(x), ctx["hist"]], dim=1)  # B,1+3,D
        pos_q = torch.cat([pos_a, ctx["pos_h"]], dim=1)  # B,1+3,3
        cond = self.step_emb(t) + ctx["hist_cond"]  # B,D
        for blk in self.blocks:
            q = blk(q, pos_q, ctx["scene"], ctx["pos_s"], ctx["goal"], ctx["pos_g"], cond, ctx.get("mask_s"),
                    ctx.get("mask_g"))
        return self.out(self.out_norm(q[:, : x.shape[1]]))  # B,1,A

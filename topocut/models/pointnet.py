"""PointNet-style alternative to the graph transformer (paper appendix "PointNet-Based Perception Model").

    topology encoder   input embedding (xyz ‖ one-hot 32) -> 96, then set-abstraction blocks with
                       point-wise local and global attention ("SPALPA"): FPS centroids, kNN grouping
                       (QueryAndGroup with k nearest instead of a ball), shared Conv2d MLP, softmax
                       local attention over the k neighbours, multi-head self-attention over centroids
    action encoder     the same on the 2-class cut mask
    cross-attention    pre-norm attention from coarsest topology to coarsest action tokens, gated residual
    decoder            feature propagation (inverse-distance interpolation of the 3 nearest coarse
                       points + skip features + MLP) back to every input point
    heads              segmentation head (Conv1d -> 32 logits), point head (residual blocks -> Δxyz)

``PointNetEncoder`` has Φ's interface (points, labels) -> (B,N,hidden); inside the dynamics model the
cross-attention runs between its encoding and decoding halves.
"""
from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

from topocut.models.config import DynamicsConfig
from topocut.models.dynamics import point_head
from topocut.models.encoder import centre_points, one_hot_labels
from topocut.models.graphs import knn


def gather(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """x (B,N,C), idx (B,...) long -> (B,...,C)."""
    B = x.shape[0]
    flat = idx.reshape(B, -1)
    out = torch.gather(x, 1, flat[..., None].expand(-1, -1, x.shape[-1]))
    return out.view(*idx.shape, x.shape[-1])


class SetAbstraction(nn.Module):
    """One SPALPA block: (xyz (B,N,3), feat (B,N,C)) -> (xyz (B,M,3), feat (B,M,out)), M = ceil(ratio N)."""

    def __init__(self, in_dim: int, out_dim: int, ratio: float, k: int, heads: int):
        super().__init__()
        self.ratio, self.k = ratio, k
        self.mlp = nn.Sequential(nn.Conv2d(in_dim + 3, out_dim, 1), nn.GroupNorm(1, out_dim), nn.ReLU(),
                                 nn.Conv2d(out_dim, out_dim, 1))
        self.local_score = nn.Conv2d(out_dim, 1, 1)  # local attention weight of each neighbour
        self.norm = nn.LayerNorm(out_dim)
        self.global_attn = nn.MultiheadAttention(out_dim, heads, batch_first=True)
        self.ffn = nn.Sequential(nn.LayerNorm(out_dim), nn.Linear(out_dim, 2 * out_dim), nn.GELU(),
                                 nn.Linear(2 * out_dim, out_dim))

    def forward(self, xyz: torch.Tensor, feat: torch.Tensor):
        from topocut.metrics import fps_torch

        M = max(1, int(round(xyz.shape[1] * self.ratio)))
        with torch.no_grad():
            cidx = fps_torch(xyz.detach(), M) if M < xyz.shape[1] else None
        new_xyz = gather(xyz, cidx.long()) if cidx is not None else xyz  # B,M,3
        nbr, valid = knn(new_xyz, xyz, self.k)  # B,M,k
        rel = gather(xyz, nbr) - new_xyz[:, :, None]  # B,M,k,3
        grouped = torch.cat([rel, gather(feat, nbr)], dim=-1).permute(0, 3, 1, 2)  # B,C+3,M,k
        h = self.mlp(grouped)  # B,out,M,k
        score = self.local_score(h).masked_fill(~valid[:, None], float("-inf"))  # B,1,M,k
        h = (h * torch.softmax(score, dim=-1)).sum(-1).transpose(1, 2)  # B,M,out
        a = self.norm(h)
        h = h + self.global_attn(a, a, a, need_weights=False)[0]
        return new_xyz, h + self.ffn(h)


class FeaturePropagation(nn.Module):
    """Interpolate coarse features onto fine points (3 nearest, inverse distance) and fuse with skips."""

    def __init__(self, coarse_dim: int, skip_dim: int, out_dim: int):
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(coarse_dim + skip_dim, out_dim), nn.LayerNorm(out_dim), nn.ReLU(),
                                 nn.Linear(out_dim, out_dim))

    def forward(self, xyz_f, feat_f, xyz_c, feat_c):  # B,N,3  B,N,Cs  B,M,3  B,M,Cc -> B,N,out
        idx, valid = knn(xyz_f, xyz_c, 3)
        d = (gather(xyz_c, idx) - xyz_f[:, :, None]).norm(dim=-1)  # B,N,3
        w = valid.float() / (d + 1e-8)
        w = w / w.sum(-1, keepdim=True)
        interp = (gather(feat_c, idx) * w[..., None]).sum(2)  # B,N,Cc
        return self.mlp(torch.cat([interp, feat_f], dim=-1))


class PointNetEncoder(nn.Module):
    """Hierarchical point encoder with Φ's interface: (points (B,N,3), labels (B,N)) -> (B,N,out_dim)."""

    def __init__(self, dims: list[int], num_labels: int = 32, ratio: float = 0.25, k: int = 16, heads: int = 4,
                 coord_scale: float = 0.1, decoder: bool = True):
        super().__init__()
        self.num_labels, self.coord_scale = num_labels, coord_scale
        self.out_dim = dims[0]
        self.embed = nn.Sequential(nn.Linear(3 + num_labels, dims[0]), nn.ReLU(), nn.Linear(dims[0], dims[0]))
        self.blocks = nn.ModuleList(SetAbstraction(a, b, ratio, k, heads) for a, b in zip(dims[:-1], dims[1:]))
        self.fps = nn.ModuleList(FeaturePropagation(c, s, s) for s, c in zip(dims[:-1], dims[1:])) if decoder else None

    def encode(self, points: torch.Tensor, labels: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Levels [(xyz, feat)] from the input points (level 0) to the coarsest centroids."""
        p = centre_points(points, self.coord_scale)  # B,N,3 (grouping works in these units too)
        feat = self.embed(torch.cat([p, one_hot_labels(labels.long(), self.num_labels)], dim=-1))
        levels = [(p, feat)]
        for block in self.blocks:
            levels.append(block(*levels[-1]))
        return levels

    def decode(self, levels: list) -> torch.Tensor:
        xyz, feat = levels[-1]
        for (xyz_f, feat_f), fp in zip(reversed(levels[:-1]), reversed(self.fps)):
            feat = fp(xyz_f, feat_f, xyz, feat)
            xyz = xyz_f
        return feat  # B,N,dims[0]

    def forward(self, points: torch.Tensor, labels: torch.Tensor,
                fuse: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None) -> torch.Tensor:
        levels = self.encode(points, labels)
        if fuse is not None:  # hook: transform the coarsest features (xyz, feat) -> feat before decoding
            levels[-1] = (levels[-1][0], fuse(*levels[-1]))
        return self.decode(levels)


class CrossAttnNet(nn.Module):
    """Pre-norm cross-attention with a gated residual (gate starts near closed: tanh(0) = 0)."""

    def __init__(self, dim: int, ctx_dim: int, heads: int):
        super().__init__()
        self.nq, self.nc = nn.LayerNorm(dim), nn.LayerNorm(ctx_dim)
        self.attn = nn.MultiheadAttention(dim, heads, kdim=ctx_dim, vdim=ctx_dim, batch_first=True)
        self.gate = nn.Parameter(torch.zeros(dim))
        self.ffn = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, 2 * dim), nn.GELU(), nn.Linear(2 * dim, dim))

    def forward(self, x: torch.Tensor, ctx: torch.Tensor) -> torch.Tensor:  # B,M,D  B,S,Dc -> B,M,D
        c = self.nc(ctx)
        x = x + torch.tanh(self.gate) * self.attn(self.nq(x), c, c, need_weights=False)[0]
        return x + self.ffn(x)


class PointNetDynamics(nn.Module):
    """F built from PointNet encoders; same call signature as GraphTransformerDynamics."""

    def __init__(self, cfg: DynamicsConfig | None = None):
        super().__init__()
        cfg = (cfg or DynamicsConfig(model="pointnet")).validate()
        self.cfg = cfg
        dims = list(cfg.pointnet_dims)
        self.topo_encoder = PointNetEncoder(dims, cfg.num_labels, cfg.pointnet_ratio, cfg.pointnet_k, cfg.num_heads,
                                            cfg.coord_scale)
        self.action_encoder = PointNetEncoder(dims, 2, cfg.pointnet_ratio, cfg.pointnet_k, cfg.num_heads,
                                              cfg.coord_scale, decoder=False)
        self.cross = nn.ModuleList(CrossAttnNet(dims[-1], dims[-1], cfg.num_heads) for _ in range(2))
        D = dims[0]
        self.seg_head = nn.Sequential(nn.Conv1d(D, D, 1), nn.ReLU(), nn.Conv1d(D, cfg.num_labels, 1))
        self.pos_head = point_head(D, 3)

    @property
    def encoder(self) -> PointNetEncoder:
        return self.topo_encoder

    def forward(self, x_t: torch.Tensor, f_t: torch.Tensor, x_a: torch.Tensor, g: torch.Tensor):
        """x_t (B,N,3), f_t (B,N), x_a (B,M,3), g (B,M) -> (x_t1 (B,N,3), logits (B,N,C))."""
        _, ctx = self.action_encoder.encode(x_a, g)[-1]  # B,S,D

        def fuse(xyz, feat):
            for layer in self.cross:
                feat = layer(feat, ctx)
            return feat

        h = self.topo_encoder(x_t, f_t, fuse=fuse)  # B,N,D
        logits = self.seg_head(h.transpose(1, 2)).transpose(1, 2)  # B,N,C
        return x_t + self.cfg.coord_scale * self.pos_head(h), logits


def build_model(cfg: DynamicsConfig) -> nn.Module:
    """The dynamics model F named by ``cfg.model``."""
    from topocut.models.dynamics import GraphTransformerDynamics

    cfg.validate()
    return GraphTransformerDynamics(cfg) if cfg.model == "graph_transformer" else PointNetDynamics(cfg)


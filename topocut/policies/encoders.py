"""Perception encoders for PDDP: points (B,N,3) + topology labels (B,N) -> per-point embeddings (B,N,96).

The paper's three perception configurations (Table "cutting_eval"):
  "none"       no perception model: a per-point MLP + kNN max-pool, trained from scratch with the policy;
  "pretrained" the frozen dynamics-informed encoder Phi from pretraining (its checkpoint, or the architecture a
  PDDP checkpoint recorded: build_encoder);
  "graphconv"  a self-attention GraphConv encoder (local attention over kNN graphs) trained with the policy.
Every encoder has ``out_dim`` and ``forward(points, labels)``.  Labels may be -1 (unassigned).
"""
from __future__ import annotations

import torch
import torch.nn as nn

ENCODER_KINDS = ("none", "pretrained", "graphconv")


def knn(points: torch.Tensor, k: int) -> torch.Tensor:
    """Indices (B,N,k) of each point's k nearest neighbours (itself included)."""
    d = torch.cdist(points, points)  # B,N,N
    return d.topk(min(k, points.shape[1]), dim=-1, largest=False).indices


def gather(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """x (B,N,C), idx (B,N,k) -> (B,N,k,C)."""
    B, N, k = idx.shape
    return x.gather(1, idx.reshape(B, N * k, 1).expand(-1, -1, x.shape[-1])).view(B, N, k, x.shape[-1])


def label_index(labels: torch.Tensor, num_labels: int) -> torch.Tensor:
    """-1 (unassigned) -> 0, cluster c -> c + 1, clipped to the embedding table."""
    return (labels.long() + 1).clamp(0, num_labels - 1)


class PointMLPEncoder(nn.Module):
    """"w/o perception": per-point MLP on (xyz, label embedding), then max-pool of edge features over kNN."""

    def __init__(self, out_dim: int = 96, num_labels: int = 32, k: int = 16, width: int = 64):
        super().__init__()
        self.out_dim, self.num_labels, self.k = out_dim, num_labels, k
        self.label = nn.Embedding(num_labels, 16)
        self.point = nn.Sequential(nn.Linear(3 + 16, width), nn.ReLU(), nn.Linear(width, width))
        self.edge = nn.Sequential(nn.Linear(width + 3, width), nn.ReLU(), nn.Linear(width, width))
        self.head = nn.Sequential(nn.Linear(2 * width, out_dim), nn.LayerNorm(out_dim))

    def forward(self, points, labels):  # B,N,3 ; B,N
        h = self.point(torch.cat([points, self.label(label_index(labels, self.num_labels))], -1))  # B,N,W
        idx = knn(points, self.k)  # B,N,k
        rel = gather(points, idx) - points[:, :, None]  # B,N,k,3
        e = self.edge(torch.cat([gather(h, idx), rel], -1)).max(2).values  # B,N,W
        return self.head(torch.cat([h, e], -1))


class LocalAttention(nn.Module):
    """Self-attention restricted to the kNN graph, with relative-position encodings on keys and values."""

    def __init__(self, dim: int, n_heads: int = 4):
        super().__init__()
        self.n_heads = n_heads
        self.norm = nn.LayerNorm(dim)
        self.qkv = nn.Linear(dim, 3 * dim)
        self.pos = nn.Sequential(nn.Linear(3, dim), nn.ReLU(), nn.Linear(dim, dim))
        self.out = nn.Linear(dim, dim)
        self.mlp = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, 2 * dim), nn.GELU(), nn.Linear(2 * dim, dim))

    def forward(self, h, points, idx):  # h B,N,D ; points B,N,3 ; idx B,N,k
        B, N, D = h.shape
        k, H = idx.shape[-1], self.n_heads
        q, kk, v = self.qkv(self.norm(h)).chunk(3, -1)
        p = self.pos(gather(points, idx) - points[:, :, None])  # B,N,k,D
        kk, v = gather(kk, idx) + p, gather(v, idx) + p  # B,N,k,D
        logits = (q.view(B, N, 1, H, D // H) * kk.view(B, N, k, H, D // H)).sum(-1) / (D // H) ** 0.5  # B,N,k,H
        a = logits.softmax(2)[..., None]  # over neighbours
        o = (a * v.view(B, N, k, H, D // H)).sum(2).reshape(B, N, D)
        h = h + self.out(o)
        return h + self.mlp(h)


class GraphConvEncoder(nn.Module):
    """"GraphConv" configuration: label+position embedding, then ``layers`` local self-attention GraphConvs."""

    def __init__(self, out_dim: int = 96, num_labels: int = 32, k: int = 16, layers: int = 2, n_heads: int = 4):
        super().__init__()
        self.out_dim, self.num_labels, self.k = out_dim, num_labels, k
        self.label = nn.Embedding(num_labels, out_dim)
        self.point = nn.Sequential(nn.Linear(3, out_dim), nn.ReLU(), nn.Linear(out_dim, out_dim))
        self.layers = nn.ModuleList(LocalAttention(out_dim, n_heads) for _ in range(layers))
        self.norm = nn.LayerNorm(out_dim)

    def forward(self, points, labels):
        h = self.point(points) + self.label(label_index(labels, self.num_labels))  # B,N,D
        idx = knn(points, self.k)
        for layer in self.layers:
            h = layer(h, points, idx)
        return self.norm(h)


class FrozenEncoder(nn.Module):
    """The pretrained perception encoder Phi, frozen (no gradients, always in eval mode)."""

    def __init__(self, encoder: nn.Module):
        super().__init__()
        self.encoder = encoder.eval()
        for p in self.encoder.parameters():
            p.requires_grad_(False)
        self.out_dim = int(getattr(encoder, "out_dim", 96))

    def train(self, mode: bool = True):  # keep dropout/normalisation of Phi as pretrained
        super().train(mode)
        self.encoder.eval()
        return self

    @torch.no_grad()
    def forward(self, points, labels):
        return self.encoder(points, labels.long())


def build_encoder(kind: str, ckpt: str | None = None, out_dim: int = 96, num_labels: int = 32,
                  arch: dict | None = None) -> nn.Module:
    """One of ENCODER_KINDS. "pretrained": Φ of the pretrain checkpoint ``ckpt``, or, given ``arch`` (the
    DynamicsConfig that checkpoint recorded), Φ built from it without reading any file: a PDDP checkpoint holds
    Φ's weights in its own state dict, so it loads on a machine that never had the perception checkpoint."""
    if kind == "none":
        return PointMLPEncoder(out_dim, num_labels)
    if kind == "graphconv":
        return GraphConvEncoder(out_dim, num_labels)
    if kind == "pretrained":
        import dataclasses

        from topocut.models.module import DynamicsModule, load_dynamics  # lazy: written by the perception package

        if arch is not None:
            enc = FrozenEncoder(DynamicsModule(arch).encoder)  # weights: the caller's state dict
        elif ckpt:
            dyn = load_dynamics(ckpt)
            enc, arch = FrozenEncoder(dyn.encoder), dataclasses.asdict(dyn.cfg)
        else:
            raise ValueError("encoder='pretrained' needs ckpt: the path of a pretrain checkpoint")
        enc.arch = arch  # saved in the policy's hyper-parameters (PDDPModule's encoder_arch)
        return enc
    raise ValueError(f"encoder={kind!r} is not valid; choose one of {', '.join(ENCODER_KINDS)}")

"""kNN graphs restricted to groups (clusters or mask sides) and GCN message passing in plain torch.

A graph over a batch of clouds is kept twice:
  * ``idx (B,N,k)`` / ``valid (B,N,k)``: each node's k nearest neighbours *within its group*
    (``valid`` is False where the group has fewer than k+1 members), used for attention biases;
  * a flat, symmetrised edge list over the B*N nodes with self loops and the GCN normalisation
    D^-1/2 (A + I) D^-1/2 (Kipf & Welling), used for message passing with ``index_add_``.
No torch-geometric: everything is index tensors.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

INF = float("inf")


@dataclass
class Graph:
    idx: torch.Tensor  # B,N,k long   neighbour j of node i (within the group)
    valid: torch.Tensor  # B,N,k bool
    src: torch.Tensor  # E long        flat node index b*N + j
    dst: torch.Tensor  # E long        flat node index b*N + i
    weight: torch.Tensor  # E float    GCN normalisation of edge j -> i
    num_nodes: int  # N per cloud

    def dense(self) -> torch.Tensor:
        """Symmetric adjacency (B,N,N) bool without self loops."""
        B, N, _ = self.idx.shape
        adj = torch.zeros(B, N, N, dtype=torch.bool, device=self.idx.device)
        own = torch.arange(N, device=self.idx.device)[None, :, None].expand_as(self.idx)
        adj.scatter_(2, torch.where(self.valid, self.idx, own), True)  # invalid slots hit the diagonal, cleared below
        adj = adj | adj.transpose(1, 2)
        return adj & ~torch.eye(N, dtype=torch.bool, device=adj.device)


def knn(query: torch.Tensor, points: torch.Tensor, k: int, allowed: torch.Tensor | None = None):
    """k nearest ``points`` of each ``query`` point among the allowed pairs.

    query (B,M,3), points (B,N,3), allowed (B,M,N) bool or None -> idx (B,M,k) long, valid (B,M,k) bool.
    Slots beyond the allowed neighbours are marked invalid (their idx is arbitrary but in range).
    """
    k_eff = min(k, points.shape[1])
    d2 = torch.cdist(query, points).square()  # B,M,N
    if allowed is not None:
        d2 = d2.masked_fill(~allowed, INF)
    dist, idx = torch.topk(d2, k_eff, dim=-1, largest=False)  # B,M,k
    valid = torch.isfinite(dist)
    if k_eff < k:  # pad to a fixed width so callers can rely on k
        pad = k - k_eff
        idx = torch.cat([idx, idx[..., :1].expand(*idx.shape[:-1], pad)], -1)
        valid = torch.cat([valid, torch.zeros_like(valid[..., :1]).expand(*valid.shape[:-1], pad)], -1)
    return idx, valid


def group_knn(points: torch.Tensor, groups: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """k nearest neighbours of each point among the *other* points of the same group.

    points (B,N,3), groups (B,N) long -> idx (B,N,k), valid (B,N,k).  Edges never cross groups.
    """
    N = points.shape[1]
    same = groups[:, :, None] == groups[:, None, :]  # B,N,N
    same = same & ~torch.eye(N, dtype=torch.bool, device=points.device)
    return knn(points, points, k, allowed=same)


def build_graph(points: torch.Tensor, groups: torch.Tensor, k: int) -> Graph:
    """Group-restricted kNN graph with symmetrised, self-looped, GCN-normalised edge list."""
    B, N, _ = points.shape
    idx, valid = group_knn(points, groups, k)
    dev = points.device
    offs = (torch.arange(B, device=dev) * N)[:, None, None]  # B,1,1
    dst = (torch.arange(N, device=dev)[None, :, None] + offs).expand_as(idx)[valid]
    src = (idx + offs)[valid]
    M = B * N
    # symmetrise and drop duplicate edges: key = src * M + dst
    keys = torch.unique(torch.cat([src * M + dst, dst * M + src]))
    loops = torch.arange(M, device=dev)
    src = torch.cat([keys // M, loops])
    dst = torch.cat([keys % M, loops])
    deg = torch.zeros(M, device=dev).index_add_(0, dst, torch.ones_like(dst, dtype=torch.float32))
    weight = deg[src].rsqrt() * deg[dst].rsqrt()
    return Graph(idx=idx, valid=valid, src=src, dst=dst, weight=weight, num_nodes=N)


def propagate(x: torch.Tensor, g: Graph) -> torch.Tensor:
    """One step of normalised neighbourhood averaging: (Â x) for x (B,N,C) -> (B,N,C)."""
    B, N, C = x.shape
    flat = x.reshape(B * N, C)
    out = torch.zeros_like(flat).index_add_(0, g.dst, flat[g.src] * g.weight[:, None].to(flat.dtype))
    return out.view(B, N, C)


class GCNConv(torch.nn.Module):
    """h = Â x W + b (graph convolution of Kipf & Welling)."""

    def __init__(self, in_dim: int, out_dim: int):
        super().__init__()
        self.lin = torch.nn.Linear(in_dim, out_dim, bias=False)
        self.bias = torch.nn.Parameter(torch.zeros(out_dim))

    def forward(self, x: torch.Tensor, g: Graph) -> torch.Tensor:  # B,N,in -> B,N,out
        return propagate(self.lin(x), g) + self.bias

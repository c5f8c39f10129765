"""Perception encoder Φ (the paper's ``t_graph_encoder``): GCN over a cluster-restricted kNN graph.

    z = Φ(X, F):  node encoder  GCN 3 -> 96 -> 96 on centred, scaled positions
                  label encoder GCN 32 -> 96 on one-hot cluster labels
                  shared LayerNorm on both, embedding encoder 192 -> 96
The graph connects each point to its k nearest neighbours *of the same label*, so messages never
cross a cut: points on both sides of a separation get different embeddings even when they touch.
The same class with ``num_labels=2`` is the action encoder (``a_graph_encoder``) over cut masks.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from topocut.models.graphs import GCNConv, Graph, build_graph


def centre_points(points: torch.Tensor, scale: float) -> torch.Tensor:
    """Translate each cloud to its centroid and divide by ``scale`` (B,N,3) -> (B,N,3).

    Objects sit anywhere on the board; centring makes Φ translation invariant and the scale keeps
    coordinates O(1) for the 0.15-0.3 sized objects.
    """
    return (points - points.mean(dim=1, keepdim=True)) / scale


def one_hot_labels(labels: torch.Tensor, num_labels: int) -> torch.Tensor:
    """(B,N) long -> (B,N,num_labels) float; negative labels (unassigned) give a zero vector,
    ids >= num_labels are merged into the last class."""
    lab = labels.clamp(0, num_labels - 1)
    return F.one_hot(lab, num_labels).float() * (labels >= 0)[..., None].float()


class TopoEncoder(nn.Module):
    """Φ: forward(points (B,N,3), labels (B,N) long) -> (B,N,hidden) point-wise embeddings."""

    def __init__(self, hidden: int = 96, num_labels: int = 32, k: int = 8, coord_scale: float = 0.1):
        super().__init__()
        self.hidden, self.num_labels, self.k, self.coord_scale = hidden, num_labels, k, coord_scale
        self.out_dim = hidden
        self.node1 = GCNConv(3, hidden)  # node encoder 3 -> 96 -> 96
        self.node2 = GCNConv(hidden, hidden)
        self.label = GCNConv(num_labels, hidden)  # label encoder 32 -> 96
        self.norm = nn.LayerNorm(hidden)  # shared by both branches
        self.embed = nn.Sequential(nn.Linear(2 * hidden, hidden), nn.ReLU(), nn.Linear(hidden, hidden))  # 192 -> 96

    def graph(self, points: torch.Tensor, labels: torch.Tensor) -> Graph:
        return build_graph(points, labels, self.k)

    def forward(self, points: torch.Tensor, labels: torch.Tensor, graph: Graph | None = None) -> torch.Tensor:
        if points.dim() != 3 or points.shape[-1] != 3 or labels.shape != points.shape[:2]:
            raise ValueError(f"TopoEncoder expects points (B,N,3) and labels (B,N); got {tuple(points.shape)} "
                             f"and {tuple(labels.shape)}")
        g = graph if graph is not None else self.graph(points, labels)
        p = centre_points(points, self.coord_scale)  # B,N,3
        node = self.node2(F.relu(self.node1(p, g)), g)  # B,N,H
        lab = self.label(one_hot_labels(labels.long(), self.num_labels), g)  # B,N,H
        return self.embed(torch.cat([self.norm(node), self.norm(lab)], dim=-1))  # B,N,H

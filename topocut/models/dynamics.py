"""Graph-transformer dynamics model F: (topo_t, a_t) -> topo_{t+1} (paper §3.3.1, appendix "Graph Network").

    z_t = Φ_t(X_t, F_t)      topology graph: kNN within a cluster        (B,N,96)
    z_a = Φ_a(X_a, G)        action graph:   kNN within a cut-mask side  (B,M,96)
    L x [ self-attention over z_t   (bias: topology-graph edges, same-cluster pairs)
          cross-attention z_t -> z_a (bias: spatial kNN from topology to action points)
          MLP ]
    h = z + QueryEncoder(X_t)                      3 -> 64 -> 96
    X_{t+1} = X_t + coord_scale * PosHead(h)       residual blocks -> 3
    logits  = FeatHead(h)                          -> 32 cluster logits

Graph structure enters attention as an additive, learned per-head bias on the logits (not a hard
mask), so attention stays global - the paper's "globally refines the features via self-attention" -
while neighbours in the graph are preferred from the first step on.
"""
from __future__ import annotations

import torch
from torch import nn

from topocut.models.config import DynamicsConfig
from topocut.models.encoder import TopoEncoder, centre_points
from topocut.models.graphs import Graph, knn


class ResBlock(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.net = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, dim), nn.ReLU(), nn.Linear(dim, dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.net(x)


def point_head(dim: int, out: int, blocks: int = 2) -> nn.Sequential:
    """Residual blocks and a final Linear whose zero init makes the initial prediction 'no motion'."""
    last = nn.Linear(dim, out)
    nn.init.zeros_(last.weight)
    nn.init.zeros_(last.bias)
    return nn.Sequential(*[ResBlock(dim) for _ in range(blocks)], nn.LayerNorm(dim), last)


class GraphBias(nn.Module):
    """Per-head additive attention bias  sum_r w_{r,h} * R_r[b,i,j]  for boolean relations R_r."""

    def __init__(self, num_relations: int, num_heads: int, init: float = 1.0):
        super().__init__()
        self.w = nn.Parameter(torch.full((num_relations, num_heads), init))

    def forward(self, relations: list[torch.Tensor]) -> torch.Tensor:
        # relations: R x (B,L,S) bool -> (B*H, L, S) float, batch-major as nn.MultiheadAttention wants
        rel = torch.stack(relations, dim=1).to(self.w.dtype)  # B,R,L,S
        bias = torch.einsum("brls,rh->bhls", rel, self.w)  # B,H,L,S
        B, H, L, S = bias.shape
        return bias.reshape(B * H, L, S)


class GraphTransformerLayer(nn.Module):
    """Pre-norm self-attention, cross-attention to the action tokens and an MLP, each residual."""

    def __init__(self, dim: int, heads: int, dropout: float = 0.0):
        super().__init__()
        self.n1, self.n2, self.n2a, self.n3 = (nn.LayerNorm(dim) for _ in range(4))
        self.self_attn = nn.MultiheadAttention(dim, heads, dropout=dropout, batch_first=True)
        self.cross_attn = nn.MultiheadAttention(dim, heads, dropout=dropout, batch_first=True)
        self.mlp = nn.Sequential(nn.Linear(dim, 4 * dim), nn.GELU(), nn.Linear(4 * dim, dim), nn.Dropout(dropout))
        self.self_bias = GraphBias(2, heads)  # topology-graph edge, same cluster
        self.cross_bias = GraphBias(1, heads, init=2.0)  # spatial neighbour in the action cloud

    def forward(self, z: torch.Tensor, za: torch.Tensor, self_rel: list, cross_rel: list) -> torch.Tensor:
        h = self.n1(z)
        z = z + self.self_attn(h, h, h, attn_mask=self.self_bias(self_rel), need_weights=False)[0]
        h, ha = self.n2(z), self.n2a(za)
        z = z + self.cross_attn(h, ha, ha, attn_mask=self.cross_bias(cross_rel), need_weights=False)[0]
        return z + self.mlp(self.n3(z))


class GraphTransformerDynamics(nn.Module):
    """F with the graph encoders Φ_t (``t_graph_encoder``, the reusable perception encoder) and Φ_a."""

    def __init__(self, cfg: DynamicsConfig | None = None):
        super().__init__()
        cfg = (cfg or DynamicsConfig()).validate()
        self.cfg = cfg
        H = cfg.hidden
        self.t_graph_encoder = TopoEncoder(H, cfg.num_labels, cfg.k, cfg.coord_scale)
        self.a_graph_encoder = TopoEncoder(H, 2, cfg.k, cfg.coord_scale)
        self.layers = nn.ModuleList(GraphTransformerLayer(H, cfg.num_heads, cfg.dropout) for _ in range(cfg.num_layers))
        self.query_encoder = nn.Sequential(nn.Linear(3, cfg.query_hidden), nn.ReLU(), nn.Linear(cfg.query_hidden, H))
        self.pos_head = point_head(H, 3)
        self.feat_head = nn.Sequential(nn.LayerNorm(H), nn.Linear(H, H), nn.ReLU(), nn.Linear(H, cfg.num_labels))

    @property
    def encoder(self) -> TopoEncoder:
        return self.t_graph_encoder

    def forward(self, x_t: torch.Tensor, f_t: torch.Tensor, x_a: torch.Tensor, g: torch.Tensor):
        """x_t (B,N,3), f_t (B,N) long, x_a (B,M,3), g (B,M) long cut mask -> (x_t1 (B,N,3), logits (B,N,C))."""
        tg: Graph = self.t_graph_encoder.graph(x_t, f_t)
        ag: Graph = self.a_graph_encoder.graph(x_a, g)
        z = self.t_graph_encoder(x_t, f_t, graph=tg)  # B,N,H
        za = self.a_graph_encoder(x_a, g, graph=ag)  # B,M,H
        same = f_t[:, :, None] == f_t[:, None, :]  # B,N,N
        self_rel = [tg.dense(), same]
        cidx, cvalid = knn(x_t, x_a, self.cfg.cross_k)  # B,N,k
        near = torch.zeros(x_t.shape[0], x_t.shape[1], x_a.shape[1], dtype=torch.bool, device=x_t.device)
        near.scatter_(2, cidx, cvalid)  # all slots valid here: no group restriction
        for layer in self.layers:
            z = layer(z, za, self_rel, [near])
        h = z + self.query_encoder(centre_points(x_t, self.cfg.coord_scale))
        x_t1 = x_t + self.cfg.coord_scale * self.pos_head(h)  # residual: predicted motion
        return x_t1, self.feat_head(h)

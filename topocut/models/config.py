"""Hyperparameters of the dynamics-informed perception model F (Hydra group ``model``; docs/perception.md).

Plain-typed dataclass so Hydra can register it as a structured-config schema.  Sizes follow the
paper's appendix "Graph Network Architecture" / "PointNet-Based Perception Model Architecture" and
Table 2 (final model: graph-based, sorted, Gaussian noise, 256 points).
"""
from __future__ import annotations

from dataclasses import dataclass, field

MODELS = ("graph_transformer", "pointnet")


@dataclass
class DynamicsConfig:
    model: str = "graph_transformer"  # graph_transformer | pointnet (Table 2 comparison)
    # -- inputs (TransitionDataset) ------------------------------------------
    num_points: int = 256  # FPS-downsampled points per cloud
    sort: bool = True  # order points along x after sampling
    noise: bool = True  # Gaussian jitter of the input positions while training
    noise_std: float = 0.002  # scene units (objects are 0.15-0.3 across)
    num_labels: int = 32  # one-hot width of cluster labels (ids >= this are merged into the last)
    coord_scale: float = 0.1  # positions are centred and divided by this before entering the networks
    # -- graph transformer ----------------------------------------------------
    hidden: int = 96  # width of Φ and of the transformer
    k: int = 8  # kNN within a cluster (topology graph) / within a mask side (action graph)
    cross_k: int = 8  # spatial kNN from topology to action points (cross-attention bias)
    num_layers: int = 4
    num_heads: int = 4
    query_hidden: int = 64  # query point encoder 3 -> 64 -> hidden
    dropout: float = 0.0
    # -- pointnet alternative -------------------------------------------------
    pointnet_dims: list[int] = field(default_factory=lambda: [96, 192, 384])  # per set-abstraction block
    pointnet_ratio: float = 0.25  # centroids kept by each block
    pointnet_k: int = 16  # neighbours grouped per centroid
    # -- loss -----------------------------------------------------------------
    lambda_pos: float = 1.0
    lambda_topo: float = 1.0
    w_chamfer: float = 1.0
    w_emd: float = 1.0
    w_hausdorff: float = 1.0
    pos_scale: float = 0.1  # point-set distances are measured in units of this length (O(1) losses)
    emd_method: str = "auto"  # exact (scipy, host) | auction (device, <= (1 + emd_tol) x exact) | auto (auction on cuda)
    emd_tol: float = 0.01  # relative error bound of the auction EMD (models/point_losses.py)
    # the auction's round budget, 0 = none: an item unfinished after it is solved exactly on the host (the bound holds
    # either way).  On the demonstrations' clouds the median item takes 8 rounds, 6.5% more than 16, and those take
    # a batch to ~1,200 (docs/perception.md, "The auction's rounds on real data")
    emd_rounds: int = 32
    # -- optimisation ---------------------------------------------------------
    lr: float = 1e-3
    weight_decay: float = 1e-4
    warmup_steps: int = 50
    min_lr_ratio: float = 0.05  # cosine decays to lr * this

    def validate(self) -> DynamicsConfig:
        if self.model not in MODELS:
            raise ValueError(f"model.model={self.model!r} is not valid; choose one of {', '.join(MODELS)}")
        for name in ("num_points", "num_labels", "hidden", "k", "cross_k", "num_layers", "num_heads", "query_hidden",
                     "pointnet_k"):
            if getattr(self, name) < 1:
                raise ValueError(f"model.{name}={getattr(self, name)} must be >= 1")
        if self.hidden % self.num_heads:
            raise ValueError(f"model.hidden={self.hidden} must be divisible by model.num_heads={self.num_heads}")
        if not 0.0 < self.pointnet_ratio <= 1.0:
            raise ValueError(f"model.pointnet_ratio={self.pointnet_ratio} must lie in (0, 1]")
        if not self.pointnet_dims:
            raise ValueError("model.pointnet_dims must list at least one block width")
        bad = [d for d in self.pointnet_dims if d % self.num_heads]
        if bad:
            raise ValueError(f"model.pointnet_dims: width {bad[0]} is not divisible by model.num_heads={self.num_heads}")
        if self.emd_method not in ("auto", "exact", "auction"):
            raise ValueError(f"model.emd_method={self.emd_method!r} is not valid; choose one of auto, exact, auction")
        if self.emd_rounds < 0:
            raise ValueError(f"model.emd_rounds={self.emd_rounds} must be >= 0 (0: no budget)")
        if not self.emd_tol > 0:
            raise ValueError(f"model.emd_tol={self.emd_tol} must be > 0 (a relative error bound)")
        for name in ("coord_scale", "pos_scale"):  # lengths that divide positions / point-set distances
            if not getattr(self, name) > 0:
                raise ValueError(f"model.{name}={getattr(self, name)} must be > 0 (a length in scene units)")
        for name in ("noise_std", "lr"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"model.{name}={getattr(self, name)} must be >= 0")
        return self

"""Dynamics-informed perception: the topology dynamics model F and its encoder Φ (docs/perception.md).

Imports are lazy so that ``topocut.models.config`` (used by the Hydra schema) does not pull in torch.
"""
from __future__ import annotations

from topocut.utils.lazy import lazy_exports

_EXPORTS = {
    "DynamicsConfig": "topocut.models.config",
    "MODELS": "topocut.models.config",
    "TopoEncoder": "topocut.models.encoder",
    "GraphTransformerDynamics": "topocut.models.dynamics",
    "PointNetDynamics": "topocut.models.pointnet",
    "PointNetEncoder": "topocut.models.pointnet",
    "build_model": "topocut.models.pointnet",
    "build_graph": "topocut.models.graphs",
    "group_knn": "topocut.models.graphs",
    "hungarian_cluster_loss": "topocut.models.losses",
    "cluster_accuracy": "topocut.models.losses",
    "dynamics_loss": "topocut.models.losses",
    "DynamicsModule": "topocut.models.module",
    "load_dynamics": "topocut.models.module",
    "load_encoder": "topocut.models.module",
    "TransitionDataset": "topocut.models.datamodule",
    "EpisodeDataModule": "topocut.models.datamodule",
}

__all__ = list(_EXPORTS)
__getattr__ = lazy_exports(__name__, _EXPORTS)

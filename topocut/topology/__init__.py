"""Topology discovery: which particles form which piece after a cut (docs/topology.md).

Importing this package loads numpy/scipy/trimesh only; Warp is imported when
``discover`` first runs.
"""
from topocut.topology.config import TopologyConfig
from topocut.topology.discover import TopologyResult, discover
from topocut.topology.tracking import match_labels

__all__ = ["TopologyConfig", "TopologyResult", "discover", "match_labels"]

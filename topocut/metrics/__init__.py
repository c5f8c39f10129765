"""Point-set metrics and sampling (numpy; torch only when given torch tensors).

``fps`` / ``fps_torch`` / ``fps_clouds``: farthest point sampling; ``chamfer``, ``hausdorff``,
``emd``: distances between point sets (docs/reward.md, topocut/metrics/pointsets.py).
"""
from topocut.metrics.pointsets import MAX_EXACT_EMD, chamfer, emd, hausdorff
from topocut.metrics.sampling import fps, fps_clouds, fps_torch, valid_rows

__all__ = ["fps", "fps_clouds", "fps_torch", "valid_rows", "chamfer", "hausdorff", "emd", "MAX_EXACT_EMD"]

"""Pose-diffusion baselines of Table 1: DP3 and 3D Diffuser Actor (docs/evaluation.md).

Both predict one knife pose per step by DDPM and act through ``PosePolicy``.  Exports are lazy so that
importing the package does not import torch.
"""
from __future__ import annotations

from topocut.utils.lazy import lazy_exports

_EXPORTS = {
    "PoseDiffusionModule": "module", "PosePolicy": "module", "PoseStepDataset": "module", "GaussianDiffusion": "module",
    "action_stats": "module", "load_pose_policy": "module", "encode_action": "module", "decode_action": "module",
    "prepare_inputs": "module", "DP3Net": "dp3", "DP3Encoder": "dp3", "ConditionalUnet1D": "dp3",
    "DiffuserActorNet": "diffuser_actor", "RelativeAttention": "diffuser_actor", "Rotary3D": "diffuser_actor",
}
__all__ = list(_EXPORTS)
__getattr__ = lazy_exports(__name__, {name: "." + module for name, module in _EXPORTS.items()})

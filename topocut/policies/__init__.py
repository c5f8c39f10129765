"""Policies: the Policy protocol and PDDP, the particle-based score-entropy discrete diffusion policy.

Torch-free names (Policy, configs, plane recovery) import eagerly; the torch
modules load on first use so planners and the simulator stay light.
"""
from topocut.policies.base import OBS_KEYS, Policy, check_obs, history_from_actions, make_obs
from topocut.policies.config import PDDPConfig, PolicyTrainConfig, SamplerConfig
from topocut.policies.plane import action_from_mask, fit_plane
from topocut.utils.lazy import lazy_exports

_LAZY = {
    "PDDPModule": "topocut.policies.module", "PDDPPolicy": "topocut.policies.deploy",
    "PolicyDataset": "topocut.policies.dataset", "PDDPNet": "topocut.policies.pddp",
    "build_encoder": "topocut.policies.encoders",
}

__all__ = ["OBS_KEYS", "Policy", "check_obs", "history_from_actions", "make_obs", "PDDPConfig",
           "PolicyTrainConfig", "SamplerConfig", "action_from_mask", "fit_plane", *_LAZY]
__getattr__ = lazy_exports(__name__, _LAZY)

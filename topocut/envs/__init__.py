"""Gymnasium environments over the cutting simulator (docs/gym.md)."""
from topocut.envs.vector import CuttingEnvGym, CuttingVectorEnv

__all__ = ["CuttingVectorEnv", "CuttingEnvGym"]

"""Gymnasium environments over the cutting simulator (docs/gym.md).  Importing this registers ``TopoCut/Slice-v0``,
``TopoCut/Stick-v0`` and ``TopoCut/Dice-v0`` (``gymnasium.make`` / ``gymnasium.make_vec``)."""
from topocut.envs.vector import (
    REGISTERED,
    CuttingEnvGym,
    CuttingVectorEnv,
    make_env,
    make_vector_env,
    protocol_task_config,
    register_envs,
)

register_envs()

__all__ = ["CuttingVectorEnv", "CuttingEnvGym", "REGISTERED", "make_env", "make_vector_env", "protocol_task_config",
           "register_envs"]

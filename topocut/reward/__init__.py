"""Pose-invariant spectral reward (paper §3.2; docs/reward.md).

``spectral_distance(x, y, cfg)``, ``spectral_reward(fragments, goal_fragments, cfg) -> RewardResult``,
``spectral_rewards(fragment_sets, goal_fragments, cfg)`` (one result per set, descriptors batched),
``spectral_descriptors(batch (B,n,3)) -> (eigvals (B,K), signature (B,S))`` (torch).
Pure numpy/scipy at import time; torch is imported only by the batched path.
"""
from topocut.reward.config import RewardConfig
from topocut.reward.matching import (
    RewardResult,
    distance_matrices,
    distance_matrix,
    match,
    piecewise_reward,
    reward_from_distances,
    spectral_reward,
    spectral_rewards,
)
from topocut.reward.spectral import descriptor, spectral_descriptors, spectral_distance

__all__ = ["RewardConfig", "RewardResult", "spectral_distance", "spectral_reward", "spectral_rewards",
           "spectral_descriptors", "descriptor", "distance_matrix", "distance_matrices", "match", "piecewise_reward",
           "reward_from_distances"]

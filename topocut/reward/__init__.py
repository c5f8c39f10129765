"""Pose-invariant spectral reward (paper §3.2; docs/reward.md).

``piece_distance(x, y, cfg)`` (d_spec + d_size: what R sees), ``spectral_distance(x, y, cfg)`` (the scale-free
shape term alone), ``spectral_reward(fragments, goal_fragments, cfg) -> RewardResult``,
``spectral_rewards(fragment_sets, goal_fragments, cfg)`` (one result per set, descriptors batched),
``spectral_descriptors(batch (B,n,3)) -> (eigvals (B,K), signature (B,S))`` (torch); ``planar_misfit`` and
``handedness`` (a stroke on the board against its letter, up to a yaw: topocut.reward.planar).
Pure numpy/scipy at import time; torch is imported only by the batched path.
"""
from topocut.reward.config import RewardConfig
from topocut.reward.distance import (
    distance_matrices,
    distance_matrix,
    distances_and_volumes,
    piece_distance,
    piecewise_reward,
)
from topocut.reward.matching import (
    RewardResult,
    assign,
    match,
    reward_from_distances,
    spectral_reward,
    spectral_rewards,
)
from topocut.reward.planar import handedness, planar_misfit
from topocut.reward.size import size_descriptor, size_distance
from topocut.reward.spectral import descriptor, spectral_descriptors, spectral_distance

__all__ = ["RewardConfig", "RewardResult", "spectral_distance", "spectral_reward", "spectral_rewards",
           "spectral_descriptors", "descriptor", "distance_matrix", "distance_matrices", "match", "piecewise_reward",
           "reward_from_distances", "distances_and_volumes", "piece_distance", "assign", "size_descriptor", "size_distance",
           "planar_misfit", "handedness"]

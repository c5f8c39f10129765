"""Every seed rule of an episode, in one place.

Two episode-seed rules, on purpose: the demonstrations (stage=mppi) number their episodes e = 0, 1, ... within
one run seed, while evaluation derives an episode's seed from what it is (task, object, index) so that every
policy and every evaluation config sees the same episode for the same cell whatever else is evaluated.  Both
rules stay as they are: datasets (their episode keys) and the evaluation tables depend on their numbers.
"""
from __future__ import annotations

import zlib

_MOD = 2**31 - 1  # Taichi's random_seed is an int32


def mix_seed(seed: int, episode_seed: int | None) -> int:
    """A policy's own seed combined with an episode's (stable across processes)."""
    return int(seed) if episode_seed is None else (int(seed) * 1_000_003 + int(episode_seed)) % _MOD


def demo_episode_seed(run_seed: int, e: int) -> int:
    """Demonstration episode e's seed (stage=mppi): distinct for every (run seed, episode) pair in range
    (run_seed * 1000 + e was not: seed 0 episode 1000 = seed 1 episode 0); ``mix_seed(run_seed, e)``."""
    return mix_seed(run_seed, e)


def eval_episode_seed(base_seed: int, task: str, obj: str, episode: int) -> int:
    """Evaluation episode (task, object, index)'s seed: stable across processes and Python versions (unlike hash())."""
    return int((base_seed * 1_000_003 + zlib.crc32(f"{task}|{obj}|{episode}".encode())) % _MOD)


def step_seed(episode_seed: int, cut: int) -> int:
    """Seed of the observation before cut ``cut`` (0-based) of an episode."""
    return (int(episode_seed) * 7919 + int(cut) + 1) % _MOD

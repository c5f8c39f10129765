"""The episode core: one episode loop for demonstrations, evaluation, teleop replay, renders and the gym env.

- ``records``: ``Episode``, ``Score``, ``EpisodeOutcome`` / ``EpisodeLog``, the pose history (HISTORY_LEN,
  ``history_len_of``), ``reads_points`` (whether a policy reads the observed points), ``make_record`` (one dataset record);
- ``seeds``: the demonstrations' and evaluation's episode seeds, the observation seeds, ``mix_seed``;
- ``scene``: what the core reads from a simulator, and its divergence error;
- ``scoring``: ``make_scoring`` (the one Scoring builder), ``Scorer`` (one goal: MPPI's rollouts, teleop),
  ``fragments``, ``piece_agreement``;
- ``engine``: ``EpisodeBatch`` (B episodes advanced one cut at a time), ``reset_policy``;
- ``run``: ``run_episodes`` and ``run_episode`` (one demonstration).

MPPI's rollouts (topocut.planning.rollout) build on this core; it imports nothing from them.
"""
from topocut.episode.engine import EpisodeBatch, reset_policy
from topocut.episode.records import (
    HISTORY_LEN,
    Episode,
    EpisodeLog,
    EpisodeOutcome,
    Score,
    history_len_of,
    make_record,
    new_history,
    reads_points,
)
from topocut.episode.run import run_episode, run_episodes
from topocut.episode.scene import env_board_z, env_spacing, simulation_diverged_error, topology_device
from topocut.episode.scoring import Scorer, Scoring, discover_labels, fragments, make_scoring, piece_agreement
from topocut.episode.seeds import demo_episode_seed, eval_episode_seed, mix_seed, step_seed

__all__ = ["EpisodeBatch", "reset_policy", "HISTORY_LEN", "Episode", "EpisodeLog", "EpisodeOutcome", "Score",
           "history_len_of", "make_record", "new_history", "reads_points", "run_episode", "run_episodes", "env_board_z",
           "env_spacing", "simulation_diverged_error", "topology_device", "Scorer", "Scoring", "discover_labels",
           "fragments", "make_scoring", "piece_agreement", "demo_episode_seed", "eval_episode_seed", "mix_seed",
           "step_seed"]

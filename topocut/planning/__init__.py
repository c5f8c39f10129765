"""Planners and demonstration sources: MPPI, the goal-planes and heuristic policies, teleoperation (the episode runner,
``run_episode``, and ``Scorer`` are the episode core's, topocut.episode, re-exported here).

Pure numpy at import time; the simulator, topology and reward modules are
imported when a rollout or an episode actually runs.
"""
from topocut.episode import Scorer, run_episode
from topocut.planning.config import MPPIConfig
from topocut.planning.heuristic import GoalPlanesPolicy, HeuristicPolicy
from topocut.planning.mppi import MPPI, MPPIPolicy, mppi_weights, shift
from topocut.planning.rollout import make_sim_rollout, sim_rollout_factory

__all__ = ["MPPIConfig", "MPPI", "MPPIPolicy", "GoalPlanesPolicy", "HeuristicPolicy", "mppi_weights", "shift",
           "Scorer", "make_sim_rollout", "sim_rollout_factory", "run_episode"]

"""The scripted policies' builders: what ``registry.build`` calls for a spec whose ``builder`` names one.

Each takes a ``ScriptedSetup`` (what stage=eval has at hand when it builds its policies) and returns a Policy.
A new scripted policy is a function here (or in any importable module) and a ``PolicySpec`` naming it.
Imports happen inside the builders: the registry stays torch- and taichi-free at import.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field


@dataclass
class ScriptedSetup:
    """What a scripted policy may be built from: the evaluation's simulator and its config, the planner, reward
    and topology configs, the task configs of the evaluated tasks and the run's seed."""
    env: object = None
    sim: object = None
    planner: object = None
    reward: object = None
    topology: object = None
    task_cfgs: dict = field(default_factory=dict)
    seed: int = 0

    @property
    def board_z(self) -> float:
        return float(getattr(self.sim, "board_z", 0.05))


def oracle(setup: ScriptedSetup):
    """The goal's own steps at the episode's true pose, each plane carried with its piece (Table 1's reference)."""
    from topocut.planning.oracle import OraclePolicy

    return OraclePolicy(board_z=setup.board_z)


def heuristic(setup: ScriptedSetup):
    """The task's planes for the object's nominal pose, open loop (Table 1's "Heuristic")."""
    from topocut.planning.heuristic import HeuristicPolicy

    return HeuristicPolicy(setup.task_cfgs, spacing=setup.sim.spacing, board_z=setup.board_z)


def mppi(setup: ScriptedSetup):
    """MPPI over knife planes, its rollouts in the evaluation's own simulator (the demonstrator)."""
    from topocut.planning import MPPIConfig, MPPIPolicy, sim_rollout_factory
    from topocut.tasks import get_task

    planner = setup.planner if setup.planner is not None else MPPIConfig()
    push = {task: bool(t.push) for task, t in setup.task_cfgs.items()}  # rollouts push where the episode does
    success = {task: functools.partial(get_task(task).success, cfg=t) for task, t in setup.task_cfgs.items()}
    factory = sim_rollout_factory(setup.env, setup.reward, setup.topology, board_z=setup.board_z, push=push,
                                  push_last=planner.push_last, success=success)
    return MPPIPolicy(planner, factory, seed=setup.seed)

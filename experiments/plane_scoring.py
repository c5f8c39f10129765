"""One cut of the pyramid task, scored by simulation (docs/tasks.md): the pyramid experiments' scene, the goal's
plane turned or moved off it, and a batched scorer of cut planes (simulate, discover the pieces, spectral reward
against the corner tetrahedron).  experiments/pyramid_mppi.py plans with it; experiments/reference_check.py
scores the goal's own plane against wrong ones with it."""
from __future__ import annotations

import numpy as np

from topocut.reward import distances_and_volumes, reward_from_distances
from topocut.sim.action import KnifeAction


def perturbed_plane(ideal: KnifeAction, pivot, offset: float, dyaw: float, dtilt: float,
                    board_z: float) -> KnifeAction:
    """The ideal plane turned by (dyaw, dtilt) about ``pivot`` (a point near the goal piece), then moved
    ``offset`` along the ideal normal (< 0: into the object, a bigger corner)."""
    p = np.asarray(pivot, float)
    p = p - ((p - ideal.plane_point(board_z)) @ ideal.normal) * ideal.normal  # onto the ideal plane
    turned = KnifeAction(0.0, 0.0, ideal.yaw + dyaw, ideal.tilt + dtilt)
    return KnifeAction.from_plane(turned.normal, p + offset * ideal.normal, board_z)


class PlaneScorer:
    """Batched one-cut rollouts from one state: action vectors (K,4) -> fragments, rewards (two RewardConfigs)."""

    def __init__(self, env, state: dict, goal, reward_cfg, cost_cfg, topo_cfg):
        from topocut.planning.rollout import Scorer, simulation_diverged_error, topology_device

        self.env, self.state, self.goal = env, state, goal
        self.scorer = Scorer(goal, reward_cfg, topo_cfg, device=topology_device(env))
        self.cost_cfg = cost_cfg
        self.diverged = simulation_diverged_error()
        self.log: list[dict] = []

    def run(self, actions: np.ndarray) -> list[dict]:
        env, B = self.env, self.env.batch_size
        out = []
        for c0 in range(0, len(actions), B):
            chunk = [KnifeAction.from_vector(a) for a in actions[c0:c0 + B]]
            n = len(chunk)
            env.set_state(self.state, b=None)
            try:
                env.cut(chunk + [chunk[-1]] * (B - n))
            except self.diverged:  # as in make_sim_rollout: the chunk gets no weight, the search goes on
                env.set_state(self.state, b=None)
                x0 = env.state().x[0]
                out += [{"action": a.to_vector(), "x": x0, "labels": np.zeros(len(x0), np.int32), "reward": 0.0,
                         "cost_reward": -np.inf} for a in chunk]
                continue
            st = env.state()
            xs = [st.x[b].copy() for b in range(n)]
            labs = [self.scorer.labels(st.x[b], st.damage[b], st.sweeps[b]) for b in range(n)]
            # one distance matrix per scene, scored under both reward configs (they differ only in R(d))
            sets = [self.scorer.fragments(x, lab) for x, lab in zip(xs, labs)]
            Ds, vols, gvols = distances_and_volumes(sets, list(self.goal.fragments), self.scorer.reward_cfg)
            G = len(self.goal.fragments)
            for b in range(n):
                out.append({"action": chunk[b].to_vector(), "x": xs[b], "labels": labs[b],
                            "reward": reward_from_distances(Ds[b], G, self.scorer.reward_cfg, vols[b], gvols).total,
                            "cost_reward": reward_from_distances(Ds[b], G, self.cost_cfg, vols[b], gvols).total})
        return out

    def rollout(self, seqs: np.ndarray) -> np.ndarray:
        """MPPI cost (K,1,4) -> (K,): minus the tail-softened spectral reward."""
        res = self.run(np.asarray(seqs)[:, 0])
        self.log.append({"rewards": [r["reward"] for r in res], "cost_rewards": [r["cost_reward"] for r in res],
                         "actions": [r["action"].tolist() for r in res]})
        return -np.array([r["cost_reward"] for r in res])


def pyramid_scene(n_grid: int, batch: int, size: float = 0.1, device: str = "cpu", seed: int = 0):
    """(env of ``batch`` scenes holding the cube at the nominal pose, its pyramid goal of leg ``size``): the
    setting of the pyramid experiments; on the CPU Taichi runs one thread, so a re-run cut is bit-identical."""
    from topocut.sim import CuttingEnv, SimConfig, init_taichi
    from topocut.sim.objects import ObjectPose
    from topocut.tasks import make_goal, task_config

    init_taichi(device, cpu_threads=1 if device == "cpu" else None)
    sim = SimConfig(n_grid=n_grid, batch_size=batch, arch=device)
    pose = ObjectPose()
    goal = make_goal(task_config("pyramid", size=size, max_cuts=1), "cube", pose, spacing=sim.spacing,
                     board_z=sim.board_z)
    env = CuttingEnv(sim, batch_size=batch)
    env.reset("cube", pose, seed=seed)
    return env, goal


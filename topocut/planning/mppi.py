"""Model Predictive Path Integral control over knife-cut sequences (paper appendix "MPPI for Data Generation").

An action is one cut, the knife start pose vector a = [x, y, yaw, tilt]
(KnifeAction.to_vector).  MPPI keeps a mean sequence U (H,4) and refines it:

    eps_k ~ N(0, Sigma)  (K,H,4), zero in dims that are not sampled (e.g. tilt)
    J_k   = rollout(U + eps_k) + lambda_u * sum_h ||eps_kh||^2_{Sigma^-1}
    w_k   = exp(-(J_k - J_min) / lambda) / sum_j exp(-(J_j - J_min) / lambda)
    U    <- sum_k w_k (U + eps_k)

``rollout`` maps a batch of sequences (K,H,4) to task costs (K,) — in data
generation minus the spectral reward of the fragments the simulator produces
(topocut.planning.rollout.make_sim_rollout); in tests any synthetic function.
A rollout may also return (costs (K,), success (K,) bool): with ``stop_at_success``
the first iteration in which a sequence succeeds is the last (the paper's success
threshold that "terminates MPPI-based trajectory planning").
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from topocut.planning.config import ACTION_DIMS, MPPIConfig
from topocut.sim.action import KnifeAction, executed_action

Rollout = Callable[[np.ndarray], "np.ndarray | tuple[np.ndarray, np.ndarray]"]  # (K,H,4) -> (K,) [, (K,) bool]


def mppi_weights(costs: np.ndarray, temperature: float, normalize: bool = False) -> np.ndarray:
    """Softmin weights (K,) of costs; non-finite costs (diverged rollouts) get weight 0."""
    costs = np.asarray(costs, np.float64)
    finite = np.isfinite(costs)
    w = np.zeros_like(costs)
    if not finite.any():
        return np.full_like(costs, 1.0 / len(costs))
    c = costs[finite] - costs[finite].min()
    if normalize and c.max() > 0:
        c = c / c.max()
    e = np.exp(-c / temperature)  # the minimum has exp(0) = 1, so the sum never underflows
    w[finite] = e / e.sum()
    return w


class MPPI:
    """Sampling-based optimiser of an action sequence (H,4) against a batched rollout cost."""

    def __init__(self, cfg: MPPIConfig | None = None, rollout: Rollout | None = None,
                 rng: np.random.Generator | None = None):
        self.cfg = cfg or MPPIConfig()
        self.cfg.validate()
        if rollout is None:
            raise ValueError("MPPI needs a rollout: a callable mapping action sequences (K,H,4) to costs (K,)")
        self.rollout = rollout
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.sigma = np.asarray(self.cfg.noise_sigma, np.float64)  # 4,
        self.dim_mask = np.array([d in self.cfg.sampled_dims for d in ACTION_DIMS], np.float64)  # 4,

    def clip(self, seq: np.ndarray) -> np.ndarray:
        """Keep board points on the board square and tilt within ±tilt_max; (...,4)."""
        seq = np.array(seq, np.float64)
        lo, hi = self.cfg.xy_bounds
        seq[..., :2] = np.clip(seq[..., :2], lo, hi)
        seq[..., 3] = np.clip(seq[..., 3], -self.cfg.tilt_max, self.cfg.tilt_max)
        return seq

    def sample(self, mean: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Perturbed sequences (K,H,4) around mean (H,4) and their effective perturbations."""
        K, (H, D) = self.cfg.num_samples, mean.shape
        eps = self.rng.standard_normal((K, H, D)) * self.sigma * self.dim_mask  # K,H,4
        if self.cfg.include_mean:
            eps[0] = 0.0
        samples = self.clip(mean[None] + eps)
        return samples, samples - mean[None]  # clipping changes the perturbation actually applied

    def control_cost(self, eps: np.ndarray) -> np.ndarray:
        """lambda_u * sum_h eps^T Sigma^-1 eps over the sampled dims; (K,H,4) -> (K,)."""
        return self.cfg.control_penalty * np.sum((eps * self.dim_mask / self.sigma) ** 2, axis=(1, 2))

    def plan(self, mean) -> tuple[np.ndarray, dict]:
        """Run cfg.iterations refinement iterations from mean (H,4), fewer where a rollout succeeds and
        cfg.stop_at_success; returns (new mean (H,4), info)."""
        mean = self.clip(np.asarray(mean, np.float64))
        if mean.ndim != 2 or mean.shape[1] != len(ACTION_DIMS):
            raise ValueError(f"MPPI mean must have shape (H, {len(ACTION_DIMS)}), got {mean.shape}")
        best_seq, best_cost, history, stopped = mean.copy(), np.inf, [], False
        for _ in range(self.cfg.iterations):
            samples, eps = self.sample(mean)
            out = self.rollout(samples.astype(np.float32))
            task, succeeded = out if isinstance(out, tuple) else (out, None)
            task = np.asarray(task, np.float64).reshape(-1)  # K,
            if task.shape[0] != len(samples):
                raise ValueError(f"rollout returned {task.shape[0]} costs for {len(samples)} sequences")
            costs = task + self.control_cost(eps)
            w = mppi_weights(costs, self.cfg.temperature, self.cfg.normalize_costs)  # K,
            k = int(np.nanargmin(np.where(np.isfinite(costs), costs, np.nan))) if np.isfinite(costs).any() else 0
            if costs[k] < best_cost:
                best_cost, best_seq = float(costs[k]), samples[k].copy()
                keep = getattr(self.rollout, "keep", None)  # a simulator rollout keeps its state after the cut
                if keep is not None:
                    keep(k)
            mean = self.clip(np.einsum("k,khd->hd", w, samples))
            history.append({"costs": costs, "task_costs": task, "weights": w, "best": k})
            if succeeded is not None and self.cfg.stop_at_success:
                if bool(np.any(np.asarray(succeeded, bool).reshape(-1) & np.isfinite(task))):
                    stopped = True
                    break
        info = {"best_sequence": best_seq, "best_cost": best_cost, "iterations": history,
                "num_rollouts": len(history) * self.cfg.num_samples, "stopped_at_success": stopped}
        return mean, info


def shift(mean: np.ndarray, fill: np.ndarray | None = None) -> np.ndarray:
    """Drop the executed first action, append ``fill`` (4,) or repeat the last action; (H,4) -> (H,4)."""
    tail = mean[-1] if fill is None else np.asarray(fill, np.float64)
    return np.concatenate([mean[1:], tail[None]], axis=0)


class MPPIPolicy:
    """The MPPI expert as a Policy (reset(goal), act(obs)): replans from the simulator state in obs.

    ``rollout_factory(obs, goal) -> rollout`` builds the batched cost for the
    current state (topocut.planning.rollout.sim_rollout_factory); the initial
    guess and the horizon fill come from the heuristic's goal planes.
    """

    uses_simulator = True  # its rollouts are the env's scenes: the episode engine runs its episodes one at a time
    observation_fields = ("goal", "sim_state", "particle_labels", "cuts_done")  # the registry's inputs

    def __init__(self, cfg: MPPIConfig | None = None, rollout_factory=None, seed: int = 0, goal=None):
        self.cfg = cfg or MPPIConfig()
        self.cfg.validate()
        if rollout_factory is None:
            raise ValueError("MPPIPolicy needs rollout_factory(obs, goal) -> rollout (K,H,4) -> (K,)")
        self.rollout_factory = rollout_factory
        self.seed = int(seed)
        self.rng = np.random.default_rng(seed)
        self.last_info: dict = {}
        self.simulated_cut = None  # the last act's cut as its best rollout simulated it (SimulatedCut), or None
        if goal is not None:
            self.reset(goal)

    def reset(self, goal, seed: int | None = None) -> None:
        from topocut.planning.heuristic import GoalPlanesPolicy
        from topocut.policies.base import mix_seed

        if seed is not None:  # an episode's samples do not depend on the episodes planned before it
            self.rng = np.random.default_rng(mix_seed(self.seed, seed))
        self.goal = goal
        self.heuristic = GoalPlanesPolicy(goal)
        self.t = 0
        self.iterations_done: list[int] = []  # per executed cut: the iterations planned (fewer: stop_at_success)
        self.mean = self.heuristic.sequence(0, self.cfg.horizon)  # H,4

    def act(self, obs: dict) -> KnifeAction:
        self.simulated_cut = None
        rollout = self.rollout_factory(obs, self.goal)
        mppi = MPPI(self.cfg, rollout, self.rng)
        self.mean, info = mppi.plan(self.mean)
        if self.cfg.execute == "best" and self.cfg.reuse_rollout_cut and hasattr(rollout, "kept"):
            # the best sequence's rollout already made its first cut: the episode restores that state
            # (topocut.episode.simulated) where it is the cut executed below
            self.simulated_cut = rollout.kept()
        first = info["best_sequence"][0] if self.cfg.execute == "best" else self.mean[0]
        if self.cfg.execute == "best":
            self.mean = info["best_sequence"].copy()  # keep planning around the sequence that was executed
        self.last_info = info
        self.iterations_done.append(len(info["iterations"]))
        self.t += 1
        fill = self.heuristic.sequence(self.t + self.cfg.horizon - 1, 1)[0] if self.cfg.shift_fill == "heuristic" else None
        self.mean = shift(self.mean, fill)
        # the rollouts evaluated float32 vectors (quantized as make_sim_rollout runs them): execute exactly
        # that plane, not the float64 sample, which can differ by ~1e-8 (a cut grazing a lattice layer
        # then makes other pieces) or, at yaw = pi/2, by the reversed normal
        return executed_action(KnifeAction.from_vector(np.asarray(first).astype(np.float32)))

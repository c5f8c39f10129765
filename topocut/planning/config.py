"""MPPI planner configuration (Hydra group ``planner``; docs/data.md)."""
from __future__ import annotations

from dataclasses import dataclass, field

ACTION_DIMS = ("x", "y", "yaw", "tilt")  # order of KnifeAction.to_vector()
SHIFT_FILLS = ("heuristic", "repeat")
EXECUTE = ("best", "mean")


@dataclass
class MPPIConfig:
    num_samples: int = 16  # K perturbed action sequences per iteration
    horizon: int = 2  # H cuts per sequence
    iterations: int = 3  # n refinement iterations before each executed cut
    noise_sigma: list[float] = field(default_factory=lambda: [0.01, 0.01, 0.15, 0.1])  # std of x, y, yaw, tilt
    sampled_dims: list[str] = field(default_factory=lambda: ["x", "y", "yaw"])  # tilt frozen unless listed
    temperature: float = 0.1  # lambda of w ∝ exp(-(J - J_min) / lambda)
    normalize_costs: bool = True  # divide J - J_min by the iteration's cost range so lambda is scale-free
    control_penalty: float = 0.01  # lambda_u of lambda_u * sum_h ||eps_h||^2_{Sigma^-1}
    include_mean: bool = True  # sample 0 is the unperturbed mean (never worse than the initial guess)
    execute: str = "best"  # "best": first cut of the lowest-cost evaluated sequence; "mean": of the updated mean
    shift_fill: str = "heuristic"  # horizon shift appends the heuristic's next plane, or repeats the last
    xy_bounds: list[float] = field(default_factory=lambda: [0.0, 1.0])  # board point clipped to this square
    tilt_max: float = 0.6  # |tilt| clipped (rad)
    # a rollout of a pushing task pushes after every cut of its horizon but the last; true: after the last too.
    # That push moves apart what the last cut made, which the reward then scores (docs/data.md, "The rollout's last
    # push"); at 128^3 a push and its settling are two thirds of a cut's substeps
    push_last: bool = False
    # an iteration in which a rollout succeeds (the task's success after the rollout's cuts: every goal piece made
    # and the reward at task.success_threshold) ends the cut's planning, the paper's threshold that "terminates
    # MPPI-based trajectory planning"; the executed cut is still the best evaluated sequence's.  false: always
    # `iterations` (docs/data.md, "Stopping at success")
    stop_at_success: bool = True
    # the executed cut (execute: best) is its best rollout's own first cut: that scene's state after the cut (and its
    # push), kept on the device, is restored instead of simulating the same cut again (docs/data.md, "The executed
    # cut").  Needs num_samples <= the env's batch size (one chunk of rollouts); false: the cut is simulated again
    reuse_rollout_cut: bool = True

    def validate(self) -> None:
        if self.num_samples < 1:
            raise ValueError(f"planner.num_samples must be >= 1, got {self.num_samples}")
        if self.horizon < 1:
            raise ValueError(f"planner.horizon must be >= 1, got {self.horizon}")
        if self.iterations < 1:
            raise ValueError(f"planner.iterations must be >= 1, got {self.iterations}")
        if len(self.noise_sigma) != len(ACTION_DIMS) or min(self.noise_sigma) <= 0:
            raise ValueError(f"planner.noise_sigma must be {len(ACTION_DIMS)} positive stds for "
                             f"{', '.join(ACTION_DIMS)}, got {list(self.noise_sigma)}")
        bad = [d for d in self.sampled_dims if d not in ACTION_DIMS]
        if bad:
            raise ValueError(f"planner.sampled_dims: unknown dim {bad[0]!r}; valid: {', '.join(ACTION_DIMS)}")
        if self.temperature <= 0:
            raise ValueError(f"planner.temperature must be > 0, got {self.temperature}")
        if self.execute not in EXECUTE:
            raise ValueError(f"planner.execute: {self.execute!r}; valid: {', '.join(EXECUTE)}")
        if self.shift_fill not in SHIFT_FILLS:
            raise ValueError(f"planner.shift_fill: {self.shift_fill!r}; valid: {', '.join(SHIFT_FILLS)}")
        if len(self.xy_bounds) != 2 or self.xy_bounds[0] >= self.xy_bounds[1]:
            raise ValueError(f"planner.xy_bounds must be [lo, hi] with lo < hi, got {list(self.xy_bounds)}")

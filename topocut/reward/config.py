"""Spectral reward configuration (docs/reward.md explains every choice)."""
from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class RewardConfig:
    # graph / spectrum (paper appendix: num_point = 512, k = 30)
    num_point: int = 512  # FPS resampling size of every fragment
    knn: int = 30  # neighbours per node of the kNN graph
    num_eig: int = 20  # non-trivial eigenpairs kept (the constant mode is dropped)
    # Gaussian width in scene units; None: sigma_scale x the mean kNN distance of the *goal* pieces
    # (the reference sets the resolution; fragments are graphed with the same sigma, so size is not normalised away)
    sigma: float | None = None
    sigma_scale: float = 1.0
    eig_floor: float = 1e-4  # added before log(eigenvalue) (disconnected graphs have zero eigenvalues)
    # eigenvector term: quantiles of the normalised heat kernel signature at t = c / lambda_K
    hks_times: list[float] = field(default_factory=lambda: [2.0, 4.0, 8.0])
    num_quantiles: int = 16
    alpha: float = 1.0  # weight of the eigenvalue term  mean_k (log lx_k - log ly_k)^2
    beta: float = 1.0  # weight of the eigenvector (HKS distribution) term
    min_points: int = 32  # fragments with fewer points get distance inf (reward 0)
    # piecewise-linear reward R(d) (paper appendix): R_max - gamma d for d <= tau, then slope delta > gamma; clipped at 0
    r_max: float = 1.0
    gamma: float = 1.0
    tau: float = 0.01
    # delta = 10 puts R = 0 at d = 0.11, the distance of a slab to one 1.5x as thick (docs/reward.md#calibration);
    # with 5, a slab twice too thick still earned ~0.5 and a wrong cut could raise the total (Q1)
    delta: float = 10.0
    kappa: float | None = None  # total = kappa * sum_i R(d_i); None: 1 / (number of goal pieces)
    # a matched piece counts as a correct cut (N_C) if d <= this, i.e. R(d) >= 0.59 with the defaults;
    # None: tau (R >= 0.99), which no simulated cut reaches (see docs/reward.md)
    success_distance: float | None = 0.05
    backend: str = "scipy"  # "scipy" (sparse shift-invert eigsh, CPU) or "torch" (batched dense eigh)
    device: str = "cpu"  # torch backend only

    def validate(self) -> RewardConfig:
        if self.delta <= self.gamma:
            raise ValueError(f"reward.delta={self.delta} must exceed reward.gamma={self.gamma} (paper: delta > gamma)")
        if self.backend not in ("scipy", "torch"):
            raise ValueError(f"reward.backend={self.backend!r}; valid: scipy, torch")
        for k in ("num_point", "knn", "num_eig", "num_quantiles", "min_points"):
            if getattr(self, k) < 1:
                raise ValueError(f"reward.{k}={getattr(self, k)} must be >= 1")
        if self.min_points < self.num_eig + 2:
            raise ValueError(f"reward.min_points={self.min_points} must be >= reward.num_eig + 2 = {self.num_eig + 2}")
        if self.sigma is not None and self.sigma <= 0:
            raise ValueError(f"reward.sigma={self.sigma} must be > 0 or None")
        return self

"""Noise schedules sigma(t) on t in [0, 1]: total noise sigma(t) and its rate sigma'(t).

The forward chain at time t is exp(sigma(t) Q) applied to the clean state, so
the schedule only enters through sigma and its derivative (the loss weight and
the Euler step).
"""
from __future__ import annotations

import abc
import math

import torch


class Noise(abc.ABC):
    def __call__(self, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.total_noise(t), self.rate_noise(t)

    @abc.abstractmethod
    def total_noise(self, t: torch.Tensor) -> torch.Tensor:
        """sigma(t)."""

    @abc.abstractmethod
    def rate_noise(self, t: torch.Tensor) -> torch.Tensor:
        """d sigma / dt."""


class LogLinearNoise(Noise):
    """sigma(t) = -log(1 - (1 - eps) t): the move probability 1 - e^-sigma = (1 - eps) t is linear in t.

    With the absorbing graph that is the fraction of masked positions; with the
    2-state uniform graph the flip probability is (1 - eps) t / 2, reaching ~1/2 (pure noise) at t = 1.
    """

    def __init__(self, eps: float = 1e-3):
        if not 0.0 < eps < 1.0:
            raise ValueError(f"noise_eps={eps} must lie in (0, 1)")
        self.eps = float(eps)

    def total_noise(self, t):
        return -torch.log1p(-(1.0 - self.eps) * t)

    def rate_noise(self, t):
        return (1.0 - self.eps) / (1.0 - (1.0 - self.eps) * t)


class GeometricNoise(Noise):
    """sigma(t) = sigma_min^(1-t) sigma_max^t (SEDD's schedule for the uniform graph)."""

    def __init__(self, sigma_min: float = 1e-4, sigma_max: float = 20.0):
        if not 0.0 < sigma_min < sigma_max:
            raise ValueError(f"need 0 < sigma_min < sigma_max, got sigma_min={sigma_min}, sigma_max={sigma_max}")
        self.sigma_min, self.sigma_max = float(sigma_min), float(sigma_max)
        self._log_ratio = math.log(sigma_max / sigma_min)

    def total_noise(self, t):
        return self.sigma_min ** (1.0 - t) * self.sigma_max ** t

    def rate_noise(self, t):
        return self.total_noise(t) * self._log_ratio


NOISES = ("loglinear", "geometric")


def build_noise(name: str, eps: float = 1e-3, sigma_min: float = 1e-4, sigma_max: float = 20.0) -> Noise:
    if name == "loglinear":
        return LogLinearNoise(eps)
    if name == "geometric":
        return GeometricNoise(sigma_min, sigma_max)
    raise ValueError(f"noise={name!r} is not valid; choose one of {', '.join(NOISES)}")

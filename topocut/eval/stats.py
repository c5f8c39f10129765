"""Evaluation statistics: percentile-bootstrap intervals of a mean and of a paired difference (docs/evaluation.md).

The resampling unit is the *episode spec*: one scene (task, object, episode seed) that every policy runs.  A
policy trained with k seeds runs each spec k times; its value on the spec is the mean over those k episodes,
so the k copies of one scene are not counted as k independent draws.  ``paired_difference`` pairs two policies
on the specs both ran (same task, object and episode seed: the same scene) and bootstraps the mean of the
per-spec differences, which removes the scene-to-scene variance both policies share.

Intervals are ``scipy.stats.bootstrap`` percentile intervals with a generator seeded from (seed, a label of what
is estimated), so a report is reproducible and does not depend on the order its cells are computed in.
"""
from __future__ import annotations

import inspect
import math
import zlib
from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

CONFIDENCE = 0.95
RESAMPLES = 10_000
SEED = 0


@dataclass(frozen=True)
class Interval:
    """A mean with its bootstrap interval over ``n`` units (lo/hi NaN when n < 2 or a value is NaN)."""

    mean: float
    lo: float
    hi: float
    n: int

    @property
    def defined(self) -> bool:
        return math.isfinite(self.lo) and math.isfinite(self.hi)

    @property
    def tie(self) -> bool | None:
        """For a difference: the interval contains 0 (the gap is smaller than its uncertainty); None if undefined."""
        return bool(self.lo <= 0.0 <= self.hi) if self.defined else None


NAN_INTERVAL = Interval(math.nan, math.nan, math.nan, 0)


def _rng(seed: int, label: str) -> np.random.Generator:
    return np.random.default_rng([int(seed), zlib.crc32(label.encode())])


def _bootstrap(sample: np.ndarray, confidence: float, n_resamples: int, rng: np.random.Generator):
    from scipy import stats

    # scipy >= 1.15 names the generator `rng` (`random_state` is its deprecated spelling); 1.11-1.14 only know
    # `random_state`
    kw = "rng" if "rng" in inspect.signature(stats.bootstrap).parameters else "random_state"
    res = stats.bootstrap((sample,), np.mean, n_resamples=int(n_resamples), confidence_level=float(confidence),
                          method="percentile", vectorized=True, **{kw: rng})
    return float(res.confidence_interval.low), float(res.confidence_interval.high)


def bootstrap_mean(values: Sequence[float], *, confidence: float = CONFIDENCE, n_resamples: int = RESAMPLES,
                   seed: int = SEED, label: str = "") -> Interval:
    """Mean of ``values`` with its percentile-bootstrap interval.

    Fewer than two values (or any NaN) leave the interval undefined (NaN); identical values give the zero-width
    interval [v, v] (every resample's mean is v).
    """
    v = np.asarray(values, np.float64).ravel()
    if len(v) == 0:
        return NAN_INTERVAL
    mean = float(v.mean())
    if not np.all(np.isfinite(v)):
        return Interval(math.nan, math.nan, math.nan, len(v))
    if len(v) < 2:
        return Interval(mean, math.nan, math.nan, 1)
    if np.all(v == v[0]):
        return Interval(float(v[0]), float(v[0]), float(v[0]), len(v))
    lo, hi = _bootstrap(v, confidence, n_resamples, _rng(seed, label))
    return Interval(mean, lo, hi, len(v))


def paired_difference(a: Mapping[Hashable, float], b: Mapping[Hashable, float], **kw) -> Interval:
    """Mean over the keys both hold of a[key] - b[key], with its bootstrap interval (``bootstrap_mean``'s
    keywords).  Keys are episode specs (``unit_means``): the same scene for both policies."""
    keys = sorted((k for k in a if k in b), key=repr)
    if not keys:
        return NAN_INTERVAL
    return bootstrap_mean([a[k] - b[k] for k in keys], **kw)


def unit_means(items: Sequence[tuple[Hashable, float]]) -> dict[Hashable, float]:
    """{unit: mean of its values} from (unit, value) pairs, e.g. a spec's episodes over training seeds."""
    groups: dict[Hashable, list[float]] = {}
    for unit, value in items:
        groups.setdefault(unit, []).append(float(value))
    return {u: float(np.mean(vs)) for u, vs in groups.items()}


def seed_spread(items: Sequence[tuple[Hashable, float]]) -> float:
    """Sample std (ddof=1) over training seeds of each seed's mean, from (seed, value) pairs; NaN under 2 seeds."""
    means = list(unit_means(items).values())
    return float(np.std(means, ddof=1)) if len(means) >= 2 else math.nan

"""Aggregate scores per policy over every Table-1 cell (issue #51; Agarwal et al. 2021, "Deep RL at the edge of
the statistical precipice"), implemented with numpy/scipy (rliable is not a dependency):

* ``iqm``: the interquartile mean, ``scipy.stats.trim_mean(x, 0.25)`` (rliable's), of R̂ over all a policy's
  episodes, pooled across tasks and splits;
* ``probability_of_improvement``: P(X > Y) per stratum (a cell: task x split), mean over pairs of [x > y] +
  0.5 [x == y] (the Mann-Whitney U over n m), then averaged over the strata both policies ran;
* ``stratified_bootstrap``: their percentile intervals, resampling episodes with replacement within each
  stratum (rliable's ``StratifiedBootstrap``), the generator seeded as ``topocut.eval.stats`` seeds its own;
* ``wilson_interval``: the success rate with its Wilson score interval;
* ``plot_profiles``: the performance profile, the fraction of a policy's episodes with R̂ > tau.

``aggregate_markdown`` writes the "Aggregates" table of results.md from ``topocut.eval.summary.prepare_episodes``'
episode dicts (``policy``, ``task``, ``split``, ``R``, ``R_hat``, ``success``).
"""
from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence

import numpy as np

from topocut.eval import stats

Z95 = 1.96  # the conventional two-sided 95% normal quantile


def iqm(x, axis=None) -> float | np.ndarray:
    """Interquartile mean: the mean of the middle 50% (``scipy.stats.trim_mean(x, 0.25)``, as rliable)."""
    from scipy.stats import trim_mean

    return trim_mean(np.asarray(x, np.float64), 0.25, axis=axis)


def _pairwise(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """S[i, j] = [x_i > y_j] + 0.5 [x_i == y_j]."""
    return (x[:, None] > y[None, :]) + 0.5 * (x[:, None] == y[None, :])


def probability_of_improvement(x: Sequence[Sequence[float]], y: Sequence[Sequence[float]]) -> float:
    """P(X > Y): per stratum k, the mean over all pairs (x in x[k], y in y[k]) of [x > y] + 0.5 [x == y]; the
    mean over the strata.  1 when every x beats every y, 0.5 for identical samples."""
    per = [float(_pairwise(np.asarray(a, np.float64), np.asarray(b, np.float64)).mean()) for a, b in zip(x, y)]
    return float(np.mean(per)) if per else math.nan


def _counts(rng: np.random.Generator, n: int, n_resamples: int) -> np.ndarray:
    """(n_resamples, n) multiplicities of a resample of n items drawn with replacement."""
    idx = rng.integers(0, n, size=(n_resamples, n)) + n * np.arange(n_resamples)[:, None]
    return np.bincount(idx.ravel(), minlength=n_resamples * n).reshape(n_resamples, n)


def stratified_bootstrap(strata: Sequence[Sequence[float]], statistic: str = "iqm", *,
                         others: Sequence[Sequence[float]] | None = None, confidence: float = stats.CONFIDENCE,
                         n_resamples: int = stats.RESAMPLES, seed: int = stats.SEED, label: str = "") -> stats.Interval:
    """A statistic of ``strata`` (one list of episode values per stratum) with its percentile interval: every
    resample redraws each stratum's episodes with replacement (its size kept) and recomputes the statistic.

    ``statistic="iqm"``: the IQM of the pooled values; ``"improvement"``: ``probability_of_improvement(strata,
    others)``, both samples of a stratum redrawn independently.  ``n`` of the Interval counts the episodes (of
    ``strata``).  Empty or NaN input: NaN; every value equal: the zero-width interval (each resample gives it)."""
    strata = [np.asarray(s, np.float64).ravel() for s in strata]
    if statistic == "improvement":
        others = [np.asarray(s, np.float64).ravel() for s in others or []]
        keep = [k for k, (a, b) in enumerate(zip(strata, others)) if len(a) and len(b)]
        strata, others = [strata[k] for k in keep], [others[k] for k in keep]
    elif statistic != "iqm":
        raise ValueError(f"statistic={statistic!r}: choose iqm or improvement")
    strata = [s for s in strata if len(s)] if statistic == "iqm" else strata
    n = sum(len(s) for s in strata)
    values = np.concatenate(strata + (others if statistic == "improvement" else [])) if strata else np.empty(0)
    if n == 0 or not np.all(np.isfinite(values)):
        return stats.Interval(math.nan, math.nan, math.nan, n)
    if statistic == "iqm":
        point = float(iqm(np.concatenate(strata)))
        if np.all(values == values[0]):
            return stats.Interval(float(values[0]), float(values[0]), float(values[0]), n)
    else:
        point = probability_of_improvement(strata, others)
    rng = stats._rng(seed, label)
    if statistic == "iqm":
        boot = iqm(np.concatenate([s[rng.integers(0, len(s), size=(n_resamples, len(s)))] for s in strata], axis=1),
                   axis=1)
    else:  # P_b = cx_b S cy_b^T / (n m) with cx, cy the resamples' multiplicities: no (B, n, m) array
        boot = np.zeros(n_resamples)
        for a, b in zip(strata, others):
            cx, cy = _counts(rng, len(a), n_resamples), _counts(rng, len(b), n_resamples)
            boot += ((cx @ _pairwise(a, b)) * cy).sum(axis=1) / (len(a) * len(b))
        boot /= len(strata)
    alpha = 1.0 - float(confidence)
    lo, hi = np.percentile(boot, [100 * alpha / 2, 100 * (1 - alpha / 2)])
    return stats.Interval(point, float(lo), float(hi), n)


def z_value(confidence: float = stats.CONFIDENCE) -> float:
    """1.96 at 95%, else the normal quantile."""
    from scipy.stats import norm

    return Z95 if confidence == 0.95 else float(norm.ppf(0.5 + confidence / 2))


def wilson_interval(successes: int, n: int, z: float = Z95) -> stats.Interval:
    """The success rate p = successes / n with its Wilson score interval: centre (p + z²/2n) / (1 + z²/n),
    half-width z sqrt(p(1-p)/n + z²/4n²) / (1 + z²/n).  ``mean`` is p itself (the interval is not centred on it)."""
    if n <= 0:
        return stats.NAN_INTERVAL
    p = successes / n
    d = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / d
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return stats.Interval(p, max(0.0, centre - half), min(1.0, centre + half), n)


def _strata(episodes: Sequence[dict], policy: str, key: str) -> dict[tuple, list[float]]:
    out: dict[tuple, list[float]] = {}
    for e in episodes:
        if e["policy"] == policy:
            out.setdefault((e["task"], e["split"]), []).append(float(e[key]))
    return dict(sorted(out.items()))


def policy_aggregates(episodes: Sequence[dict], reference: str, *, confidence: float = stats.CONFIDENCE,
                      n_resamples: int = stats.RESAMPLES, seed: int = stats.SEED) -> dict[str, dict]:
    """{policy: {"iqm", "improvement", "success"}} (Intervals), the reference first, then Table 1's order.
    IQM of R̂ over every episode, strata the cells (task, split); P(improvement) over ``reference`` on raw R (the
    same order as R̂ within a cell, and defined where R̂ is not), averaged over the cells both ran (NaN for the
    reference itself); success with its Wilson interval."""
    boot = dict(confidence=confidence, n_resamples=n_resamples, seed=seed)
    ref = _strata(episodes, reference, "R")
    out = {}
    from topocut.policies import registry

    names = [reference, *registry.display_names()]  # Table 1's row order: the reference first
    order = {p: (names.index(p) if p in names else len(names), p) for p in {e["policy"] for e in episodes}}
    for p in sorted(order, key=order.get):
        r_hat, raw = _strata(episodes, p, "R_hat"), _strata(episodes, p, "R")
        cells = [c for c in raw if c in ref]
        improvement = (stats.NAN_INTERVAL if p == reference or not cells else
                       stratified_bootstrap([raw[c] for c in cells], "improvement", others=[ref[c] for c in cells],
                                            label=f"{p}|P>{reference}", **boot))
        eps = [e for e in episodes if e["policy"] == p]
        out[p] = {"iqm": stratified_bootstrap(list(r_hat.values()), label=f"{p}|IQM", **boot),
                  "improvement": improvement,
                  "success": wilson_interval(sum(bool(e.get("success")) for e in eps), len(eps), z_value(confidence))}
    return out


def _iv(iv: stats.Interval, digits: int = 2) -> str:
    if not math.isfinite(iv.mean):
        return "-"
    return f"{iv.mean:.{digits}f}" + (f" [{iv.lo:.{digits}f}, {iv.hi:.{digits}f}]" if iv.defined else "")


def aggregate_markdown(aggregates: Mapping[str, dict], reference: str, name: Callable[[str], str] = str,
                       title: str = "Aggregates", note: str = "") -> str:
    """policy | IQM R̂ [interval] | P(improvement over the reference) [interval] | success [Wilson] (k/n)."""
    lines = [f"### {title}", note, "",
             f"| Algorithm | IQM R̂ | P(improvement over {name(reference)}) | success |", "|---|---|---|---|"]
    for p, a in aggregates.items():
        s = a["success"]
        success = f"{_iv(s)} ({round(s.mean * s.n)}/{s.n})" if s.n else "-"
        lines.append(f"| {name(p)} | {_iv(a['iqm'])} | {'-' if p == reference else _iv(a['improvement'])} | "
                     f"{success} |")
    return "\n".join(lines) + "\n"


def plot_profiles(episodes: Sequence[dict], path, reference: str | None = None,
                  name: Callable[[str], str] = str, points: int = 201) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The performance profile: per policy, the fraction of its episodes with R̂ > tau for tau in [0, max R̂]
    (every policy's episodes pooled over the cells; NaN R̂ left out), the reference dashed.  Returns the curves
    drawn, {policy: (tau, fraction)}."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scores: dict[str, np.ndarray] = {}
    for e in episodes:
        scores.setdefault(e["policy"], []).append(float(e["R_hat"]))
    scores = {p: v[np.isfinite(v)] for p, v in ((p, np.asarray(v, np.float64)) for p, v in scores.items())}
    scores = {p: v for p, v in scores.items() if len(v)}
    top = max((float(v.max()) for v in scores.values()), default=1.0)
    tau = np.linspace(0.0, top if top > 0 else 1.0, points)
    curves = {p: (tau, (v[None, :] > tau[:, None]).mean(axis=1)) for p, v in scores.items()}
    fig, ax = plt.subplots(figsize=(6, 4))
    for p, (t, f) in curves.items():
        ax.plot(t, f, "--" if p == reference else "-", label=name(p) + (" (reference)" if p == reference else ""))
    ax.set_xlabel("normalised reward threshold τ")
    ax.set_ylabel("fraction of episodes with R̂ > τ")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title("Performance profile (all tasks and splits)", fontsize=10)
    if curves:
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return curves


def markdown(episodes: Sequence[dict], reference: str, name: Callable[[str], str] = str, *,
             confidence: float = stats.CONFIDENCE, n_resamples: int = stats.RESAMPLES, seed: int = stats.SEED) -> str:
    """results.md's "Aggregates" table from the report's prepared episodes (``policy_aggregates``)."""
    note = (f"Per policy over every cell (task x split). IQM: mean of the middle 50% of all its episodes' R̂; "
            f"P(improvement over `{reference}`): P(X > Y) + ½ P(X = Y) per cell on final R, averaged over the cells "
            f"both ran; both with {confidence:.0%} stratified-bootstrap percentile intervals (episodes resampled "
            f"within each cell, {n_resamples} resamples, seed {seed}). Success: the share of successful episodes, "
            f"{confidence:.0%} Wilson score interval (successes/episodes).")
    scores = policy_aggregates(episodes, reference, confidence=confidence, n_resamples=n_resamples, seed=seed)
    return aggregate_markdown(scores, reference, name, note=note)

"""Aggregate scores of the report (issue #51; Agarwal et al. 2021): the IQM of R̂ with its stratified-bootstrap
interval, the probability of improvement over the reference, the success rate's Wilson interval, the performance
profile, and the "Aggregates" table of results.md, against values worked by hand."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from topocut.eval import aggregates
from topocut.eval.report import write_report


def test_iqm_is_the_mean_of_the_middle_half():
    assert aggregates.iqm(np.arange(1, 9)) == pytest.approx((3 + 4 + 5 + 6) / 4)  # 1..8: drop 1, 2 and 7, 8
    assert aggregates.iqm([8, 1, 100, 4, 5, 3, 6, -50]) == pytest.approx((3 + 4 + 5 + 6) / 4)  # outliers trimmed


def test_stratified_bootstrap_of_the_iqm():
    rng = np.random.default_rng(0)
    strata = [rng.uniform(0, 1, 15), rng.uniform(1, 3, 15), rng.uniform(0, 2, 10)]
    iv = aggregates.stratified_bootstrap(strata, n_resamples=2000, label="x")
    assert iv.n == 40 and iv.mean == pytest.approx(aggregates.iqm(np.concatenate(strata)))
    assert iv.lo < iv.mean < iv.hi
    assert aggregates.stratified_bootstrap(strata, n_resamples=2000, label="x") == iv  # seeded
    same = aggregates.stratified_bootstrap([[0.7] * 4, [0.7] * 3], n_resamples=500)
    assert (same.mean, same.lo, same.hi, same.n) == (0.7, 0.7, 0.7, 7)  # degenerate: every resample is 0.7
    assert math.isnan(aggregates.stratified_bootstrap([]).mean)
    assert math.isnan(aggregates.stratified_bootstrap([[1.0, math.nan]]).lo)


def test_probability_of_improvement():
    x, y = [[2.0, 3.0, 4.0], [5.0, 6.0]], [[0.0, 1.0], [1.0, 2.0, 3.0]]
    assert aggregates.probability_of_improvement(x, y) == 1.0  # every x beats every y
    assert aggregates.probability_of_improvement(y, x) == 0.0
    assert aggregates.probability_of_improvement(x, x) == 0.5  # identical samples
    # ties, by hand: stratum 1, x = [1, 2, 3] vs y = [2, 2]: 1 loses twice (0), 2 ties twice (0.5 + 0.5), 3 wins
    # twice (2) -> 3 / 6 = 0.5; stratum 2, x = [1] vs y = [1, 2]: tie, loss -> 0.5 / 2 = 0.25; mean over strata
    p = aggregates.probability_of_improvement([[1.0, 2.0, 3.0], [1.0]], [[2.0, 2.0], [1.0, 2.0]])
    assert p == pytest.approx((0.5 + 0.25) / 2)
    iv = aggregates.stratified_bootstrap([[1.0, 2.0, 3.0, 4.0], [1.0, 5.0]], "improvement",
                                         others=[[2.0, 2.0, 3.5], [1.0, 2.0, 0.5]], n_resamples=2000, label="p")
    assert iv.lo <= iv.mean <= iv.hi and 0.0 <= iv.lo < iv.hi <= 1.0
    top = aggregates.stratified_bootstrap(x, "improvement", others=y, n_resamples=500)
    assert (top.mean, top.lo, top.hi) == (1.0, 1.0, 1.0)  # every resample: x beats y
    tie = aggregates.stratified_bootstrap(x, "improvement", others=x, n_resamples=500)
    assert tie.mean == 0.5 and tie.lo < 0.5 < tie.hi  # resampled independently: not degenerate
    # the pair-count shortcut equals recomputing the statistic on explicit resamples
    rng = np.random.default_rng(5)
    a, b = rng.integers(0, 4, 7).astype(float), rng.integers(0, 4, 5).astype(float)
    cx, cy = aggregates._counts(rng, 7, 3), aggregates._counts(rng, 5, 3)
    for i in range(3):
        fast = (cx[i] @ aggregates._pairwise(a, b) * cy[i]).sum() / 35
        assert fast == pytest.approx(aggregates.probability_of_improvement([np.repeat(a, cx[i])], [np.repeat(b, cy[i])]))


def test_wilson_interval_against_the_formula():
    iv = aggregates.wilson_interval(7, 10)
    p, n, z = 0.7, 10, 1.96
    centre = (p + z**2 / (2 * n)) / (1 + z**2 / n)
    half = z * math.sqrt(p * (1 - p) / n + z**2 / (4 * n**2)) / (1 + z**2 / n)
    assert (iv.mean, iv.n) == (0.7, 10)
    assert iv.lo == pytest.approx(centre - half) and iv.hi == pytest.approx(centre + half)
    assert iv.lo == pytest.approx(0.3968, abs=1e-4) and iv.hi == pytest.approx(0.8922, abs=1e-4)
    zero = aggregates.wilson_interval(0, 10)  # near 0 the interval is not degenerate, unlike p +- z se
    assert zero.lo == 0.0 and zero.hi == pytest.approx(z**2 / n / (1 + z**2 / n))
    assert aggregates.wilson_interval(0, 0).n == 0 and math.isnan(aggregates.wilson_interval(0, 0).mean)


# synthetic episodes: one task, two cells (in, out); the oracle is the reference
REWARDS = {"oracle": {"in": [1.0, 1.0, 1.0, 1.0], "out": [1.0, 1.0, 1.0, 1.0]},
           "dp3": {"in": [0.5, 0.5, 2.0, 0.0], "out": [1.0, 0.5, 0.0, 0.5]},
           "pddp": {"in": [2.0, 2.0, 2.0, 2.0], "out": [2.0, 2.0, 2.0, 2.0]}}
SUCCESS = {"oracle": 8, "dp3": 3, "pddp": 7}  # the first k episodes of each policy succeed


def _write(tmp_path):
    for policy, cells in REWARDS.items():
        k = 0
        for split, rewards in cells.items():
            for i, r in enumerate(rewards):
                e = {"policy": policy, "spec": {"task": "slice", "object": f"obj{split}", "split": split, "episode": i},
                     "final_reward": r, "final_cut_count": 1, "status": "ok", "success": k < SUCCESS[policy]}
                k += 1
                p = tmp_path / "episodes" / policy / f"slice_{split}_{i}.json"
                p.parent.mkdir(parents=True, exist_ok=True)
                p.write_text(json.dumps(e))


def _row(md: str, label: str) -> list[str]:
    line = next(ln for ln in md.splitlines() if ln.startswith(f"| {label} |"))
    return [c.strip() for c in line.strip("|").split("|")][1:]


def test_report_writes_the_aggregates_table_and_the_profile(tmp_path):
    _write(tmp_path)
    out = write_report(tmp_path, "oracle", console=False, n_resamples=500)
    md = out["md"].read_text()
    scores = md[md.index("### Aggregates\n"):md.index("Paper (Table 1)")]
    assert md.index("Aggregates (both splits") < md.index("### Aggregates\n")  # after the existing aggregates
    assert "| Algorithm | IQM R̂ | P(improvement over Oracle (goal planes)) | success |" in scores
    # the oracle's mean R is 1, so R̂ = R.  Oracle: IQM 1, every resample 1; its P(improvement) is "-"
    z = 1.96

    def wilson(k, n):
        p = k / n
        c, h = (p + z**2 / (2 * n)) / (1 + z**2 / n), z * math.sqrt(p * (1 - p) / n + z**2 / (4 * n**2)) / (1 + z**2 / n)
        return f"{p:.2f} [{c - h:.2f}, {c + h:.2f}] ({k}/{n})"

    assert _row(scores, "Oracle (goal planes)") == ["1.00 [1.00, 1.00]", "-", wilson(8, 8)]
    # PDDP: 2 everywhere, above every oracle episode: IQM 2 [2, 2], P = 1 [1, 1]
    assert _row(scores, "PDDP (Ours)") == ["2.00 [2.00, 2.00]", "1.00 [1.00, 1.00]", wilson(7, 8)]
    # DP3: R̂ sorted 0 0 .5 .5 .5 .5 1 2 -> IQM = mean(.5 .5 .5 .5) = 0.5; P over the oracle (all 1): in, .5 .5 2 0
    # -> (0 + 0 + 1 + 0) / 4 = .25; out, 1 .5 0 .5 -> (.5 + 0 + 0 + 0) / 4 = .125; mean .1875 (prints 0.19)
    dp3 = _row(scores, "DP3")
    assert dp3[0].startswith("0.50 [") and dp3[1].startswith("0.19 [") and dp3[2] == wilson(3, 8)
    assert out["profile"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out["profile"].parent == out["png"].parent


def test_performance_profile_curves(tmp_path):
    eps = [{"policy": "a", "R_hat": v} for v in (0.0, 0.5, 1.0, 2.0)] + [{"policy": "b", "R_hat": math.nan}]
    curves = aggregates.plot_profiles(eps, tmp_path / "profile.png", points=5)  # tau = 0, .5, 1, 1.5, 2
    tau, frac = curves["a"]
    assert tau.tolist() == [0.0, 0.5, 1.0, 1.5, 2.0] and frac.tolist() == [0.75, 0.5, 0.25, 0.25, 0.0]
    assert "b" not in curves  # no finite R̂: no curve

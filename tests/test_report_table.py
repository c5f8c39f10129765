"""Table 1's bold and results.png (issue #48): a column's best mean among the compared policies is bolded only
where it is above 0 (a smoke table of learned policies at 0.00 bolded a 0.00 as the winner, the reference row being
left out of the comparison), and the plot draws the reference too (its panels were bars of zero height only)."""
from __future__ import annotations

import math
import re

from topocut.eval.report import best_shown, plot_results, summarize, table1_markdown

IN_SLICE = ("in", "slice")


def _row(markdown: str, label: str) -> list[str]:
    """The cells of the row whose label starts with ``label``."""
    line = next(ln for ln in markdown.splitlines() if ln.startswith(f"| {label}"))
    return [c.strip() for c in line.strip("|").split("|")][1:]


def test_best_shown_is_the_printed_maximum_and_only_above_zero():
    assert best_shown([0.0, 0.0, 0.0]) is None  # nothing beats nothing
    assert best_shown([0.004, 0.001]) is None  # both print 0.00
    assert best_shown([math.nan, None]) is None and best_shown([]) is None
    assert best_shown([0.3, 0.7, math.nan]) == 0.7
    assert best_shown([0.701, 0.699]) == 0.7  # equal as printed: both get the bold


def test_a_column_of_zeros_has_no_bold_and_the_reference_row_is_never_bolded():
    table = {"oracle": {IN_SLICE: (0.62, 2.0)},  # the reference: raw R, higher than any R̂ below
             "heuristic": {IN_SLICE: (0.0, 0.0)}, "dp3": {IN_SLICE: (0.0, 1.0)}, "pddp": {IN_SLICE: (0.0, 0.0)}}
    md = table1_markdown(table, "oracle")
    ref = _row(md, "Oracle")
    assert ref[:2] == ["0.62", "2.00"]  # shown, first, not bold
    assert md.index("| Oracle") < md.index("| Heuristic")
    for label in ("Heuristic", "DP3", "PDDP (Ours)"):
        assert _row(md, label)[0] == "0.00", label  # R̂ all 0.00: no bold anywhere in the column
    assert _row(md, "DP3")[1] == "**1.00**"  # N_C: DP3's 1.00 beats the others' 0.00
    assert _row(md, "Heuristic")[1] == "0.00"
    assert "**0.00" not in md


def test_the_best_positive_mean_is_bolded_with_its_interval_and_ties_share_it():
    table = {"oracle": {IN_SLICE: ((0.9, 0.8, 1.0), (3.0, 2.0, 4.0))},
             "heuristic": {IN_SLICE: ((0.50, 0.4, 0.6), (2.0, 1.0, 3.0))},
             "dp3": {IN_SLICE: ((0.501, 0.3, 0.7), (1.0, 0.0, 2.0))},
             "pddp": {IN_SLICE: ((0.2, 0.1, 0.3), (2.0, 2.0, 2.0))}}
    md = table1_markdown(table, "oracle")
    assert _row(md, "Heuristic")[:2] == ["**0.50 [0.40, 0.60]**", "**2.00 [1.00, 3.00]**"]
    assert _row(md, "DP3")[:2] == ["**0.50 [0.30, 0.70]**", "1.00 [0.00, 2.00]"]  # 0.501 prints as 0.50: a tie
    assert _row(md, "PDDP (Ours)")[:2] == ["0.20 [0.10, 0.30]", "**2.00 [2.00, 2.00]**"]
    assert not re.search(r"\*\*", " ".join(_row(md, "Oracle")))


def _episodes(policy, rewards, cuts):
    return [{"policy": policy, "spec": {"task": "slice", "object": "cube", "split": split, "episode": 0},
             "final_reward": r, "final_cut_count": n, "status": "ok"}
            for split, r, n in zip(("in", "out"), rewards, cuts)]


def test_results_png_draws_the_reference_first(tmp_path):
    """A smoke evaluation's learned policies read 0: the reference's bars keep the panels from being empty."""
    episodes = (_episodes("dp3", (0.0, 0.0), (0, 0)) + _episodes("oracle", (0.5, 0.8), (2, 2))
                + _episodes("pddp", (0.0, 0.0), (0, 0)))
    rows = summarize(episodes, "oracle", "task", n_resamples=50)
    drawn = plot_results(rows, tmp_path / "results.png", reference="oracle")
    assert (tmp_path / "results.png").read_bytes()[:4] == b"\x89PNG"
    assert set(drawn) == {(m, s) for m in ("R_hat", "N_C") for s in ("in", "out")}
    for panel, bars in drawn.items():
        assert list(bars) == ["oracle", "dp3", "pddp"], panel  # the reference first, then the row order
        assert bars["oracle"][0] > 0 and bars["dp3"][0] == 0, (panel, bars)
    # R̂ of the reference is its reward over its own task mean (0.65): 0.5 / 0.65 in, 0.8 / 0.65 out
    assert math.isclose(drawn["R_hat", "in"]["oracle"][0], 0.5 / 0.65)
    assert math.isclose(drawn["R_hat", "out"]["oracle"][0], 0.8 / 0.65)

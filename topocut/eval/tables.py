"""Table 1 as text: the markdown tables of results.md (ours with intervals, the paired differences, the
aggregates, the paper's), the console table and the wandb.Table; all read ``topocut.eval.summary``'s rows."""
from __future__ import annotations

import math

import numpy as np

from topocut.eval.config import table_tasks
from topocut.eval.summary import ALL, CSV_COLUMNS, DIFF_METRICS, DISPLAY

SPLIT_TITLES = {"in": "In-distribution", "out": "Out-of-distribution"}
SPLIT_SHORT = {"in": "ID", "out": "OOD"}

# The paper's Table 1 (topocut-paper.tex, table:cutting_eval): {policy: {(split, task): (R̂, N_C)}}.
# Its R̂ is normalised by human teleoperation per cut mode; the teleop row holds raw R (in-distribution only).
PAPER_TABLE1 = {
    "teleop": {("in", "slice"): (3.3, 4.7), ("in", "stick"): (1.7, 3.5), ("in", "dice"): (3.9, 5.0)},
    "heuristic": {("in", "slice"): (0.82, 2.40), ("in", "stick"): (0.53, 0.90), ("in", "dice"): (0.59, 1.90),
                  ("out", "slice"): (0.88, 2.80), ("out", "stick"): (0.29, 0.40), ("out", "dice"): (0.41, 1.60)},
    "dp3": {("in", "slice"): (0.74, 2.72), ("in", "stick"): (0.50, 0.92), ("in", "dice"): (0.49, 2.29),
            ("out", "slice"): (0.85, 2.90), ("out", "stick"): (0.26, 0.52), ("out", "dice"): (0.42, 1.60)},
    "3dda": {("in", "slice"): (0.83, 2.91), ("in", "stick"): (0.66, 1.00), ("in", "dice"): (0.52, 2.54),
             ("out", "slice"): (0.58, 2.42), ("out", "stick"): (0.31, 0.95), ("out", "dice"): (0.43, 1.40)},
    "pddp_noperc": {("in", "slice"): (0.92, 5.25), ("in", "stick"): (0.56, 0.93), ("in", "dice"): (0.51, 2.58),
                    ("out", "slice"): (0.64, 3.22), ("out", "stick"): (0.25, 0.94), ("out", "dice"): (0.45, 1.51)},
    "pddp": {("in", "slice"): (0.85, 4.83), ("in", "stick"): (0.71, 1.15), ("in", "dice"): (0.57, 2.33),
             ("out", "slice"): (0.82, 4.31), ("out", "stick"): (0.39, 0.84), ("out", "dice"): (0.49, 1.89)},
}
PAPER_REFERENCE = "teleop"


def _fmt(v: float, digits: int = 2) -> str:
    return "-" if v is None or not math.isfinite(v) else f"{v:.{digits}f}"


def _mean(v) -> float:
    return v[0] if isinstance(v, tuple) else v


def format_interval(v, digits: int = 2) -> str:
    """``mean [lo, hi]`` for a (mean, lo, hi) triple (the mean alone when the interval is undefined), or a number."""
    if not isinstance(v, tuple):
        return _fmt(v, digits)
    m, lo, hi = v
    if not (math.isfinite(lo) and math.isfinite(hi)) or not math.isfinite(m):
        return _fmt(m, digits)
    return f"{m:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


def format_difference(m, lo, hi, tie) -> str:
    """``+0.12 [+0.02, +0.20]``; ties (the interval holds 0) start with ≈."""
    if m is None or not math.isfinite(m):
        return "-"
    if tie is None:
        return f"{m:+.2f}"
    return f"{'≈ ' if tie else ''}{m:+.2f} [{lo:+.2f}, {hi:+.2f}]"


def row_label(policy: str, seeds: dict | None) -> str:
    k = (seeds or {}).get(policy, 0)
    return DISPLAY.get(policy, policy) + (f" ({k} seed{'s' if k > 1 else ''})" if k else "")


def _shown(m, digits: int = 2) -> float | None:
    """A mean as the table prints it (None where it prints "-")."""
    return round(float(m), digits) if m is not None and math.isfinite(m) else None


def best_shown(means, digits: int = 2) -> float | None:
    """The value a Table-1 column bolds, among the compared policies' means (the reference row is not compared: it
    holds raw R, not R̂): the highest as printed, and only when it is above 0.  A column where every compared
    policy reads 0.00 has no best, so nothing there is bolded (a bold 0.00 read as a winner); equal printed
    values share the bold."""
    shown = [v for v in (_shown(m, digits) for m in means) if v is not None]
    top = max(shown, default=None)
    return top if top is not None and top > 0 else None


def table1_markdown(table: dict, reference: str | None = None, title: str = "", note: str = "",
                    seeds: dict | None = None) -> str:
    """Paper layout from {policy: {(split, task): (R̂, N_C)}}, each a number or a (mean, lo, hi) triple; the
    reference row first, with raw R; in each column the best mean of the other rows in bold where it is above 0
    (``best_shown``); ``seeds`` {policy: training seeds pooled} labels the rows."""
    cols = [(s, t) for s in ("in", "out") for t in table_tasks(t for cells in table.values() for _, t in cells)]
    head = "| Algorithm | " + " | ".join(f"{SPLIT_SHORT[s]} {t} R̂ | {SPLIT_SHORT[s]} {t} N_C"
                                          for s, t in cols) + " |"
    lines = [f"### {title}" if title else "", note, "(ID: in-distribution / seen objects; OOD: out-of-distribution)",
             "", head, "|---" * (1 + 2 * len(cols)) + "|"]
    others = [p for p in table if p != reference]
    best = {(c, k): best_shown([_mean(table[p][c][k]) for p in others if c in table[p]]) for c in cols
            for k in (0, 1)}
    for p in ([reference] if reference in table else []) + others:
        cells = []
        for c in cols:
            for k in (0, 1):
                v = table[p].get(c, (math.nan, math.nan))[k]
                s = format_interval(v)
                if p != reference and best[c, k] is not None and _shown(_mean(v)) == best[c, k]:
                    s = f"**{s}**"
                cells.append(s)
        name = row_label(p, seeds) + (" (reference, raw R)" if p == reference else "")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def table1_cells(rows: list[dict]) -> list[dict]:
    return [r for r in rows if r["object"] == ALL and r["split"] in SPLIT_SHORT and r["task"] != ALL]


def seed_counts(rows: list[dict]) -> dict:
    return {r["policy"]: max(r["train_seeds"], 0) for r in rows}


def rows_to_table(rows: list[dict], reference: str | None = None) -> dict:
    """{policy: {(split, task): ((R̂ mean, lo, hi), (N_C mean, lo, hi))}} of the Table-1 cells; the reference
    policy's cells hold its raw R."""
    out: dict = {}
    for r in table1_cells(rows):
        m = "R" if r["policy"] == reference else "R_hat"
        out.setdefault(r["policy"], {})[r["split"], r["task"]] = (
            (r[f"{m}_mean"], r[f"{m}_lo"], r[f"{m}_hi"]), (r["N_C_mean"], r["N_C_lo"], r["N_C_hi"]))
    return out


def difference_markdown(rows: list[dict], compare_to: str, title: str = "", note: str = "") -> str:
    """Δ R̂ and Δ N_C against ``compare_to`` per Table-1 cell, paired by scene; ≈ marks a tie."""
    cols = [(s, t) for s in ("in", "out") for t in table_tasks(r["task"] for r in table1_cells(rows))]
    cells = {(r["policy"], r["split"], r["task"]): r for r in table1_cells(rows) if r["policy"] != compare_to}
    policies = list(dict.fromkeys(p for p, _, _ in cells))
    lines = [f"### {title}" if title else "", note, "",
             "| Algorithm | " + " | ".join(f"{SPLIT_SHORT[s]} {t} ΔR̂ | {SPLIT_SHORT[s]} {t} ΔN_C" for s, t in cols)
             + " |", "|---" * (1 + 2 * len(cols)) + "|"]
    seeds = seed_counts(rows)
    for p in policies:
        out = []
        for s, t in cols:
            r = cells.get((p, s, t))
            for m in DIFF_METRICS:
                out.append(format_difference(r[f"d{m}_mean"], r[f"d{m}_lo"], r[f"d{m}_hi"], r[f"d{m}_tie"]) if r else "-")
        lines.append(f"| {row_label(p, seeds)} | " + " | ".join(out) + " |")
    return "\n".join(lines) + "\n"


def aggregate_markdown(rows: list[dict], compare_to: str, title: str = "", note: str = "") -> str:
    """R̂ and Δ R̂ per task over both splits, and over every task."""
    agg = {(r["policy"], r["task"]): r for r in rows if r["object"] == ALL and r["split"] == ALL}
    tasks = [t for t in (*table_tasks(k[1] for k in agg if k[1] != ALL), ALL) if any(k[1] == t for k in agg)]
    policies = list(dict.fromkeys(p for p, _ in agg))
    lines = [f"### {title}" if title else "", note, "",
             "| Algorithm | " + " | ".join(f"{t} R̂ | {t} ΔR̂" for t in tasks) + " |",
             "|---" * (1 + 2 * len(tasks)) + "|"]
    seeds = seed_counts(rows)
    for p in policies:
        out = []
        for t in tasks:
            r = agg.get((p, t))
            if r is None:
                out += ["-", "-"]
                continue
            out.append(format_interval((r["R_hat_mean"], r["R_hat_lo"], r["R_hat_hi"])))
            out.append("-" if p == compare_to else
                       format_difference(r["dR_hat_mean"], r["dR_hat_lo"], r["dR_hat_hi"], r["dR_hat_tie"]))
        lines.append(f"| {row_label(p, seeds)} | " + " | ".join(out) + " |")
    return "\n".join(lines) + "\n"


def print_table(rows: list[dict], title: str = "Evaluation") -> None:
    from rich.table import Table

    from topocut.utils.progress import console

    table = Table(title=title, header_style="bold")
    for c in ("policy", "split", "task", "R̂ [95% CI]", "N_C [95% CI]", "R", "ΔR̂ (paired)", "seeds", "episodes",
              "failures"):
        table.add_column(c, justify="left" if c in ("policy", "split", "task") else "right")
    for r in rows:
        if r["object"] != ALL:
            continue
        table.add_row(DISPLAY.get(r["policy"], r["policy"]), r["split"], r["task"],
                      format_interval((r["R_hat_mean"], r["R_hat_lo"], r["R_hat_hi"])),
                      format_interval((r["N_C_mean"], r["N_C_lo"], r["N_C_hi"])), f"{_fmt(r['R_mean'], 3)}",
                      format_difference(r["dR_hat_mean"], r["dR_hat_lo"], r["dR_hat_hi"], r["dR_hat_tie"]),
                      str(r["train_seeds"] or "-"), str(r["episodes"]), str(r["failures"]))
    console().print(table)


def wandb_data(rows: list[dict], columns=CSV_COLUMNS) -> list[list]:
    """The rows as a wandb.Table's data: one type per column, as wandb.Table demands (its first row fixes a
    column's type; a "" for a missing value and a bool further down failed the whole stage=eval).  A column of
    numbers (bools among them: a tie flag) keeps numbers, a missing one NaN; any other column is text."""
    out = [[r[c] for c in columns] for r in rows]
    for j in range(len(columns)):
        vals = [row[j] for row in out if row[j] is not None]
        numeric = bool(vals) and all(isinstance(v, (bool, int, float, np.integer, np.floating)) for v in vals)
        for row in out:
            v = row[j]
            row[j] = (float("nan") if v is None else float(v)) if numeric else ("" if v is None else str(v))
    return out


def log_wandb_table(rows: list[dict], key: str = "eval/table1") -> bool:
    """A wandb.Table of the rows when a wandb run is active; returns whether it logged."""
    try:
        import wandb
    except ImportError:
        return False
    if wandb.run is None:
        return False
    wandb.log({key: wandb.Table(columns=CSV_COLUMNS, data=wandb_data(rows))})
    return True

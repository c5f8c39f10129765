"""Table 1 from the episode JSONs: results.csv, results.md, results.png, a console table, a wandb.Table.

Metrics (docs/evaluation.md):
  R̂   = final spectral reward / mean final reward of the reference policy on the same task
        (per task, or per task and split with normalize_by="task_split"); mean and std over episodes.
  N_C = RewardResult.cut_count after the last cut: correctly segmented, goal-consistent pieces.
Standard deviations are population std (ddof=0) over the episodes of a cell.
"""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from topocut.eval.config import TASKS

SPLIT_TITLES = {"in": "In-distribution", "out": "Out-of-distribution"}
SPLIT_SHORT = {"in": "ID", "out": "OOD"}
DISPLAY = {"oracle": "Oracle (goal planes)", "heuristic": "Heuristic", "mppi": "MPPI (expert)", "teleop": "Human Tele-Op", "dp3": "DP3",
           "3dda": "3D Diffuser Actor", "pddp_noperc": "Ours w/o Perception", "pddp_graphconv": "Ours (GraphConv)",
           "pddp": "PDDP (Ours)"}
CSV_COLUMNS = ["policy", "task", "split", "episodes", "failures", "R_hat_mean", "R_hat_std", "N_C_mean", "N_C_std",
               "R_mean", "R_std", "reference", "reference_R_mean"]

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


def load_episodes(out_dir) -> list[dict]:
    """Every episodes/<policy>/*.json under out_dir (temp files of an interrupted write are ignored)."""
    return [json.loads(p.read_text()) for p in sorted(Path(out_dir).glob("episodes/*/*.json"))]


def _stats(values) -> tuple[float, float]:
    v = np.asarray(values, np.float64)
    return (float(v.mean()), float(v.std())) if len(v) else (math.nan, math.nan)


def summarize(episodes: list[dict], reference: str = "oracle", normalize_by: str = "task") -> list[dict]:
    """One row per (policy, task, split), in the CSV_COLUMNS layout."""
    if normalize_by not in ("task", "task_split"):
        raise ValueError(f"normalize_by={normalize_by!r} is not valid; choose one of task, task_split")
    cells: dict[tuple, list[dict]] = {}
    for e in episodes:
        cells.setdefault((e["policy"], e["spec"]["task"], e["spec"]["split"]), []).append(e)

    def ref_mean(task, split):
        eps = [e for (p, t, s), es in cells.items() for e in es
               if p == reference and t == task and (normalize_by == "task" or s == split)]
        return _stats([e["final_reward"] for e in eps])[0] if eps else math.nan

    rows = []
    for (policy, task, split), eps in sorted(cells.items(), key=lambda kv: _order(kv[0])):
        r = [e["final_reward"] for e in eps]
        ref = ref_mean(task, split)
        ok_ref = ref > 0 and math.isfinite(ref)
        r_hat = [v / ref for v in r] if ok_ref else [math.nan] * len(r)
        rows.append(dict(zip(CSV_COLUMNS, [
            policy, task, split, len(eps), sum(e["status"] != "ok" for e in eps), *_stats(r_hat),
            *_stats([e["final_cut_count"] for e in eps]), *_stats(r), reference, ref])))
    return rows


def _order(key):
    policy, task, split = key
    names = list(DISPLAY)
    return (names.index(policy) if policy in names else len(names), policy, ("in", "out").index(split),
            TASKS.index(task) if task in TASKS else len(TASKS), task)


def write_csv(rows: list[dict], path) -> None:
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=CSV_COLUMNS)
        w.writeheader()
        w.writerows(rows)


def _fmt(v: float, digits: int = 2) -> str:
    return "-" if v is None or not math.isfinite(v) else f"{v:.{digits}f}"


def table1_markdown(table: dict, reference: str | None = None, title: str = "", note: str = "") -> str:
    """Paper layout from {policy: {(split, task): (R̂, N_C)}}; the reference row shows raw R; best in bold."""
    cols = [(s, t) for s in ("in", "out") for t in TASKS]
    head = "| Algorithm | " + " | ".join(f"{SPLIT_SHORT[s]} {t} R̂ | {SPLIT_SHORT[s]} {t} N_C"
                                          for s, t in cols) + " |"
    lines = [f"### {title}" if title else "", note, "(ID: in-distribution / seen objects; OOD: out-of-distribution)",
             "", head, "|---" * (1 + 2 * len(cols)) + "|"]
    others = [p for p in table if p != reference]
    best = {}
    for c in cols:
        for k in (0, 1):
            vals = [table[p][c][k] for p in others if c in table[p] and math.isfinite(table[p][c][k])]
            best[c, k] = max(vals) if vals else None
    for p in ([reference] if reference in table else []) + others:
        cells = []
        for c in cols:
            for k in (0, 1):
                v = table[p].get(c, (math.nan, math.nan))[k]
                s = _fmt(v)
                if p != reference and best[c, k] is not None and math.isfinite(v) and np.isclose(v, best[c, k]):
                    s = f"**{s}**"
                cells.append(s)
        name = DISPLAY.get(p, p) + (" (reference, raw R)" if p == reference else "")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def rows_to_table(rows: list[dict], reference: str | None = None) -> dict:
    """{policy: {(split, task): (R̂ mean, N_C mean)}}; the reference policy's cells hold its raw R mean."""
    out: dict = {}
    for r in rows:
        rv = r["R_mean"] if r["policy"] == reference else r["R_hat_mean"]
        out.setdefault(r["policy"], {})[r["split"], r["task"]] = (rv, r["N_C_mean"])
    return out


def plot_results(rows: list[dict], path, reference: str | None = None) -> None:
    """Grouped bars: rows R̂ / N_C, columns in / out of distribution, groups = tasks, bars = policies."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    policies = list(dict.fromkeys(r["policy"] for r in rows if r["policy"] != reference))
    tasks = [t for t in TASKS if any(r["task"] == t for r in rows)]
    fig, axes = plt.subplots(2, 2, figsize=(11, 6.5), sharey="row", squeeze=False)
    width = 0.8 / max(len(policies), 1)
    for j, split in enumerate(("in", "out")):
        for i, (metric, label) in enumerate((("R_hat", "normalised reward R̂"), ("N_C", "cut count N_C"))):
            ax = axes[i, j]
            for k, p in enumerate(policies):
                cell = {r["task"]: r for r in rows if r["policy"] == p and r["split"] == split}
                mean = [cell[t][f"{metric}_mean"] if t in cell else np.nan for t in tasks]
                std = [cell[t][f"{metric}_std"] if t in cell else np.nan for t in tasks]
                ax.bar(np.arange(len(tasks)) + (k - (len(policies) - 1) / 2) * width, mean, width, yerr=std,
                       capsize=2, label=DISPLAY.get(p, p))
            ax.set_xticks(np.arange(len(tasks)), tasks)
            ax.set_title(f"{SPLIT_TITLES[split]} — {label}", fontsize=10)
            if j == 0:
                ax.set_ylabel(label)
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def print_table(rows: list[dict], title: str = "Evaluation") -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title, header_style="bold")
    for c in ("policy", "split", "task", "R̂", "N_C", "R", "episodes", "failures"):
        table.add_column(c, justify="left" if c in ("policy", "split", "task") else "right")
    for r in rows:
        table.add_row(DISPLAY.get(r["policy"], r["policy"]), r["split"], r["task"],
                      f"{_fmt(r['R_hat_mean'])} ± {_fmt(r['R_hat_std'])}",
                      f"{_fmt(r['N_C_mean'])} ± {_fmt(r['N_C_std'])}", f"{_fmt(r['R_mean'], 3)}",
                      str(r["episodes"]), str(r["failures"]))
    Console().print(table)


def log_wandb_table(rows: list[dict], key: str = "eval/table1") -> bool:
    """A wandb.Table of the rows when a wandb run is active; returns whether it logged."""
    try:
        import wandb
    except ImportError:
        return False
    if wandb.run is None:
        return False
    wandb.log({key: wandb.Table(columns=CSV_COLUMNS, data=[[r[c] for c in CSV_COLUMNS] for r in rows])})
    return True


def write_report(out_dir, reference: str = "oracle", normalize_by: str = "task", console: bool = True) -> dict:
    """results.csv, results.md (ours, then the paper's Table 1), results.png from out_dir/episodes."""
    out_dir = Path(out_dir)
    episodes = load_episodes(out_dir)
    if not episodes:
        raise FileNotFoundError(f"no episode JSONs under {out_dir / 'episodes'}")
    rows = summarize(episodes, reference, normalize_by)
    write_csv(rows, out_dir / "results.csv")
    ours = table1_markdown(rows_to_table(rows, reference), reference, title="TopoCut reimplementation",
                           note=f"R̂ normalised by `{reference}` per {normalize_by.replace('_', ' and ')}; "
                                f"{len(episodes)} episodes; means over episodes (std in results.csv).")
    paper = table1_markdown(PAPER_TABLE1, PAPER_REFERENCE, title="Paper (Table 1)",
                            note="R̂ normalised by human teleoperation per cut mode.")
    (out_dir / "results.md").write_text(ours + "\n" + paper)
    plot_results(rows, out_dir / "results.png", reference)
    if console:
        print_table(rows, title=f"Table 1 (reference: {reference})")
    logged = log_wandb_table(rows)
    return {"rows": rows, "csv": out_dir / "results.csv", "md": out_dir / "results.md",
            "png": out_dir / "results.png", "wandb": logged}

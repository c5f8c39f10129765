"""Table 1 from the episode JSONs: results.csv, results_objects.csv, results.md, results.png, a console table,
a wandb.Table.

Metrics (docs/evaluation.md):
  R̂   = final spectral reward / mean final reward of the reference policy on the same task
        (per task, or per task and split with normalize_by="task_split").
  N_C = RewardResult.cut_count after the last cut: correctly segmented, goal-consistent pieces.
Every mean comes with a percentile-bootstrap interval over episode specs (``topocut.eval.stats``; 95% by
default), and every policy with its paired difference from ``compare_to`` (the reference by default): the mean
over the scenes both ran of (its value - the other's), with its interval; an interval holding 0 is a tie (≈).
A learned policy evaluated with several training seeds (episode directories ``<policy>@s<seed>``) is pooled
into one row per cell, its seed count in ``train_seeds``.  Standard deviations are population std (ddof=0) over
the episodes of a cell.
"""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from topocut.eval import aggregates, stats
from topocut.eval.config import TASKS
from topocut.policies import registry

SPLIT_TITLES = {"in": "In-distribution", "out": "Out-of-distribution"}
SPLIT_SHORT = {"in": "ID", "out": "OOD"}


class _Display(dict):
    """Row labels; a name the registry lacks (a ``module.path:ClassName`` entry) gets its own display name."""

    def get(self, key, default=None):
        return super().get(key) or (registry.display_name(key) if registry.is_import_path(key) else default)


DISPLAY = _Display(registry.display_names())  # Table 1 row labels, in row order (topocut/policies/registry.py)
ALL = "all"  # the task / split / object of an aggregate row
METRICS = ("R_hat", "N_C", "R")
DIFF_METRICS = ("R_hat", "N_C")
CSV_COLUMNS = ["policy", "task", "split", "object", "train_seeds", "episodes", "failures",
               "R_hat_mean", "R_hat_lo", "R_hat_hi", "R_hat_std", "R_hat_seed_sd",
               "N_C_mean", "N_C_lo", "N_C_hi", "N_C_std", "R_mean", "R_lo", "R_hi", "R_std",
               "reference", "reference_R_mean", "compared_to", "pairs",
               "dR_hat_mean", "dR_hat_lo", "dR_hat_hi", "dR_hat_tie", "dN_C_mean", "dN_C_lo", "dN_C_hi", "dN_C_tie"]
RUN_SEP = "@s"  # episodes/<policy>@s<train seed>/: one learned policy's checkpoint trained with that seed
RUNS_FILE = "policies.json"  # {run name: {"policy", "train_seed", "checkpoint"}}, written by the eval stage

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


def run_name(policy: str, train_seed: int) -> str:
    """Episode directory of one training seed's checkpoint of a learned policy."""
    return f"{policy}{RUN_SEP}{int(train_seed)}"


def split_run(name: str) -> tuple[str, int | None]:
    """``pddp@s2`` -> ("pddp", 2); a plain policy name -> (name, None)."""
    base, sep, seed = name.rpartition(RUN_SEP)
    return (base, int(seed)) if sep and base and seed.isdigit() else (name, None)


def load_episodes(out_dir) -> list[dict]:
    """Every episodes/<run>/*.json under out_dir (temp files of an interrupted write are ignored).

    Each dict gets ``run`` (the directory's name), ``policy`` (the policy it belongs to) and ``train_seed`` (the
    training seed of its checkpoint: from policies.json, else from a ``<policy>@s<seed>`` name; None for a
    scripted policy).
    """
    out_dir = Path(out_dir)
    runs = json.loads((out_dir / RUNS_FILE).read_text()) if (out_dir / RUNS_FILE).exists() else {}
    episodes = []
    for p in sorted(out_dir.glob("episodes/*/*.json")):
        e = json.loads(p.read_text())
        run = e.get("policy", p.parent.name)
        policy, seed = split_run(run)
        meta = runs.get(run, {})
        e.update(run=run, policy=meta.get("policy", policy), train_seed=meta.get("train_seed", seed))
        episodes.append(e)
    return episodes


def _std(values) -> float:
    v = np.asarray(values, np.float64)
    return float(v.std()) if len(v) else math.nan


def _unit(spec: dict) -> tuple:
    """The scene an episode ran: (task, split, object, episode seed); the same key for every policy and training
    seed (a spec without a seed, as hand-made test episodes, is keyed by its index)."""
    return (spec["task"], spec["split"], spec.get("object", "?"), spec.get("seed", f"episode{spec.get('episode', 0)}"))


def _prepare(episodes: list[dict], reference: str, normalize_by: str) -> list[dict]:
    prepared = []
    for e in episodes:
        policy, seed = split_run(e["policy"])
        spec = e["spec"]
        prepared.append(dict(policy=policy, train_seed=e.get("train_seed", seed), task=spec["task"],
                             split=spec["split"], object=spec.get("object", "?"), unit=_unit(spec),
                             R=float(e["final_reward"]), N_C=float(e["final_cut_count"]), ok=e["status"] == "ok",
                             success=bool(e.get("success", False))))
    ref_eps = [e for e in prepared if e["policy"] == reference]
    ref_means = {}
    for e in prepared:
        key = (e["task"], e["split"] if normalize_by == "task_split" else None)
        if key not in ref_means:
            vals = [r["R"] for r in ref_eps if r["task"] == key[0] and (key[1] is None or r["split"] == key[1])]
            ref_means[key] = float(np.mean(vals)) if vals else math.nan
        ref = ref_means[key]
        e["ref"] = ref
        e["R_hat"] = e["R"] / ref if ref > 0 and math.isfinite(ref) else math.nan
    return prepared


# Row levels: the Table-1 cell (policy x task x split), aggregates over splits and over everything, and the
# per-object breakdown (results_objects.csv)
LEVELS = {"cell": lambda e: (e["task"], e["split"], ALL), "task": lambda e: (e["task"], ALL, ALL),
          "policy": lambda e: (ALL, ALL, ALL), "object": lambda e: (e["task"], e["split"], e["object"])}


def summarize(episodes: list[dict], reference: str = "oracle", normalize_by: str = "task", *,
              compare_to: str | None = None, levels=("cell", "task", "policy"), confidence: float = stats.CONFIDENCE,
              n_resamples: int = stats.RESAMPLES, seed: int = stats.SEED) -> list[dict]:
    """One row per (policy, task, split, object) at each of ``levels``, in the CSV_COLUMNS layout.

    ``compare_to`` (default: ``reference``) is the policy the ``d*`` columns compare with, paired by scene.
    """
    if normalize_by not in ("task", "task_split"):
        raise ValueError(f"normalize_by={normalize_by!r} is not valid; choose one of task, task_split")
    bad = [lv for lv in levels if lv not in LEVELS]
    if bad:
        raise ValueError(f"levels: unknown level {bad[0]!r}; valid: {', '.join(LEVELS)}")
    compare_to = compare_to or reference
    boot = dict(confidence=confidence, n_resamples=n_resamples, seed=seed)
    prepared = _prepare(episodes, reference, normalize_by)
    groups: dict[tuple, list[dict]] = {}
    for level in levels:
        for e in prepared:
            groups.setdefault((e["policy"], *LEVELS[level](e)), []).append(e)

    def units(eps, metric):
        means = stats.unit_means([(e["unit"], e[metric]) for e in eps])
        return dict(sorted(means.items(), key=lambda kv: repr(kv[0])))

    rows = []
    for key, eps in sorted(groups.items(), key=lambda kv: _order(kv[0])):
        policy, task, split, obj = key
        label = "|".join(map(str, key))
        seeds = {e["train_seed"] for e in eps if e["train_seed"] is not None}
        refs = {e["ref"] for e in eps}
        row = dict(policy=policy, task=task, split=split, object=obj, train_seeds=len(seeds), episodes=len(eps),
                   failures=sum(not e["ok"] for e in eps), reference=reference,
                   reference_R_mean=refs.pop() if len(refs) == 1 else math.nan, compared_to=compare_to)
        for m in METRICS:
            iv = stats.bootstrap_mean(list(units(eps, m).values()), label=f"{label}|{m}", **boot)
            row.update({f"{m}_mean": iv.mean, f"{m}_lo": iv.lo, f"{m}_hi": iv.hi,
                        f"{m}_std": _std([e[m] for e in eps])})
        row["R_hat_seed_sd"] = stats.seed_spread([(e["train_seed"], e["R_hat"]) for e in eps
                                                  if e["train_seed"] is not None])
        other = groups.get((compare_to, task, split, obj)) if policy != compare_to else None
        row["pairs"] = 0
        for m in DIFF_METRICS:
            d = (stats.paired_difference(units(eps, m), units(other, m), label=f"{label}|d{m}", **boot)
                 if other else stats.NAN_INTERVAL)
            row.update({f"d{m}_mean": d.mean, f"d{m}_lo": d.lo, f"d{m}_hi": d.hi, f"d{m}_tie": d.tie})
            row["pairs"] = d.n
        rows.append({c: row[c] for c in CSV_COLUMNS})
    return rows


def _order(key):
    policy, task, split, obj = key
    names = list(DISPLAY)
    return (names.index(policy) if policy in names else len(names), policy, ("in", "out", ALL).index(split),
            TASKS.index(task) if task in TASKS else len(TASKS) + (task == ALL), task, obj != ALL, obj)


def write_csv(rows: list[dict], path) -> None:
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=CSV_COLUMNS)
        w.writeheader()
        w.writerows(rows)


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


def _name(policy: str, seeds: dict | None) -> str:
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
    cols = [(s, t) for s in ("in", "out") for t in TASKS]
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
        name = _name(p, seeds) + (" (reference, raw R)" if p == reference else "")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _cells(rows: list[dict]) -> list[dict]:
    return [r for r in rows if r["object"] == ALL and r["split"] in SPLIT_SHORT and r["task"] != ALL]


def _seeds(rows: list[dict]) -> dict:
    return {r["policy"]: max(r["train_seeds"], 0) for r in rows}


def rows_to_table(rows: list[dict], reference: str | None = None) -> dict:
    """{policy: {(split, task): ((R̂ mean, lo, hi), (N_C mean, lo, hi))}} of the Table-1 cells; the reference
    policy's cells hold its raw R."""
    out: dict = {}
    for r in _cells(rows):
        m = "R" if r["policy"] == reference else "R_hat"
        out.setdefault(r["policy"], {})[r["split"], r["task"]] = (
            (r[f"{m}_mean"], r[f"{m}_lo"], r[f"{m}_hi"]), (r["N_C_mean"], r["N_C_lo"], r["N_C_hi"]))
    return out


def difference_markdown(rows: list[dict], compare_to: str, title: str = "", note: str = "") -> str:
    """Δ R̂ and Δ N_C against ``compare_to`` per Table-1 cell, paired by scene; ≈ marks a tie."""
    cols = [(s, t) for s in ("in", "out") for t in TASKS]
    cells = {(r["policy"], r["split"], r["task"]): r for r in _cells(rows) if r["policy"] != compare_to}
    policies = list(dict.fromkeys(p for p, _, _ in cells))
    lines = [f"### {title}" if title else "", note, "",
             "| Algorithm | " + " | ".join(f"{SPLIT_SHORT[s]} {t} ΔR̂ | {SPLIT_SHORT[s]} {t} ΔN_C" for s, t in cols)
             + " |", "|---" * (1 + 2 * len(cols)) + "|"]
    seeds = _seeds(rows)
    for p in policies:
        out = []
        for s, t in cols:
            r = cells.get((p, s, t))
            for m in DIFF_METRICS:
                out.append(format_difference(r[f"d{m}_mean"], r[f"d{m}_lo"], r[f"d{m}_hi"], r[f"d{m}_tie"]) if r else "-")
        lines.append(f"| {_name(p, seeds)} | " + " | ".join(out) + " |")
    return "\n".join(lines) + "\n"


def aggregate_markdown(rows: list[dict], compare_to: str, title: str = "", note: str = "") -> str:
    """R̂ and Δ R̂ per task over both splits, and over every task."""
    agg = {(r["policy"], r["task"]): r for r in rows if r["object"] == ALL and r["split"] == ALL}
    tasks = [t for t in (*TASKS, ALL) if any(k[1] == t for k in agg)]
    policies = list(dict.fromkeys(p for p, _ in agg))
    lines = [f"### {title}" if title else "", note, "",
             "| Algorithm | " + " | ".join(f"{t} R̂ | {t} ΔR̂" for t in tasks) + " |",
             "|---" * (1 + 2 * len(tasks)) + "|"]
    seeds = _seeds(rows)
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
        lines.append(f"| {_name(p, seeds)} | " + " | ".join(out) + " |")
    return "\n".join(lines) + "\n"


def plot_results(rows: list[dict], path, reference: str | None = None) -> dict:
    """Grouped bars: rows R̂ / N_C, columns in / out of distribution, groups = tasks, bars = policies, the
    reference first (hatched; its R̂ is its reward over its own mean, about 1, the scale the others are read
    against: without it a smoke run's panels were bars of zero height only); the error bars are the bootstrap
    intervals (none where undefined).  Returns the bars drawn: {(metric, split): {policy: [mean per task]}}."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = _cells(rows)
    policies = list(dict.fromkeys(r["policy"] for r in rows))
    policies.sort(key=lambda p: p != reference)  # stable: the reference first, the others in row order
    drawn: dict = {}
    tasks = [t for t in TASKS if any(r["task"] == t for r in rows)]
    fig, axes = plt.subplots(2, 2, figsize=(11, 6.5), sharey="row", squeeze=False)
    width = 0.8 / max(len(policies), 1)
    for j, split in enumerate(("in", "out")):
        for i, (metric, label) in enumerate((("R_hat", "normalised reward R̂"), ("N_C", "cut count N_C"))):
            ax = axes[i, j]
            for k, p in enumerate(policies):
                cell = {r["task"]: r for r in rows if r["policy"] == p and r["split"] == split}
                mean = np.array([cell[t][f"{metric}_mean"] if t in cell else np.nan for t in tasks], np.float64)
                lo = np.array([cell[t][f"{metric}_lo"] if t in cell else np.nan for t in tasks], np.float64)
                hi = np.array([cell[t][f"{metric}_hi"] if t in cell else np.nan for t in tasks], np.float64)
                err = np.nan_to_num(np.stack([mean - lo, hi - mean]), nan=0.0).clip(min=0.0)
                ref = p == reference
                ax.bar(np.arange(len(tasks)) + (k - (len(policies) - 1) / 2) * width, mean, width, yerr=err,
                       capsize=2, label=DISPLAY.get(p, p) + (" (reference)" if ref else ""),
                       hatch="//" if ref else None, edgecolor="0.3" if ref else None)
                drawn.setdefault((metric, split), {})[p] = mean.tolist()
            ax.set_xticks(np.arange(len(tasks)), tasks)
            ax.set_title(f"{SPLIT_TITLES[split]} — {label}", fontsize=10)
            if j == 0:
                ax.set_ylabel(label)
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return drawn


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


def write_report(out_dir, reference: str = "oracle", normalize_by: str = "task", console: bool = True, *,
                 compare_to: str | None = None, confidence: float = stats.CONFIDENCE,
                 n_resamples: int = stats.RESAMPLES, seed: int = stats.SEED) -> dict:
    """results.csv (Table-1 cells and aggregates), results_objects.csv (per object), results.md (ours with
    intervals, the paired differences, the aggregates, the IQM / P(improvement) / success table of
    ``topocut.eval.aggregates``, the paper's Table 1), results.png, profile.png, from out_dir/episodes."""
    out_dir = Path(out_dir)
    episodes = load_episodes(out_dir)
    if not episodes:
        raise FileNotFoundError(f"no episode JSONs under {out_dir / 'episodes'}")
    compare_to = compare_to or reference
    kw = dict(compare_to=compare_to, **(boot := dict(confidence=confidence, n_resamples=n_resamples, seed=seed)))
    rows = summarize(episodes, reference, normalize_by, **kw)
    write_csv(rows, out_dir / "results.csv")
    write_csv(summarize(episodes, reference, normalize_by, levels=("object",), **kw), out_dir / "results_objects.csv")
    seeds = _seeds(rows)
    pooled = {p: k for p, k in seeds.items() if k > 1}
    ci = (f"{confidence:.0%} percentile-bootstrap intervals over episode specs ({n_resamples} resamples, "
          f"seed {seed})")
    note = (f"R̂ normalised by `{reference}` per {normalize_by.replace('_', ' and ')}; {len(episodes)} episodes; "
            f"mean [{ci}]; a cell of one episode has no interval. Bold: a column's best mean among the policies "
            "compared (not the reference row), where it is above 0."
            + (" Training seeds pooled (each seed's checkpoint runs every episode): "
               + ", ".join(f"{DISPLAY.get(p, p)} {k}" for p, k in pooled.items()) + "." if pooled else ""))
    ours = table1_markdown(rows_to_table(rows, reference), reference, title="TopoCut reimplementation", note=note,
                           seeds=seeds)
    dnote = (f"Paired by scene (task, object, episode seed) against `{compare_to}`: mean of the per-scene "
             f"differences [{ci}]; **≈** marks a tie (the interval contains 0). A policy with several training "
             "seeds enters with its per-scene mean over seeds.")
    diff = difference_markdown(rows, compare_to, title=f"Difference from {DISPLAY.get(compare_to, compare_to)}",
                               note=dnote)
    agg = aggregate_markdown(rows, compare_to, title="Aggregates (both splits; all = every task)",
                             note=f"R̂ [{ci}]; ΔR̂ against `{compare_to}`, paired as above (≈: tie).")
    prepared, name = _prepare(episodes, reference, normalize_by), lambda p: _name(p, seeds)
    scores = aggregates.markdown(prepared, reference, name, **boot)
    paper = table1_markdown(PAPER_TABLE1, PAPER_REFERENCE, title="Paper (Table 1)",
                            note="R̂ normalised by human teleoperation per cut mode.")
    (out_dir / "results.md").write_text(ours + "\n" + diff + "\n" + agg + "\n" + scores + "\n" + paper)
    plot_results(rows, out_dir / "results.png", reference)
    aggregates.plot_profiles(prepared, out_dir / "profile.png", reference, name)
    if console:
        print_table(rows, title=f"Table 1 (reference: {reference}; Δ against {compare_to})")
    logged = log_wandb_table(rows)
    return {"rows": rows, "csv": out_dir / "results.csv", "objects_csv": out_dir / "results_objects.csv",
            "md": out_dir / "results.md", "png": out_dir / "results.png", "profile": out_dir / "profile.png",
            "wandb": logged}

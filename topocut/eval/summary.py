"""Table 1's rows from the episode JSONs: one row per policy and Table-1 cell (and per task, per policy, per
object), in the results.csv layout (``CSV_COLUMNS``).

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

from topocut.eval import stats
from topocut.eval.config import TASKS
from topocut.policies import registry


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


def prepare_episodes(episodes: list[dict], reference: str, normalize_by: str) -> list[dict]:
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
    prepared = prepare_episodes(episodes, reference, normalize_by)
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

"""Table 1 from the episode JSONs: results.csv, results_objects.csv, results.md, results.png, a console table,
a wandb.Table (``write_report``).  The jobs live apart: the rows in ``topocut.eval.summary``, the tables in
``topocut.eval.tables``, the bars in ``topocut.eval.plots``; their public names are importable from here too.

The metrics (R̂, N_C), their intervals and the paired differences: ``topocut.eval.summary`` (docs/evaluation.md).
"""
from __future__ import annotations

from pathlib import Path

from topocut.eval import aggregates, stats
from topocut.eval.plots import plot_results
from topocut.eval.summary import (
    ALL,
    CSV_COLUMNS,
    DIFF_METRICS,
    DISPLAY,
    LEVELS,
    METRICS,
    RUN_SEP,
    RUNS_FILE,
    load_episodes,
    prepare_episodes,
    run_name,
    split_run,
    summarize,
    write_csv,
)
from topocut.eval.tables import (
    PAPER_REFERENCE,
    PAPER_TABLE1,
    SPLIT_SHORT,
    SPLIT_TITLES,
    aggregate_markdown,
    best_shown,
    difference_markdown,
    format_difference,
    format_interval,
    log_wandb_table,
    print_table,
    row_label,
    rows_to_table,
    seed_counts,
    table1_markdown,
    wandb_data,
)

__all__ = ["ALL", "CSV_COLUMNS", "DIFF_METRICS", "DISPLAY", "LEVELS", "METRICS", "RUN_SEP", "RUNS_FILE", "load_episodes",
           "prepare_episodes", "run_name", "split_run", "summarize", "write_csv", "PAPER_REFERENCE", "PAPER_TABLE1",
           "SPLIT_SHORT", "SPLIT_TITLES", "aggregate_markdown", "best_shown", "difference_markdown", "format_difference",
           "format_interval", "log_wandb_table", "print_table", "row_label", "rows_to_table", "seed_counts",
           "table1_markdown", "wandb_data", "plot_results", "write_report"]


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
    seeds = seed_counts(rows)
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
    prepared, name = prepare_episodes(episodes, reference, normalize_by), lambda p: row_label(p, seeds)
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

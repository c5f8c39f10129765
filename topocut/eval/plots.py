"""results.png: Table 1's cells as grouped bars with their bootstrap intervals."""
from __future__ import annotations

import numpy as np

from topocut.eval.config import table_tasks
from topocut.eval.summary import DISPLAY
from topocut.eval.tables import SPLIT_TITLES, table1_cells


def plot_results(rows: list[dict], path, reference: str | None = None) -> dict:
    """Grouped bars: rows R̂ / N_C, columns in / out of distribution, groups = tasks, bars = policies, the
    reference first (hatched; its R̂ is its reward over its own mean, about 1, the scale the others are read
    against: without it a smoke run's panels were bars of zero height only); the error bars are the bootstrap
    intervals (none where undefined).  Returns the bars drawn: {(metric, split): {policy: [mean per task]}}."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = table1_cells(rows)
    policies = list(dict.fromkeys(r["policy"] for r in rows))
    policies.sort(key=lambda p: p != reference)  # stable: the reference first, the others in row order
    drawn: dict = {}
    tasks = [t for t in table_tasks(r["task"] for r in rows) if any(r["task"] == t for r in rows)]
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

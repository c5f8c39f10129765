"""Cream writing (docs/tasks.md): the scripted writer vs MPPI over strokes on the same letter goals, and the
top-down figure of both (``python experiments/task_figures.py writing``)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def writing_experiment(word: str = "CORL", n_grid: int = 48, num_samples: int = 4, iterations: int = 2,
                       seed: int = 0, out: str | None = None) -> dict:
    """Cream writing: the scripted writer vs MPPI over strokes (same goals); figure + numbers."""
    from topocut.planning.stroke_mppi import StrokeMPPI, StrokeMPPIConfig
    from topocut.sim import SimConfig, init_taichi
    from topocut.sim.pen import CreamPen
    from topocut.tasks import task_config
    from topocut.tasks.writing_scene import write_scripted, writing_scene

    init_taichi("cpu", cpu_threads=1)
    sim, task = SimConfig(n_grid=n_grid), task_config("cream_writing", word=word).validate()
    goals, strokes, start, _ = writing_scene(sim, task)
    pen = CreamPen(sim, task.pen, 1, start=start)
    scripted = write_scripted(pen, strokes, goals)
    xs, ss = pen.particles()
    mpen = CreamPen(sim, task.pen, num_samples, start=start)
    mppi = StrokeMPPI(mpen, goals, StrokeMPPIConfig(num_samples=num_samples, iterations=iterations), seed=seed)
    planned = mppi.write(strokes)
    xm, sm = mpen.particles()
    planned.pop("polylines")
    result = {"word": word, "n_grid": n_grid, "scripted": scripted, "mppi": planned}
    if out:
        draw_writing(out, goals, [("scripted writer", xs[0], ss, scripted),
                                  (f"MPPI over strokes (K={num_samples}, {iterations} it.)", xm[0], sm, planned)])
        Path(out).with_suffix(".json").write_text(json.dumps(result, indent=2, default=float))
    return result


def draw_writing(path, goals, results: list[tuple[str, np.ndarray, np.ndarray, dict]]) -> None:
    """Top-down figure: the letter goals, then each result (title, x (n,3), stroke (n,), rewards) by stroke."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from topocut.sim.render import label_colors

    rows = 1 + len(results)
    fig, axes = plt.subplots(rows, 1, figsize=(8, 2.3 * rows), dpi=110)
    g = np.concatenate(goals)
    axes[0].scatter(g[:, 0], g[:, 1], s=4, c=label_colors(np.repeat(np.arange(len(goals)), [len(q) for q in goals]) + 1))
    axes[0].set_title(f"goal: {len(goals)} letter point clouds ({', '.join(str(len(q)) for q in goals)} points)",
                      fontsize=9)
    for ax, (title, x, stroke, rew) in zip(axes[1:], results):
        ax.scatter(x[:, 0], x[:, 1], s=4, c=label_colors(np.asarray(stroke) + 1))
        per = ", ".join(f"{r:.2f}" for r in rew["per_letter"])
        d = ", ".join(f"{v:.3f}" for v in rew["distance"])
        ax.set_title(f"{title}: {len(x)} particles, reward {rew['total']:.3f} (per letter {per}; d {d})",
                     fontsize=9)
    lo, hi = g[:, :2].min(0) - 0.02, g[:, :2].max(0) + 0.02
    for ax in axes:
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)

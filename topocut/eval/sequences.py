"""The evaluation's cutting sequences (``eval.gifs``; docs/evaluation.md "Cutting sequences").

For one policy run (PDDP's first training seed, else the first run), the first ``eval.gifs`` episodes of each task
as a GIF (``gifs/<task>_<object>_<episode>_<run>.gif``: the state after every cut and turn, particles coloured by
cluster id, the knife of the cut, the board; the episode engine's own frames), and ``gifs/sequences.png``, the
paper's cutting-sequence figure: a row per task from its first such episode (initial state, goal, each cut).

Filmed as the evaluation goes, beside the videos (``Sequences`` is a member of topocut.eval.videos.Films, handed to
run_evaluation and to ``eval.jobs``' workers): the batch holding such an episode keeps its states, and the GIF (and,
for a figure row, the row's panels, kept under ``gifs/panels/`` until the figure is drawn) is written before the
episode's JSON, so the GIF is the evaluated episode and no episode is run again for it.  The figure is drawn once
every row's panels are there (``Sequences.draw``, after the last episode), and the panels are then removed.  Only an
episode an interrupted evaluation committed without them is run again (topocut.eval.videos.film_episodes).
"""
from __future__ import annotations

import pickle
import shutil
from pathlib import Path

from topocut.data.store import write_atomic

GIF_FPS = 1.5  # a state every 0.67 s
FIGURE = "sequences.png"


class Sequences:
    """The GIFs of run ``run`` on the episodes ``keys`` and the figure's rows ``rows`` ([(task, key, object)], one a
    task, in ``eval.tasks`` order), under ``out_dir``.  ``frames_per_cut`` 0: states only, no frames during a cut."""

    frames_per_cut = 0

    def __init__(self, out_dir, run: str, keys, rows):
        self.out_dir, self.run, self.keys, self.rows = Path(out_dir), run, frozenset(keys), list(rows)
        self.row_keys = frozenset(key for _, key, _ in self.rows)

    @classmethod
    def of(cls, specs, eval, runs, out_dir) -> Sequences | None:
        """The eval config's sequences of ``specs`` (the protocol's whole list) for the runs ``runs`` (policy run
        names, ``pddp@s0`` for a training seed), or None when ``eval.gifs`` is 0."""
        runs = list(runs)
        if int(eval.gifs) <= 0 or not runs:
            return None
        run = next((n for n in runs if n.split("@")[0] == "pddp"), runs[0])
        keys, rows = [], []
        for task in eval.tasks:
            chosen = [s for s in specs if s.task == task][: int(eval.gifs)]
            keys += [s.key for s in chosen]
            if chosen:
                rows.append((task, chosen[0].key, chosen[0].object))
        return cls(out_dir, run, keys, rows) if keys else None

    def gif_path(self, spec) -> Path:
        return self.out_dir / f"{spec.key}_{self.run}.gif"

    def panels_path(self, key: str) -> Path:
        return self.out_dir / "panels" / f"{key}.pkl"

    @property
    def figure(self) -> Path:
        return self.out_dir / FIGURE

    def _row_missing(self, spec) -> bool:
        return spec.key in self.row_keys and not self.figure.exists() and not self.panels_path(spec.key).exists()

    def wants(self, run: str, spec) -> bool:
        if run != self.run or spec.key not in self.keys:
            return False
        return self._row_missing(spec) or not self.gif_path(spec).exists()

    def write(self, run: str, spec, log, board_z: float) -> Path | None:
        """What is missing of ``log`` (an EpisodeLog kept with frames): its GIF, a figure row's panels; the GIF's path,
        None for an episode that reached no state."""
        if not log.frames:
            return None
        from topocut.sim.render import goal_colors, render_frames, write_gif

        path = self.gif_path(spec)
        if not path.exists():  # one view box over every frame of the episode: pieces pushed or turned away stay in view
            images = render_frames([dict(x=x, labels=labels, knife=knife, title=f"{run} {spec.key} {what}")
                                    for x, labels, what, knife in log.frames], board_z=board_z)
            write_atomic(path, lambda tmp: write_gif(images, tmp, fps=GIF_FPS))
        if self._row_missing(spec):
            panels = []
            for i, (x, labels, what, knife) in enumerate(log.frames):  # knife: a cut's executed action
                if i == 0 or knife is not None:
                    panels.append((x, labels, knife, "initial" if i == 0 else what))
                if i == 0 and log.goal is not None:
                    panels.append((log.goal.points, goal_colors(log.goal.labels), None, "goal"))

            def dump(tmp):
                with open(tmp, "wb") as f:
                    pickle.dump(panels, f, protocol=pickle.HIGHEST_PROTOCOL)

            write_atomic(self.panels_path(spec.key), dump)
        return path

    def draw(self, board_z: float) -> Path | None:
        """``sequences.png`` from the rows' panels (those there: a row whose episode did not run is left out), then
        the panels go; the figure already drawn is kept.  None when there is no row to draw."""
        if self.figure.exists():
            return self.figure
        rows = []
        for task, key, obj in self.rows:
            p = self.panels_path(key)
            if p.exists():
                with open(p, "rb") as f:
                    rows.append((f"{task}: {obj}", pickle.load(f)))  # noqa: S301 - this evaluation's own file
        if not rows:
            return None
        from topocut.sim.render import render_sequences

        write_atomic(self.figure, lambda tmp: render_sequences(rows, tmp, board_z=board_z))
        shutil.rmtree(self.out_dir / "panels", ignore_errors=True)
        return self.figure

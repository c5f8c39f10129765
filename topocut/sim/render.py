"""Headless pictures of particle scenes: PNG scatter plots (matplotlib Agg) and GIFs (imageio).

``python experiments/render_objects.py --objects docs/img/objects.png`` draws every
object of topocut.sim.objects (core grey, skin orange) for docs/sim.md.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

_PALETTE = np.array([[0.55, 0.55, 0.6], [0.95, 0.55, 0.2], [0.55, 0.25, 0.7], [0.2, 0.6, 0.3],
                     [0.2, 0.45, 0.85], [0.85, 0.3, 0.3], [0.6, 0.5, 0.25], [0.3, 0.75, 0.75]])


def label_colors(labels) -> np.ndarray:
    """(N,) integer labels (material, damage or cluster id; -1 = unassigned, black) -> (N,4) RGBA."""
    lab = np.asarray(labels).astype(np.int64).reshape(-1)
    rgb = _PALETTE[np.mod(lab, len(_PALETTE))]
    rgb[lab < 0] = 0.0
    return np.concatenate([rgb, np.ones((len(lab), 1))], 1)


def _colors(colors_or_labels, n: int) -> np.ndarray:
    c = np.asarray(colors_or_labels)
    if c.ndim == 2 and c.shape[1] in (3, 4):
        return c
    if c.shape[0] != n:
        raise ValueError(f"got {c.shape[0]} labels for {n} points")
    return label_colors(c)


def blade_corners(action, board_z: float, center=None, half_length: float = 0.08, height: float = 0.1) -> np.ndarray:
    """The blade's rectangle (4,3) at the end of its cut: the edge on the board along u, the back ``height``
    above it along -w, in the cut plane; centred along u at the projection of ``center`` (default the
    plane's board point).  ``action``: a KnifeAction."""
    p, u, up = action.plane_point(board_z), action.blade_axis, -action.travel  # 3, 3, 3
    if center is not None:
        p = p + u * float(np.dot(np.asarray(center, np.float64) - p, u))
    lo, hi = p - half_length * u, p + half_length * u
    return np.stack([lo, hi, hi + height * up, lo + height * up])


def _draw_knife(ax, action, board_z, center, half_length, height):
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    corners = blade_corners(action, board_z, center, half_length, height)
    ax.add_collection3d(Poly3DCollection([corners], facecolor=(0.55, 0.7, 0.85, 0.35), edgecolor=(0.1, 0.2, 0.4, 0.9),
                                         linewidths=0.8))
    ax.plot(*corners[:2].T, color=(0.1, 0.2, 0.4), lw=1.5)  # the cutting edge


def _draw_board(ax, lo, hi, board_z):
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    (x0, y0), (x1, y1) = lo[:2], hi[:2]
    quad = [(x0, y0, board_z), (x1, y0, board_z), (x1, y1, board_z), (x0, y1, board_z)]
    ax.add_collection3d(Poly3DCollection([quad], facecolor=(0.8, 0.65, 0.45, 0.45), edgecolor=(0.5, 0.35, 0.2, 0.6)))


def _draw(ax, x, colors, view, size, limits, knife=None, board_z=None):
    """Particles (N,3) coloured, the board (its top face z = board_z) and the knife (a KnifeAction) if given."""
    x = np.asarray(x, np.float32).reshape(-1, 3)
    lo, hi = limits if limits is not None else (x.min(0), x.max(0))
    if board_z is not None:
        _draw_board(ax, np.asarray(lo), np.asarray(hi), board_z)
    ax.scatter(x[:, 0], x[:, 1], x[:, 2], c=colors, s=size, depthshade=True, linewidths=0)
    if knife is not None:
        span = float(np.max(np.asarray(hi)[:2] - np.asarray(lo)[:2]))
        _draw_knife(ax, knife, board_z if board_z is not None else float(x[:, 2].min()), x.mean(0), 0.5 * span,
                    0.6 * span)
    c, r = (np.asarray(lo) + np.asarray(hi)) / 2, (np.asarray(hi) - np.asarray(lo)).max() / 2 + 1e-3
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.view_init(elev=view[0], azim=view[1])
    ax.set_box_aspect((1, 1, 1))
    ax.set_axis_off()


def render_particles(x, colors_or_labels, path, title: str | None = None, view=(25.0, -60.0), size: float = 2.0,
                     limits=None, dpi: int = 100, figsize=(5, 5), knife=None, board_z: float | None = None) -> Path:
    """Scatter plot of particles (N,3) coloured by labels (N,) or RGB(A) colours (N,3|4) into a PNG, with the
    board and the knife's last cut (a KnifeAction) when given."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = np.asarray(x).reshape(-1, 3)
    fig = plt.figure(figsize=figsize, dpi=dpi)
    ax = fig.add_subplot(projection="3d")
    _draw(ax, x, _colors(colors_or_labels, len(x)), view, size, limits, knife, board_z)
    if title:
        ax.set_title(title)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, bbox_inches="tight")
    plt.close(fig)
    return path


def row_limits(scenes, board_z: float, pad: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) (3,) of every scene's points (each (N,3)) together, padded by ``pad``, reaching down to the board."""
    x = np.concatenate([np.asarray(s, np.float64).reshape(-1, 3) for s in scenes])  # sum N,3
    lo, hi = x.min(0) - pad, x.max(0) + pad
    lo[2] = min(lo[2], board_z)
    return lo, hi


def render_sequences(rows, path, board_z: float, view=(25.0, -60.0), size: float = 1.2, panel: float = 1.3,
                     dpi: int = 220, pad: float = 0.02) -> Path:
    """The paper's cutting-sequence figure: one row per episode, one panel per state.  ``rows`` =
    [(row title, [(x (N,3), labels (N,), knife action or None, caption)])]; every panel of a row shares the row's
    extent (``row_limits``: pieces pushed or laid down away from the object stay in view) and shows the board; a
    panel with an action shows the knife at the end of that cut.  ``panel`` inches a panel: 7 columns fit a page width (two-column papers: 3.5 in a column)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = max(len(p) for _, p in rows)
    fig = plt.figure(figsize=(panel * cols, panel * len(rows) * 1.05), dpi=dpi)
    for r, (title, panels) in enumerate(rows):
        lo, hi = row_limits([p[0] for p in panels], board_z, pad)
        for c, (x, labels, knife, caption) in enumerate(panels):
            ax = fig.add_subplot(len(rows), cols, r * cols + c + 1, projection="3d")
            _draw(ax, x, _colors(labels, len(np.asarray(x).reshape(-1, 3))), view, size, (lo, hi), knife, board_z)
            ax.set_title(caption, fontsize=6, pad=0)
            if c == 0:
                ax.text2D(-0.08, 0.5, title, transform=ax.transAxes, rotation=90, va="center", ha="center",
                          fontsize=7, fontweight="bold")
    width, height = fig.get_size_inches()  # margins in inches: the row titles left, the captions on top
    fig.subplots_adjust(left=0.22 / width, right=0.995, bottom=0.0, top=1 - 0.16 / height, wspace=0.0, hspace=0.08)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def write_gif(frames, path, fps: float = 8.0) -> Path:
    """GIF from PNG paths or (H,W,3|4) uint8 arrays; frames are padded to the largest size."""
    import imageio.v2 as imageio

    imgs = [np.asarray(imageio.imread(f)) if isinstance(f, (str, Path)) else np.asarray(f) for f in frames]
    if not imgs:
        raise ValueError("write_gif needs at least one frame")
    imgs = [im[..., :3] if im.ndim == 3 else np.repeat(im[..., None], 3, -1) for im in imgs]
    h, w = max(i.shape[0] for i in imgs), max(i.shape[1] for i in imgs)
    padded = []
    for im in imgs:
        canvas = np.full((h, w, 3), 255, np.uint8)
        canvas[:im.shape[0], :im.shape[1]] = im
        padded.append(canvas)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    imageio.mimsave(path, padded, duration=1000.0 / fps, loop=0)  # ms per frame (imageio >= 2.28)
    return path


def render_objects(path, spacing: float = 0.006, view=(25.0, -60.0)) -> Path:
    """One panel per object of topocut.sim.objects at the nominal pose (core grey, skin orange)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from topocut.sim.objects import OBJECTS, UNSEEN, sample_object

    fig = plt.figure(figsize=(15, 6.4), dpi=90)
    for i, name in enumerate(OBJECTS):
        x, mat = sample_object(name, spacing=spacing)
        ax = fig.add_subplot(2, 5, i + 1, projection="3d")
        _draw(ax, x, label_colors(mat), view, 1.0, ((0.35, 0.35, 0.05), (0.65, 0.65, 0.35)))
        ax.set_title(f"{name}{' (unseen)' if name in UNSEEN else ''}\n{len(x)} particles", fontsize=10)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, bbox_inches="tight")
    plt.close(fig)
    return path

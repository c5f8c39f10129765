"""Headless pictures of particle scenes: PNG scatter plots (matplotlib Agg) and GIFs (imageio).

``python -m topocut.sim.render --objects docs/img/objects.png`` draws every
object of topocut.sim.objects (core grey, skin orange) for docs/sim.md.
"""
from __future__ import annotations

import argparse
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


def _draw(ax, x, colors, view, size, limits):
    x = np.asarray(x, np.float32).reshape(-1, 3)
    ax.scatter(x[:, 0], x[:, 1], x[:, 2], c=colors, s=size, depthshade=True, linewidths=0)
    lo, hi = limits if limits is not None else (x.min(0), x.max(0))
    c, r = (np.asarray(lo) + np.asarray(hi)) / 2, (np.asarray(hi) - np.asarray(lo)).max() / 2 + 1e-3
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.view_init(elev=view[0], azim=view[1])
    ax.set_box_aspect((1, 1, 1))
    ax.set_axis_off()


def render_particles(x, colors_or_labels, path, title: str | None = None, view=(25.0, -60.0), size: float = 2.0,
                     limits=None, dpi: int = 100, figsize=(5, 5)) -> Path:
    """Scatter plot of particles (N,3) coloured by labels (N,) or RGB(A) colours (N,3|4) into a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = np.asarray(x).reshape(-1, 3)
    fig = plt.figure(figsize=figsize, dpi=dpi)
    ax = fig.add_subplot(projection="3d")
    _draw(ax, x, _colors(colors_or_labels, len(x)), view, size, limits)
    if title:
        ax.set_title(title)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, bbox_inches="tight")
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


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", metavar="PNG", help="draw every object into this PNG")
    args = ap.parse_args(argv)
    if not args.objects:
        ap.error("nothing to do: pass --objects PATH")
    print(render_objects(args.objects))


if __name__ == "__main__":
    main()

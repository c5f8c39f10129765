"""Headless pictures of particle scenes (matplotlib Agg): the one renderer behind stage=simulate's frames and GIF,
the evaluation's GIFs and cutting-sequence figure, and the gym env's ``rgb_array`` frames (docs/sim.md#rendering).

A frame shows the particles coloured by cluster id (``cluster_colors``: -1 unassigned light grey, distinct from
every cluster colour), the cutting board, the knife's blade as a quad in its cut plane, and a legend.
``render_frames`` frames a whole sequence with one view box spanning every frame, so pieces pushed aside or laid
down never leave the picture.  ``python experiments/render_objects.py --objects docs/img/objects.png`` draws every
object of topocut.sim.objects (core grey, skin orange).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

# cluster k is drawn in _PALETTE[k % 9] (tab10 without its grey): grey is kept for particles with no cluster
_PALETTE = np.array([[0.12, 0.47, 0.71], [1.0, 0.5, 0.05], [0.17, 0.63, 0.17], [0.84, 0.15, 0.16],
                     [0.58, 0.4, 0.74], [0.55, 0.34, 0.29], [0.89, 0.47, 0.76], [0.74, 0.74, 0.13],
                     [0.09, 0.75, 0.81]])
UNASSIGNED = np.array([0.78, 0.78, 0.8])  # label -1 / "not a goal piece"
DAMAGED = np.array([0.12, 0.12, 0.12])  # particles the knife damaged (simulate's damage frames, motion frames)
KNIFE_FACE, KNIFE_EDGE = (0.55, 0.7, 0.85, 0.35), (0.1, 0.2, 0.4)
BOARD_FACE, BOARD_EDGE = (0.8, 0.65, 0.45, 0.45), (0.5, 0.35, 0.2, 0.6)
# categorical colours for materials and strokes (label_colors): 0 grey core / base, 1 orange skin, ...
_CATEGORICAL = np.array([[0.55, 0.55, 0.6], [0.95, 0.55, 0.2], [0.55, 0.25, 0.7], [0.2, 0.6, 0.3],
                         [0.2, 0.45, 0.85], [0.85, 0.3, 0.3], [0.6, 0.5, 0.25], [0.3, 0.75, 0.75]])
LEGEND_PIECES = 9  # pieces named in a legend; past that the colours repeat


def label_colors(labels) -> np.ndarray:
    """(N,) categorical labels (material, stroke; 0 grey, -1 black) -> (N,4) RGBA.  Cluster ids: cluster_colors."""
    lab = np.asarray(labels).astype(np.int64).reshape(-1)
    rgb = _CATEGORICAL[np.mod(lab, len(_CATEGORICAL))]
    rgb[lab < 0] = 0.0
    return np.concatenate([rgb, np.ones((len(lab), 1))], 1)


def cluster_colors(labels, damaged=None) -> np.ndarray:
    """(N,) cluster ids -> (N,4) RGBA: cluster k _PALETTE[k % 9], -1 UNASSIGNED; ``damaged`` (N,) bool DAMAGED."""
    lab = np.asarray(labels).astype(np.int64).reshape(-1)
    rgb = np.where((lab < 0)[:, None], UNASSIGNED, _PALETTE[np.mod(lab, len(_PALETTE))])  # N,3
    if damaged is not None:
        rgb[np.asarray(damaged, bool).reshape(-1)] = DAMAGED
    return np.concatenate([rgb, np.ones((len(lab), 1))], 1)


def goal_colors(goal_labels) -> np.ndarray:
    """A goal cloud's labels (0 not a goal piece, i goal piece i) -> RGBA: goal piece i as cluster i - 1."""
    return cluster_colors(np.asarray(goal_labels).astype(np.int64) - 1)


def _colors(colors_or_labels, n: int) -> np.ndarray:
    c = np.asarray(colors_or_labels)
    if c.ndim == 2 and c.shape[1] in (3, 4):
        return c
    if c.shape[0] != n:
        raise ValueError(f"got {c.shape[0]} labels for {n} points")
    return cluster_colors(c)


def blade_corners(action, board_z: float, center=None, half_length: float = 0.08, height: float = 0.1,
                  edge=None) -> np.ndarray:
    """The blade's rectangle (4,3) in the cut plane: the edge along u, the back ``height`` above it along -w.
    The edge lies on the board (the end of the cut) or, during a cut, passes through ``edge`` (3,); it is centred
    along u at the projection of ``center`` (default the plane's board point).  ``action``: a KnifeAction."""
    u, up = action.blade_axis, -action.travel  # 3, 3
    p = action.plane_point(board_z) if edge is None else np.asarray(edge, np.float64)  # 3,
    if center is not None:
        p = p + u * float(np.dot(np.asarray(center, np.float64) - p, u))
    lo, hi = p - half_length * u, p + half_length * u
    return np.stack([lo, hi, hi + height * up, lo + height * up])


def row_limits(scenes, board_z: float, pad: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) (3,) of every scene's points (each (N,3)) together, padded by ``pad``, reaching down to the board:
    the view box of a whole sequence, so that nothing pushed or turned away leaves it."""
    x = np.concatenate([np.asarray(s, np.float64).reshape(-1, 3) for s in scenes])  # sum N,3
    lo, hi = x.min(0) - pad, x.max(0) + pad
    lo[2] = min(lo[2], board_z)
    return lo, hi


sequence_limits = row_limits


def _draw(ax, x, colors, view, size, limits, knife=None, board_z=None, knife_edge=None, knife_color=None):
    """Particles (N,3) coloured, the board (top face z = board_z) and the knife (a KnifeAction) into a 3D axes whose
    box is ``limits`` at equal scale on every axis."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    x = np.asarray(x, np.float32).reshape(-1, 3)
    lo, hi = (np.asarray(v, np.float64) for v in (limits if limits is not None else (x.min(0), x.max(0))))
    hi = np.maximum(hi, lo + 1e-3)  # a flat scene still gets a box
    # fixed draw order: mplot3d's depth sort by centroid puts the wide board in front of the object it carries;
    # seen from above the board is behind everything, and the translucent blade goes over the particles
    ax.computed_zorder = False
    if board_z is not None:
        quad = [(lo[0], lo[1], board_z), (hi[0], lo[1], board_z), (hi[0], hi[1], board_z), (lo[0], hi[1], board_z)]
        ax.add_collection3d(Poly3DCollection([quad], facecolor=BOARD_FACE, edgecolor=BOARD_EDGE, zorder=0))
    ax.scatter(x[:, 0], x[:, 1], x[:, 2], c=colors, s=size, depthshade=True, linewidths=0, zorder=1)
    if knife is not None:
        span = float(np.max(hi[:2] - lo[:2]))
        corners = blade_corners(knife, board_z if board_z is not None else float(x[:, 2].min()), x.mean(0),
                                0.5 * span, 0.6 * span, edge=knife_edge)  # 4,3
        face = KNIFE_FACE if knife_color is None else knife_color
        edge = KNIFE_EDGE if knife_color is None else knife_color
        ax.add_collection3d(Poly3DCollection([corners], facecolor=face, edgecolor=edge, linewidths=0.8, zorder=2))
        ax.plot(*corners[:2].T, color=edge, lw=1.5, zorder=3)  # the cutting edge
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.view_init(elev=view[0], azim=view[1])
    ax.set_box_aspect(hi - lo)  # equal scale: a cube stays a cube
    ax.set_axis_off()


def _fit(fig, ax, limits, margin: float = 0.96) -> None:
    """Zoom the 3D box so its projection fills ``margin`` of the axes (matplotlib leaves wide borders round it);
    the box holds every particle, so nothing drawn inside it is cropped."""
    from mpl_toolkits.mplot3d import proj3d

    lo, hi = (np.asarray(v, np.float64) for v in limits)
    corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])  # 8,3
    # a draw sets the projection; the artists do not enter it (the limits are fixed), so they are hidden for it:
    # drawing tens of thousands of particles twice was half of a frame's time
    shown = [a for a in (*ax.collections, *ax.lines, *ax.patches) if a.get_visible()]
    for a in shown:
        a.set_visible(False)
    fig.canvas.draw()
    for a in shown:
        a.set_visible(True)
    px = ax.transData.transform(np.stack(proj3d.proj_transform(*corners.T, ax.get_proj())[:2], 1))  # 8,2
    box = ax.bbox
    centre = np.array([(box.x0 + box.x1) / 2, (box.y0 + box.y1) / 2])
    off = np.abs(px - centre).max(0)  # 2,
    scale = margin * min(box.width / 2 / max(off[0], 1e-6), box.height / 2 / max(off[1], 1e-6))
    ax.set_box_aspect(hi - lo, zoom=scale)  # the projection scales about the axes' centre


def _legend(fig, labels=None, damaged=None, knife=False, board=False, extra=(), fontsize=10):
    """The legend right of the axes: each cluster present (up to LEGEND_PIECES), unassigned, damaged, knife, board."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    dot = lambda c, name: Line2D([], [], ls="", marker="o", ms=7, mfc=c, mec=c, label=name)  # noqa: E731
    handles = []
    if labels is not None:
        ids = np.unique(np.asarray(labels).astype(np.int64))
        for k in ids[ids >= 0][:LEGEND_PIECES]:
            handles.append(dot(_PALETTE[k % len(_PALETTE)], f"piece {k}"))
        if (ids >= 0).sum() > LEGEND_PIECES:
            handles.append(Line2D([], [], ls="", label=f"(+{(ids >= 0).sum() - LEGEND_PIECES}, colours repeat)"))
        if (ids < 0).any():
            handles.append(dot(UNASSIGNED, "unassigned"))
    if damaged is not None and np.asarray(damaged).any():
        handles.append(dot(DAMAGED, "damaged"))
    handles += [dot(c, name) for name, c in extra]
    if knife:
        handles.append(Patch(facecolor=KNIFE_FACE, edgecolor=KNIFE_EDGE, label="knife"))
    if board:
        handles.append(Patch(facecolor=BOARD_FACE, edgecolor=BOARD_EDGE, label="board"))
    if handles:
        fig.legend(handles=handles, loc="center left", bbox_to_anchor=(0.79, 0.5), fontsize=fontsize, frameon=False)


def frame_figure(x, labels=None, *, colors=None, damaged=None, knife=None, knife_edge=None, board_z=None,
                 limits=None, title=None, legend=True, legend_extra=(), view=(25.0, -60.0), size=None,
                 width: int = 800, height: int = 600, dpi: int = 100, knife_color=None):
    """(fig, ax): one frame as a matplotlib Figure (Agg canvas, no pyplot state).  ``x`` (N,3); ``labels`` (N,)
    cluster ids (coloured by cluster_colors, ``damaged`` (N,) bool on top) or ``colors`` (N,3|4); ``knife`` a
    KnifeAction (its edge at ``knife_edge`` (3,) during a cut, else on the board); ``limits`` (lo, hi) the view
    box (default: this frame's points and the board).  ``width`` x ``height`` pixels."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    x = np.asarray(x, np.float64).reshape(-1, 3)  # N,3
    for name, v in (("labels", labels), ("damaged", damaged)):
        if v is not None and np.asarray(v).reshape(-1).shape[0] != len(x):
            raise ValueError(f"frame_figure: got {np.asarray(v).reshape(-1).shape[0]} {name} for {len(x)} points")
    if colors is None:
        colors = cluster_colors(np.full(len(x), -1) if labels is None else labels, damaged)
    colors = _colors(colors, len(x))
    if limits is None:
        limits = row_limits([x], board_z if board_z is not None else float(x[:, 2].min()))
    fig = Figure(figsize=(width / dpi, height / dpi), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0.0, 0.0, 0.79 if legend else 1.0, 0.93 if title else 1.0), projection="3d")
    if size is None:  # about 1.3 particle spacings across at the frame's scale, whatever the particle count
        size = float(np.clip(3.0e4 / max(len(x), 1), 0.8, 14.0)) * (width / 800) ** 2
    _draw(ax, x, colors, view, size, limits, knife, board_z, knife_edge, knife_color)
    _fit(fig, ax, limits)
    if title:
        fig.suptitle(title, y=0.985, fontsize=13)
    if legend:
        _legend(fig, labels, damaged, knife is not None, board_z is not None, legend_extra)
    return fig, ax


def render_frame(x, labels=None, **kwargs) -> np.ndarray:
    """One frame as an (H,W,3) uint8 array (frame_figure's arguments): a gym ``rgb_array``, a GIF frame."""
    fig, _ = frame_figure(x, labels, **kwargs)
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()  # H,W,3


def render_frames(frames: list[dict], board_z: float | None = None, pad: float = 0.02, **kwargs) -> list[np.ndarray]:
    """A sequence: each dict holds render_frame's arguments (``x`` and e.g. labels, knife, title); every frame shares
    one view box over all frames' points (row_limits), so pieces pushed or turned away stay in view."""
    if not frames:
        return []
    bz = board_z if board_z is not None else min(float(np.min(np.asarray(f["x"])[..., 2])) for f in frames)
    limits = row_limits([f["x"] for f in frames], bz, pad)
    return [render_frame(board_z=board_z, limits=limits, **{**kwargs, **f}) for f in frames]


def save_png(img, path) -> Path:
    """An (H,W,3|4) uint8 frame to a PNG."""
    import imageio.v2 as imageio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    imageio.imwrite(path, np.asarray(img))
    return path


def render_particles(x, colors_or_labels, path, title: str | None = None, view=(25.0, -60.0), size: float = 2.0,
                     limits=None, dpi: int = 100, figsize=(5, 5), knife=None, board_z: float | None = None) -> Path:
    """Scatter plot of particles (N,3) into a PNG, coloured by categorical labels (label_colors: 0 grey; the pen's
    strokes, the spoon's chunks) or RGB(A) colours (N,3|4), no legend; frames by cluster id: render_frame."""
    x = np.asarray(x).reshape(-1, 3)
    c = np.asarray(colors_or_labels)
    colors = c if c.ndim == 2 and c.shape[1] in (3, 4) else label_colors(c)
    fig, _ = frame_figure(x, colors=colors, knife=knife, board_z=board_z, limits=limits, title=title, legend=False,
                          view=view, size=size, width=int(figsize[0] * dpi), height=int(figsize[1] * dpi), dpi=dpi)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


def render_sequences(rows, path, board_z: float, view=(25.0, -60.0), size: float = 1.2, panel: float = 1.3,
                     dpi: int = 220, pad: float = 0.02) -> Path:
    """The paper's cutting-sequence figure: one row per episode, one panel per state.  ``rows`` =
    [(row title, [(x (N,3), cluster ids (N,) or RGBA colours (N,4) (a goal: goal_colors), knife action or None,
    caption)])]; every panel of a row shares the row's extent (``row_limits``: pieces pushed or laid down away
    from the object stay in view) and shows the board; a panel with an action shows the knife at the end of that
    cut; a legend below.  ``panel`` inches a panel: 7 columns fit a page width (two-column papers: 3.5 in a column)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    cols = max(len(p) for _, p in rows)
    fig = Figure(figsize=(panel * cols, panel * len(rows) * 1.05 + 0.25), dpi=dpi)
    FigureCanvasAgg(fig)
    ids = []
    for r, (title, panels) in enumerate(rows):
        lo, hi = row_limits([p[0] for p in panels], board_z, pad)
        for c, (x, labels, knife, caption) in enumerate(panels):
            ax = fig.add_subplot(len(rows), cols, r * cols + c + 1, projection="3d")
            _draw(ax, x, _colors(labels, len(np.asarray(x).reshape(-1, 3))), view, size, (lo, hi), knife, board_z)
            ax.set_title(caption, fontsize=6, pad=0)
            if np.asarray(labels).ndim == 1:
                ids.append(np.unique(np.asarray(labels)))
            if c == 0:
                ax.text2D(-0.08, 0.5, title, transform=ax.transAxes, rotation=90, va="center", ha="center",
                          fontsize=7, fontweight="bold")
    width, height = fig.get_size_inches()  # margins in inches: the row titles left, the captions on top, the legend
    fig.subplots_adjust(left=0.22 / width, right=0.995, bottom=0.25 / height, top=1 - 0.16 / height, wspace=0.0,
                        hspace=0.08)
    _sequence_legend(fig, np.unique(np.concatenate(ids)) if ids else None)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


def _sequence_legend(fig, ids) -> None:
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    dot = lambda c, name: Line2D([], [], ls="", marker="o", ms=4, mfc=c, mec=c, label=name)  # noqa: E731
    ids = np.asarray([] if ids is None else ids, np.int64)
    handles = [dot(_PALETTE[k % len(_PALETTE)], f"piece {k}") for k in ids[ids >= 0][:LEGEND_PIECES]]
    handles += [dot(UNASSIGNED, "unassigned / not a goal piece"),
                Patch(facecolor=KNIFE_FACE, edgecolor=KNIFE_EDGE, label="knife"),
                Patch(facecolor=BOARD_FACE, edgecolor=BOARD_EDGE, label="board")]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=5, frameon=False,
               bbox_to_anchor=(0.5, 0.0), handlelength=1.2, columnspacing=1.0)


def write_gif(frames, path, fps: float = 8.0, durations=None) -> Path:
    """GIF from PNG paths or (H,W,3|4) uint8 arrays; frames are padded to the largest size.  ``durations``: seconds
    per frame (e.g. motion frames short, the states after each cut held), else 1 / fps each."""
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
    if durations is None:
        ms = 1000.0 / fps
    else:
        if len(durations) != len(imgs):
            raise ValueError(f"write_gif: {len(durations)} durations for {len(imgs)} frames")
        ms = [1000.0 * float(d) for d in durations]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    imageio.mimsave(path, padded, duration=ms, loop=0)  # ms per frame (imageio >= 2.28)
    return path


def render_objects(path, spacing: float = 0.006, view=(25.0, -60.0)) -> Path:
    """One panel per object of topocut.sim.objects at the nominal pose (core grey, skin orange)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from topocut.sim.objects import OBJECTS, UNSEEN, sample_object

    fig = Figure(figsize=(15, 6.4), dpi=90)
    FigureCanvasAgg(fig)
    for i, name in enumerate(OBJECTS):
        x, mat = sample_object(name, spacing=spacing)
        ax = fig.add_subplot(2, 5, i + 1, projection="3d")
        _draw(ax, x, label_colors(mat), view, 1.0, ((0.35, 0.35, 0.05), (0.65, 0.65, 0.35)))
        ax.set_title(f"{name}{' (unseen)' if name in UNSEEN else ''}\n{len(x)} particles", fontsize=10)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, bbox_inches="tight")
    return path

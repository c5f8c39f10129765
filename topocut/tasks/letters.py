"""Letter goals for cream writing: one stroke polyline per letter -> a bead-shaped point cloud per letter.

A letter lives in a box of width LETTER_ASPECT and height 1 (x right, y up); ``LETTERS[c]`` is
its single stroke, a polyline (m,2) written in that order by the pen without lifting (so a letter
is one cluster).  ``layout`` places a word's letters left to right on the board (letter "up" is
world +y).  ``letter_points`` lays the bead the pen leaves along a stroke: the nozzle's layer
(topocut.sim.tools.nozzle_layer, m points) at every ``pitch`` of arc length, the stroke length the pen
covers while the extruded column grows one spacing (PenConfig.layer_pitch), in one particle layer on
the board.  So the goal holds the pen's m / pitch particles per unit of stroke (its volume flux) in the
nozzle's footprint, and the pen's own bead is what the goal asks for (docs/tasks.md#cream-writing).
"""
from __future__ import annotations

import numpy as np

LETTER_ASPECT = 0.6  # letter width / height


def _arc(cx, cy, rx, ry, a0, a1, n=24) -> np.ndarray:
    t = np.radians(np.linspace(a0, a1, n))
    return np.stack([cx + rx * np.cos(t), cy + ry * np.sin(t)], -1)


def _letters() -> dict[str, np.ndarray]:
    w = LETTER_ASPECT
    bowl = 0.25  # R / P / D bowl radius (height units)
    L = {
        "C": _arc(w / 2, 0.5, w / 2, 0.5, 55, 305),  # opens to the right, written from the top end
        "O": _arc(w / 2, 0.5, w / 2, 0.5, 90, 450, 33),  # closed: first point == last point
        "L": np.array([[0, 1], [0, 0], [w, 0]]),
        "R": np.concatenate([[[0, 0], [0, 1], [w - bowl, 1]], _arc(w - bowl, 0.75, bowl, bowl, 90, -90, 12)[1:-1],
                             [[w - bowl, 0.5], [0.25 * w, 0.5], [w, 0]]]),
        "P": np.concatenate([[[0, 0], [0, 1], [w - bowl, 1]], _arc(w - bowl, 0.75, bowl, bowl, 90, -90, 12)[1:-1],
                             [[w - bowl, 0.5], [0, 0.5]]]),
        "D": np.concatenate([[[0, 0], [0, 1], [w / 2, 1]], _arc(w / 2, 0.5, w / 2, 0.5, 90, -90, 16)[1:-1],
                             [[w / 2, 0], [0, 0]]]),
        "U": np.concatenate([[[0, 1]], _arc(w / 2, w / 2, w / 2, w / 2, 180, 360, 16), [[w, 1]]]),
        "V": np.array([[0, 1], [w / 2, 0], [w, 1]]),
        "W": np.array([[0, 1], [0.25 * w, 0], [0.5 * w, 0.6], [0.75 * w, 0], [w, 1]]),
        "M": np.array([[0, 0], [0, 1], [0.5 * w, 0.4], [w, 1], [w, 0]]),
        "N": np.array([[0, 0], [0, 1], [w, 0], [w, 1]]),
        "Z": np.array([[0, 1], [w, 1], [0, 0], [w, 0]]),
        "S": np.concatenate([_arc(w / 2, 0.75, w / 2, 0.25, 20, 270, 14), _arc(w / 2, 0.25, w / 2, 0.25, 90, -160, 14)[1:]]),
        "J": np.concatenate([[[w, 1]], _arc(w / 2, w / 2, w / 2, w / 2, 0, -180, 16)]),
        "I": np.array([[w / 2, 1], [w / 2, 0]]),
    }
    return {k: np.asarray(v, np.float64) for k, v in L.items()}


LETTERS = _letters()


def layout(word: str, height: float, gap: float, center=(0.5, 0.5)) -> list[np.ndarray]:
    """World (x, y) stroke polylines (m,2) of each letter of ``word``, centred on ``center``."""
    word = word.upper()
    missing = [c for c in word if c not in LETTERS]
    if missing:
        raise ValueError(f"no stroke for letter(s) {missing}; valid letters: {''.join(sorted(LETTERS))}")
    w = LETTER_ASPECT * height
    total = len(word) * w + (len(word) - 1) * gap
    x0 = center[0] - total / 2
    y0 = center[1] - height / 2
    return [LETTERS[c] * height + np.array([x0 + i * (w + gap), y0]) for i, c in enumerate(word)]


def polyline_length(poly) -> float:
    return float(np.linalg.norm(np.diff(np.asarray(poly, np.float64), axis=0), axis=1).sum())


def stations(poly, pitch: float) -> np.ndarray:
    """Points (k,2) at arc length 0, pitch, 2 pitch, ... <= the length of poly (m,2): where the pen lays a layer."""
    poly = np.asarray(poly, np.float64)
    seg = np.diff(poly, axis=0)
    length = np.linalg.norm(seg, axis=1)
    keep = length > 1e-12
    poly, seg, length = np.concatenate([poly[:1], poly[1:][keep]]), seg[keep], length[keep]
    s = np.concatenate([[0.0], np.cumsum(length)])
    t = np.arange(int(np.floor(s[-1] / pitch + 1e-9)) + 1) * pitch
    i = np.clip(np.searchsorted(s, t, side="right") - 1, 0, len(seg) - 1)
    return poly[i] + seg[i] * ((t - s[i]) / length[i])[:, None]


def letter_points(poly, layer, pitch: float, z: float) -> np.ndarray:
    """The bead along stroke poly (m,2): (k * len(layer), 3) points at height z.

    ``layer`` (l,2) or (l,3): the nozzle layer's horizontal offsets, laid at every station (``stations``):
    one particle layer, as the pen lays it (the cream rests where it leaves the nozzle).
    """
    lay = np.asarray(layer, np.float64)[:, :2]  # l,2
    xy = (stations(poly, pitch)[:, None, :] + lay[None]).reshape(-1, 2)  # k*l,2
    return np.concatenate([xy, np.full((len(xy), 1), z)], 1).astype(np.float32)


def pen_bead(spacing: float, pen=None) -> tuple[np.ndarray, float]:
    """(nozzle layer offsets (m,3), pitch) of the pen's bead at particle spacing ``spacing``."""
    from topocut.sim.tools import PenConfig, nozzle_layer

    pen = pen or PenConfig()
    return nozzle_layer(spacing, pen.nozzle_radius), pen.layer_pitch(spacing)


def word_goal(word: str, height: float, gap: float, spacing: float, board_z: float, pen=None,
              center=(0.5, 0.5)) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per-letter goal point clouds (k_i,3): the bead of ``pen`` (a PenConfig; None: the default pen) along each
    letter, one layer on the board at ``board_z``; and the letters' world stroke polylines."""
    strokes = layout(word, height, gap, center)
    layer, pitch = pen_bead(spacing, pen)
    return [letter_points(p, layer, pitch, board_z + spacing / 2) for p in strokes], strokes

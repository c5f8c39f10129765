"""Letter goals for cream writing: one stroke polyline per letter -> a bead-shaped point cloud per letter.

A letter lives in a box of width LETTER_ASPECT and height 1 (x right, y up); ``LETTERS[c]`` is
its single stroke, a polyline (m,2) written in that order by the pen without lifting (so a letter
is one cluster).  ``layout`` places a word's letters left to right on the board (letter "up" is
world +y), ``letter_points`` samples a stroke as the bead a pen leaves: points every ``spacing``
along the polyline, each carrying a small lattice cross-section (``bead`` = lateral x vertical
particle counts) resting on the board.
"""
from __future__ import annotations

import numpy as np

LETTER_ASPECT = 0.6  # letter width / height
# cross-section of the goal bead (particles across x layers): the pen's default bead (nozzle radius 1, extrusion
# 1.5 / pen 1.2 units/s) lays ~6 particles per spacing of stroke, 3 across and 2 high where it piles up
BEAD = (3, 2)


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


def resample_polyline(poly, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every ``spacing`` of arc length along poly (m,2) (both ends kept) and unit tangents; (k,2) each."""
    poly = np.asarray(poly, np.float64)
    seg = np.diff(poly, axis=0)
    length = np.linalg.norm(seg, axis=1)
    keep = length > 1e-12
    poly = np.concatenate([poly[:1], poly[1:][keep]])
    seg, length = seg[keep], length[keep]
    s = np.concatenate([[0.0], np.cumsum(length)])
    k = max(int(round(s[-1] / spacing)), 1)
    t = np.linspace(0.0, s[-1], k + 1)
    i = np.clip(np.searchsorted(s, t, side="right") - 1, 0, len(seg) - 1)
    pts = poly[i] + seg[i] * ((t - s[i]) / length[i])[:, None]
    tan = seg[i] / length[i][:, None]
    return pts, tan


def polyline_length(poly) -> float:
    return float(np.linalg.norm(np.diff(np.asarray(poly, np.float64), axis=0), axis=1).sum())


def letter_points(poly, spacing: float, board_z: float, bead=(2, 2)) -> np.ndarray:
    """The bead along stroke poly (m,2): (k * bead[0] * bead[1], 3) points on the board.

    Along the stroke every ``spacing``; across it ``bead[0]`` points ``spacing`` apart centred on the
    line; vertically ``bead[1]`` layers from half a spacing above the board.
    """
    pts, tan = resample_polyline(poly, spacing)
    nrm = np.stack([-tan[:, 1], tan[:, 0]], -1)  # k,2 in-plane normal of the stroke
    lat = (np.arange(bead[0]) - (bead[0] - 1) / 2) * spacing
    ver = board_z + spacing * (0.5 + np.arange(bead[1]))
    xy = (pts[:, None, :] + lat[None, :, None] * nrm[:, None, :]).reshape(-1, 2)  # k*bw,2
    out = np.concatenate([np.repeat(xy, len(ver), 0), np.tile(ver, len(xy))[:, None]], 1)
    return out.astype(np.float32)


def word_goal(word: str, height: float, gap: float, spacing: float, board_z: float, bead=BEAD,
              center=(0.5, 0.5)) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per-letter goal point clouds (k_i,3) and the letters' world stroke polylines."""
    strokes = layout(word, height, gap, center)
    return [letter_points(p, spacing, board_z, bead) for p in strokes], strokes

"""Band grids for sticks and dice: where to put k bands of width w along one axis of a slab."""
from __future__ import annotations

import itertools

import numpy as np

MIN_FILL = 0.5  # a cell is a goal piece from this share of a full cell's particles (best_grid)


def band_layout(s, lo_face, hi_face, width, count, anchor):
    """Band edges (count+1,) for ``count`` bands of ``width`` along coordinate s, anchored at the +face
    ("hi"), the -face ("lo") or centred on the material ("mid").  Returns (edges, interior edges: the
    cuts needed, i.e. the edges strictly inside (lo_face, hi_face))."""
    if anchor == "hi":
        edges = hi_face - width * np.arange(count, -1, -1)
    elif anchor == "lo":
        edges = lo_face + width * np.arange(count + 1)
    else:
        mid = 0.5 * (np.percentile(s, 5) + np.percentile(s, 95))
        edges = mid + width * (np.arange(count + 1) - count / 2)
    tol = 1e-9
    cuts = [e for e in edges if lo_face + tol < e < hi_face - tol]
    return edges, cuts


def band_index(s, edges):
    """1..len(edges)-1 for s inside band (edges[i], edges[i+1]], 0 outside."""
    k = np.searchsorted(edges, s, side="left")  # edges[k-1] < s <= edges[k]
    k[(s <= edges[0]) | (s > edges[-1])] = 0
    return k


def best_grid(coords, faces, widths, budget, cell_count, min_fill=MIN_FILL, max_bands=6):
    """Choose band counts and anchors along each axis of ``coords`` (N,A) to make as many full cells as the
    cut budget allows.  faces: [(lo, hi)] per axis; widths: band width per axis; cell_count: the particle
    count of a full cell.  A cell is a goal piece iff it holds >= min_fill * cell_count particles.
    Returns (cell labels (N,) 0 = none, [cut positions per axis], chosen (counts, anchors))."""
    A = coords.shape[1]
    best = None
    per_axis = []
    for a in range(A):
        opts = []
        for n in range(1, max_bands + 1):
            for anchor in ("hi", "lo", "mid"):
                edges, cuts = band_layout(coords[:, a], faces[a][0], faces[a][1], widths[a], n, anchor)
                opts.append((n, anchor, edges, cuts))
        per_axis.append(opts)
    for combo in itertools.product(*per_axis):
        ncuts = sum(len(c[3]) for c in combo)
        if ncuts > budget:
            continue
        idx = [band_index(coords[:, a], combo[a][2]) for a in range(A)]
        inside = np.all([i > 0 for i in idx], axis=0)
        key = np.zeros(len(coords), np.int64)
        mult = 1
        for a in range(A):
            key = key + (idx[a] - 1) * mult
            mult *= combo[a][0]
        counts = np.bincount(key[inside], minlength=mult)
        full = np.flatnonzero(counts >= min_fill * cell_count)
        score = (len(full), counts[full].sum(), -ncuts)
        if best is None or score > best[0]:
            best = (score, combo, key, inside, full)
    if not len(best[4]) and min_fill > 0.1:  # an irregular slab (sushi): accept emptier cells rather than none
        return best_grid(coords, faces, widths, budget, cell_count, min_fill / 2, max_bands)
    score, combo, key, inside, full = best
    labels = np.zeros(len(coords), np.int32)
    for i, cell in enumerate(full):
        labels[inside & (key == cell)] = i + 1
    return labels, [c[3] for c in combo], [(c[0], c[1]) for c in combo]

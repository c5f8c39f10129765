"""Consistent cluster ids over an episode.

A new piece keeps the id of the old cluster it overlaps most (Hungarian
matching on the particle-overlap matrix), provided that at least
``min_share`` of the new piece's particles come from that old cluster.  Every
other piece that owns particles gets a fresh id: next_id, next_id + 1, ... in
order of decreasing particle count (ties: smaller centroid x first).  Ids are
never reused within an episode: pass the ``next_id`` returned by the previous
step (the default, previous_labels.max() + 1, forgets ids whose pieces have
vanished since).

``assign_ids`` works on per-piece statistics only (K counts, K centroid sums,
a K x L overlap matrix), which discover() computes on the device; the
matching itself is a tiny host problem.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment


def assign_ids(counts: np.ndarray, sum_x: np.ndarray | None, overlap: np.ndarray | None, used: int,
               next_id: int | None = None, min_share: float = 0.5,
               old_ids: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """Persistent id per raw piece.

    counts (K,) particles per piece; sum_x (K,) sum of their x coordinates (None: no tie-break by
    centroid); overlap (K, L) particles of piece k whose previous id is l (None: no previous labels);
    used: one past the largest previous id; old_ids (L,): the id of each overlap column (None: the
    column index is the id).  Returns (id_of (K,) int64, -1 for empty pieces; next_id).
    """
    counts = np.asarray(counts, np.int64)
    k = len(counts)
    nxt = max(int(used), 0 if next_id is None else int(next_id))
    id_of = np.full(k, -1, np.int64)
    if overlap is not None and k:
        ov = np.asarray(overlap, np.int64).reshape(k, -1)
        # only pairs where the old cluster holds >= min_share of the piece may keep its id: filtering after the
        # matching would let a merged piece win an old id, fail the share, and take the id from a pure piece too
        ov = np.where(ov >= min_share * counts[:, None], ov, 0)
        cols = np.flatnonzero(ov.sum(0) > 0)  # the previous ids some piece may keep
        if len(cols):
            rows, c = linear_sum_assignment(-ov[:, cols])
            o = ov[rows, cols[c]]
            ok = o > 0
            id_of[rows[ok]] = cols[c[ok]] if old_ids is None else np.asarray(old_ids)[cols[c[ok]]]
    cx = np.zeros(k) if sum_x is None else np.asarray(sum_x, np.float64) / np.maximum(counts, 1)
    order = np.lexsort((cx, -counts))
    fresh = order[(id_of[order] < 0) & (counts[order] > 0)]
    id_of[fresh] = nxt + np.arange(len(fresh))
    nxt += len(fresh)
    return id_of, nxt


def match_labels(raw: np.ndarray, previous: np.ndarray | None = None, next_id: int | None = None,
                 positions: np.ndarray | None = None, min_share: float = 0.5) -> tuple[np.ndarray, np.ndarray, int]:
    """Map raw piece indices to persistent ids (numpy version of what discover() does on the device).

    raw: (N,) int, 0..K-1 per particle, -1 unassigned.  previous: (N,) int ids or None.
    Returns (labels (N,) int32, id_of_raw (K,) int64, next_id).
    """
    raw = np.asarray(raw, np.int64)
    k = int(raw.max()) + 1 if (raw >= 0).any() else 0
    prev = None if previous is None else np.asarray(previous, np.int64)
    if prev is not None and prev.shape != raw.shape:
        raise ValueError(f"previous_labels has shape {prev.shape}, expected {raw.shape}")
    used = int(prev.max()) + 1 if prev is not None and len(prev) else 0
    a = raw >= 0
    counts = np.bincount(raw[a], minlength=k)
    sum_x = None if positions is None else np.bincount(raw[a], np.asarray(positions)[a, 0], minlength=k)
    overlap = old_ids = None
    if prev is not None and k:
        ok = a & (prev >= 0)
        old_ids, col = np.unique(prev[ok], return_inverse=True)
        overlap = np.zeros((k, max(len(old_ids), 1)), np.int64)
        np.add.at(overlap, (raw[ok], col.ravel()), 1)
    id_of, nxt = assign_ids(counts, sum_x, overlap, used, next_id, min_share, old_ids)
    labels = np.where(a, id_of[np.maximum(raw, 0)] if k else -1, -1).astype(np.int32)
    return labels, id_of, nxt

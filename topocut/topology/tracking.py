"""Consistent cluster ids over an episode.

A new piece keeps the id of the old cluster it overlaps most (Hungarian
matching on the particle-overlap matrix), provided that at least
``min_share`` of the new piece's particles come from that old cluster.  Every
other piece gets a fresh id: next_id, next_id + 1, ... in order of decreasing
particle count (ties: smaller centroid x first).  Ids are never reused within
an episode: pass the ``next_id`` returned by the previous step (the default,
previous_labels.max() + 1, forgets ids whose pieces have vanished since).
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment


def _new_order(raw: np.ndarray, k: int, x: np.ndarray | None) -> np.ndarray:
    """Deterministic order of raw pieces 0..k-1: by particle count (desc), then centroid x."""
    counts = np.bincount(raw[raw >= 0], minlength=k)
    if x is None:
        cx = np.zeros(k)
    else:
        sums = np.zeros(k)
        np.add.at(sums, raw[raw >= 0], x[raw >= 0, 0])
        cx = sums / np.maximum(counts, 1)
    return np.lexsort((cx, -counts))


def match_labels(raw: np.ndarray, previous: np.ndarray | None = None, next_id: int | None = None,
                 positions: np.ndarray | None = None, min_share: float = 0.5) -> tuple[np.ndarray, np.ndarray, int]:
    """Map raw piece indices to persistent ids.

    raw: (N,) int, 0..K-1 per particle, -1 unassigned.  previous: (N,) int ids or None.
    Returns (labels (N,) int32, id_of_raw (K,) int64, next_id).
    """
    raw = np.asarray(raw, np.int64)
    k = int(raw.max()) + 1 if (raw >= 0).any() else 0
    prev = None if previous is None else np.asarray(previous, np.int64)
    if prev is not None and prev.shape != raw.shape:
        raise ValueError(f"previous_labels has shape {prev.shape}, expected {raw.shape}")
    used = int(prev.max()) + 1 if prev is not None and len(prev) else 0
    nxt = max(used, 0 if next_id is None else int(next_id))
    id_of = np.full(k, -1, np.int64)
    if prev is not None and k:
        ok = (raw >= 0) & (prev >= 0)
        old_ids, old_idx = np.unique(prev[ok], return_inverse=True)
        if len(old_ids):
            overlap = np.zeros((k, len(old_ids)), np.int64)
            np.add.at(overlap, (raw[ok], old_idx), 1)
            sizes = np.bincount(raw[raw >= 0], minlength=k)
            rows, cols = linear_sum_assignment(-overlap)
            for r, c in zip(rows, cols):
                if overlap[r, c] > 0 and overlap[r, c] >= min_share * sizes[r]:
                    id_of[r] = old_ids[c]
    for r in _new_order(raw, k, positions):
        if id_of[r] < 0:
            id_of[r] = nxt
            nxt += 1
    labels = np.where(raw >= 0, id_of[np.maximum(raw, 0)] if k else -1, -1).astype(np.int32)
    return labels, id_of, nxt

"""Action reconstruction: the knife plane separating a predicted cut mask.

The mask convention is topocut.sim.action.cut_mask: 1 on the +n side of the
canonical plane of the action.  Any plane that separates the two classes gives
an action whose cut splits the points exactly as the mask does, so the plane
is recovered by a linear classifier:

  "svm": a linear SVM (max-margin plane; the paper's choice), on isotropically
         normalised coordinates so that angles are preserved;
  "lsq": total least squares through the class boundary: the midpoints of each
         point and its k nearest opposite-class points lie within half a gap of
         the cut; the normal is a principal axis of the tightest such midpoints
         (weighted by inverse gap).  The smallest axis is the plane's normal when
         the boundary spans two directions; on a flat sheet or a line of points
         the boundary is a segment or a point and its smallest axes include the
         sheet's own normal, so the axes are tried smallest first and the first
         whose plane classifies the points (nearly) as well as the best one wins.

``vertical=True`` fits the planes through the vertical (tilt 0: the normal has
no z component), a line in the board's xy plane: the action space of
demonstrations whose cuts are all vertical (slice, stick and dice under the
oracle and MPPI, whose tilt is frozen).  A mask leaves the plane free wherever
the two classes touch along a short boundary (a laid slab cut across, one die
cut from a stick): on the demonstrator's own masks of the stick and dice plans
the free max-margin plane turns 4-9 degrees from the demonstrator's cut on the
second and later cuts, the vertical one 1-4 (docs/policy.md, "The plane from
the mask"; experiments/plane_recovery.py).

A mask with one class only (or too few points of one) has no plane: the
functions return None, meaning "no cut".
"""
from __future__ import annotations

import numpy as np

from topocut.sim.action import KnifeAction

PLANE_METHODS = ("svm", "lsq")


def _normalise(points):
    c = points.mean(0)
    s = float(np.sqrt(((points - c) ** 2).sum(1).mean())) or 1.0
    return c, s


def _svm_plane(points, mask, C: float, vertical: bool = False):
    from sklearn.svm import LinearSVC

    c, s = _normalise(points)
    dims = 2 if vertical else 3  # vertical: a line in xy, the normal's z 0
    clf = LinearSVC(C=C, dual=False, max_iter=5000, tol=1e-6)  # squared hinge, primal solver: converges on separable data
    clf.fit(((points - c) / s)[:, :dims], mask)
    w, b = np.zeros(3), float(clf.intercept_[0])  # w . (x - c)/s + b = 0, w points to class 1
    w[:dims] = clf.coef_[0]
    nrm = np.linalg.norm(w)
    if nrm == 0:
        return None
    n = w / nrm
    point = c - (b * s / nrm) * n  # the plane point closest to the centroid
    return n, point


def _lsq_plane(points, mask, keep: float, k: int = 3, vertical: bool = False):
    from scipy.spatial import cKDTree

    if vertical:  # the boundary of the points' footprint on the board: the plane through it is vertical
        points = points * np.array([1.0, 1.0, 0.0])
    a, b = points[mask == 0], points[mask == 1]
    k = min(k, len(a), len(b))
    da, ia = cKDTree(b).query(a, k)  # each class-0 point's k nearest class-1 points
    db, ib = cKDTree(a).query(b, k)
    da, ia, db, ib = (v.reshape(v.shape[0], k) for v in (da, ia, db, ib))
    mids = np.concatenate([((a[:, None] + b[ia]) / 2).reshape(-1, 3), ((b[:, None] + a[ib]) / 2).reshape(-1, 3)])
    gaps = np.concatenate([da.ravel(), db.ravel()])  # M
    sel = gaps <= np.quantile(gaps, keep)  # the pairs straddling the boundary most tightly
    m, g = mids[sel], gaps[sel]
    if len(m) < 3:
        return None
    # a midpoint's offset from the plane is at most half its gap: weight close pairs more
    w = 1.0 / (g + 0.1 * np.median(g) + 1e-12)
    point = (w[:, None] * m).sum(0) / w.sum()
    axes = np.linalg.svd((m - point) * np.sqrt(w)[:, None], full_matrices=True)[2][::-1]  # smallest variance first
    side = mask.astype(bool)
    scores = []
    if vertical:  # the flattened points' own normal (z) splits nothing
        axes = [n for n in axes if abs(n[2]) < 0.5]
    for n in axes:
        if n @ (b.mean(0) - a.mean(0)) < 0:  # orient towards class 1
            n = -n
        scores.append((float((((points - point) @ n > 0) == side).mean()), n))
    top = max(acc for acc, _ in scores)
    best = next(n for acc, n in scores if acc >= top - 0.01)  # degenerate boundaries: the first axis that separates
    return best, point


def fit_plane(points, mask, method: str = "svm", min_points: int = 3, C: float = 100.0, keep: float = 0.1,
              vertical: bool = False):
    """Plane (normal (3,), point (3,)) with class 1 on the +normal side, or None for a one-class mask;
    ``vertical``: among the vertical planes only (normal[2] = 0)."""
    if method not in PLANE_METHODS:
        raise ValueError(f"plane method={method!r} is not valid; choose one of {', '.join(PLANE_METHODS)}")
    pts = np.asarray(points, dtype=np.float64)
    m = np.asarray(mask).astype(np.int64).reshape(-1)
    if pts.shape[0] != m.shape[0]:
        raise ValueError(f"points ({pts.shape[0]}) and mask ({m.shape[0]}) differ in length")
    n1 = int(m.sum())
    if min(n1, len(m) - n1) < min_points:
        return None
    return _svm_plane(pts, m, C, vertical) if method == "svm" else _lsq_plane(pts, m, keep, vertical=vertical)


def action_from_mask(points, mask, method: str = "svm", board_z: float = 0.05, max_tilt_deg: float = 75.0,
                     **kw) -> KnifeAction | None:
    """The canonical KnifeAction whose plane separates ``mask``; None when no cut can be made:
    a one-class mask, or a plane tilted more than ``max_tilt_deg`` from vertical (a near-horizontal
    plane, which a downward knife cannot cut)."""
    plane = fit_plane(points, mask, method, **kw)
    if plane is None:
        return None
    try:
        action = KnifeAction.from_plane(plane[0], plane[1], board_z)
    except ValueError:
        return None
    return action if abs(np.degrees(action.tilt)) <= max_tilt_deg else None

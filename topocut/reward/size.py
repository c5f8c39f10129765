"""Pose-invariant size descriptor of a piece: principal extents and volume from the particle count.

The spectral descriptor (topocut.reward.spectral) is scale-free: it sees the shape, not its size.  The
task's own parameters (slice thickness, stick width, die size) are sizes, so the distance adds terms that
measure them directly, invariant to rigid motions and to the point density:

* particle spacing s: the median distance of a particle to its 4 nearest neighbours, divided by
  ``NN_RATIO`` (0.97: the value of that median on the simulator's jittered lattice, ±0.25 s per axis,
  for slabs of 2-8 layers and blocks, within ±2%), so s is the lattice spacing for any density.  Or s given:
  where the caller knows the spacing every piece was made at (topocut.reward.distance_matrix(spacing=): the pen's
  and the spoon's scenes), s is that spacing.  The estimate is calibrated on 3-D lattices and is not that spacing
  for clouds that are not: a one-particle-layer bead of cream lies at 0.57-0.72 spacings, depending on how its
  stroke runs across the nozzle's pattern, and particles that a collider put back on its surface crowd there
  without the material being compressed (docs/tasks.md, cream writing and ice-cream scooping);
* volume V = N s^3 (each particle stands for one lattice cell: the solver gives it the volume spacing^3);
* principal extents e_1 <= e_2 <= e_3: e_k = sqrt(12 c_k + s^2), c_k the eigenvalues of the points'
  covariance.  For a box of side L filled by a lattice of n = L / s layers the variance along the side is
  s^2 (n^2 - 1) / 12, so e = n s = L exactly, at any density; for other shapes e is the side of the box with
  the same second moment.

* fill phi = V / (e_1 e_2 e_3): 1 for a box, pi/6 for a sphere, 1/2 for a wedge whose thickness goes to 0.

size distance  d_size = a * sum_k (log e_xk - log e_yk)^2 + b * (log phi_x - log phi_y)^2   (a = size_weight,
b = fill_weight).  A slab of thickness r t against the goal slab of thickness t: d_size = a log(r)^2 (its
fill is the goal's); a wedge of the same volume, its thickness varying along the slab, has a larger thinnest
extent *and* a smaller fill, so it is farther from the goal than a slab of the same thinnest extent.
Extents and fill together fix the volume (V = phi e_1 e_2 e_3).

* thickness profile: the piece's thickness along its thinnest principal axis, column by column: the
  plane of the two other axes is binned into square cells of side 2 s (a grid at the centroid), each
  cell's thickness is sqrt(12 var + s^2) of the coordinate along the thinnest axis (n layers -> n s, as
  for the extents; a second moment, not max - min, so that it does not depend on how the cut planes meet the lattice), and the
  profile is ``PROFILE_QUANTILES`` quantiles (10-90%) of the thickness over the particles (a particle carries
  its cell's value; columns of < 3 particles left out).  A slab has one thickness everywhere; a wedge cut by a yawed knife has the same mean
  thickness but a spread of them, which its extents and fill barely show.

d_size += p * mean_q (log q_xq - log q_yq)^2  (p = profile_weight), when the goal piece y is a slab
(e_2 >= PROFILE_ASPECT e_1: its thinnest axis is well defined); a slab r times the goal's thickness:
d_size = (a + p) log(r)^2.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

NN_RATIO = 0.97  # median 4-NN distance / lattice spacing on a jittered lattice (jitter 0.25 spacing)
NN_K = 4
SPACING_QUERIES = 8192  # particles whose neighbour distances estimate the spacing (all of a smaller piece)
PROFILE_QUANTILES = 8
PROFILE_ASPECT = 1.5  # the profile term counts when the goal piece's e_2 >= 1.5 e_1 (a slab)


def particle_spacing(points: np.ndarray) -> float:
    """The lattice spacing the particles were sampled at, from their nearest-neighbour distances: the median
    over every particle, or over SPACING_QUERIES of them drawn from a larger piece (a fixed seed; each against all
    particles; a stride would alias with the lattice and over-count the boundary layers).  At 128³ the uncut stock holds ~10^5 particles and querying them all was most of
    the reward's time; the sampled median is within 0.2% of the full one (tests/test_reward.py)."""
    p = np.asarray(points, np.float64)
    if len(p) < 2:
        return 0.0
    k = min(NN_K, len(p) - 1)
    queries = p if len(p) <= SPACING_QUERIES else p[np.random.default_rng(0).choice(len(p), SPACING_QUERIES,
                                                                                 replace=False)]
    # the sliding-midpoint tree without the median splits: the same exact neighbours, built ~2.5x faster (the
    # build over the whole stock was half of this function at 128^3)
    d = cKDTree(p, balanced_tree=False, compact_nodes=False).query(queries, k + 1)[0][:, 1:]
    return float(np.median(d) / NN_RATIO)


def set_spacing(spacings, counts) -> float:
    """One particle spacing for pieces sampled together (a scene's fragments, a goal's pieces and offcuts): the
    median of the pieces' own estimates (particle_spacing) weighted by their particle counts, so the large pieces
    decide.  A chip's or a torn sheet's own estimate runs high, its neighbours lying in a layer or a thread (dice /
    burger / 0 at 128^3: a 48-particle sheet read ~1.5 spacings, its volume 3.4x its material).  0 when no piece
    has an estimate."""
    s, n = np.asarray(spacings, np.float64).reshape(-1), np.asarray(counts, np.float64).reshape(-1)
    ok = np.isfinite(s) & (s > 0) & (n > 0)
    if not ok.any():
        return 0.0
    s, n = s[ok], n[ok]
    order = np.argsort(s, kind="stable")
    c = np.cumsum(n[order])
    return float(s[order][np.searchsorted(c, 0.5 * c[-1])])


def material_volumes(counts, spacing: float) -> np.ndarray:
    """Pieces' material (F,): their particle counts times one lattice cell (spacing^3, their set's: set_spacing).
    MPM particles carry fixed mass, so a stretched or torn piece holds what its particles hold, whatever its shape."""
    return np.asarray(counts, np.float64).reshape(-1) * float(spacing) ** 3


def thickness_profile(local: np.ndarray, s: float, cell: float, q: int = PROFILE_QUANTILES) -> np.ndarray:
    """Quantiles (q,) of the thickness along local[:, 0] over columns cell x cell in (local[:, 1], local[:, 2]);
    a column's thickness is sqrt(12 var + s^2) of its particles' local[:, 0] (n lattice layers -> n s)."""
    ij = np.floor(local[:, 1:] / cell).astype(np.int64)
    ij -= ij.min(0)  # one integer key per column (a 1-D unique: rows would be sorted as tuples, ~5x slower)
    col = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    if col.max(initial=0) >= 4 * len(col):  # a sparse key range: compact it (a sort); else the keys index bins as
        col = np.unique(col, return_inverse=True)[1].reshape(-1)  # they are (bincount sums in the same order)
    n = np.bincount(col).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):  # empty bins of the raw keys: never read below
        m1 = np.bincount(col, local[:, 0]) / n
        m2 = np.bincount(col, local[:, 0] ** 2) / n
    thick = np.sqrt(np.maximum(12.0 * (m2 - m1 ** 2), 0.0) + s ** 2)
    keep = n[col] >= 3  # a column of one or two particles (a corner clipped by the grid) says nothing
    thick = thick[col][keep] if keep.any() else thick[col]  # each particle carries its column's value
    return np.quantile(thick, 0.1 + 0.8 * (np.arange(q) + 0.5) / q)  # the 10-90% range: robust to the rims


def size_descriptor(points, spacing: float | None = None, profile: bool = True) -> np.ndarray:
    """(e_1, e_2, e_3, V, thickness profile (PROFILE_QUANTILES,), s) of a piece (N,3); extents sorted, s its
    particle spacing.
    ``profile=False``: the profile left NaN (size_distance then needs profile_weight 0)."""
    p = np.asarray(points, np.float64)
    s = particle_spacing(p) if spacing is None else float(spacing)
    if len(p) < 4 or not s > 0:
        return np.concatenate([[s, s, s, len(p) * s ** 3], np.full(PROFILE_QUANTILES, s), [s]])
    c, vec = np.linalg.eigh(np.cov(p.T, bias=True))  # ascending: vec[:, 0] the thinnest axis
    e = np.sqrt(np.maximum(12.0 * c, 0.0) + s ** 2)
    prof = thickness_profile((p - p.mean(0)) @ vec, s, 2.0 * s) if profile else np.full(PROFILE_QUANTILES, np.nan)
    return np.concatenate([e, [len(p) * s ** 3], prof, [s]])


def size_descriptors(clouds: list, fn=size_descriptor) -> list:
    """fn (default size_descriptor) of each cloud, in threads (the KD-tree queries and the sorts release the GIL),
    BLAS on one thread (``one_blas_thread``)."""
    from topocut.utils.runtime import host_map

    return host_map(fn, clouds)


def size_distance(sx, sy, size_weight: float = 3.0, fill_weight: float = 3.0, profile_weight: float = 3.0,
                  tolerance: float = 0.0):
    """d_size between two size descriptors (..., 5 + PROFILE_QUANTILES); broadcasts.  ``tolerance``: an extent or a
    profile thickness within this many of the goal's (sy's) particle spacings of the goal's costs nothing, and only
    the excess counts beyond (reward.size_tolerance, docs/reward.md#resolution)."""
    tiny = 1e-30
    sx, sy = np.asarray(sx, np.float64), np.asarray(sy, np.float64)
    lx, ly = np.log(np.maximum(sx, tiny)), np.log(np.maximum(sy, tiny))
    q = slice(4, 4 + PROFILE_QUANTILES)
    ex, eq = sx[..., :3], sx[..., q]
    if tolerance:  # x's extents and thicknesses moved towards the goal's by up to tolerance spacings
        band = tolerance * sy[..., -1:]
        ex = _within(ex, sy[..., :3], band)
        eq = _within(eq, sy[..., q], band)
    le = np.log(np.maximum(ex, tiny)) - ly[..., :3]
    lphi = (lx[..., 3] - lx[..., :3].sum(-1)) - (ly[..., 3] - ly[..., :3].sum(-1))
    lq = np.log(np.maximum(eq, tiny)) - ly[..., q]
    # the profile needs a well-defined thinnest axis: only for goal pieces (y) at least PROFILE_ASPECT times as
    # wide as thick (slabs).  A stick's or a die's thinnest axis is any direction in a square cross-section
    # and columns along it would see the section at an arbitrary angle.
    flat = sy[..., 1] >= PROFILE_ASPECT * sy[..., 0]
    d = size_weight * (le ** 2).sum(-1) + fill_weight * lphi ** 2
    # the profile term only where it counts (a NaN profile, size_descriptor(profile=False), is never read there)
    return d + profile_weight * np.where(flat, (lq ** 2).mean(-1), 0.0) if profile_weight else d


def _within(x, y, band):
    """x moved towards y by up to ``band`` (never past it): the part of |x - y| beyond the band, on x's side."""
    return y + np.sign(x - y) * np.maximum(np.abs(x - y) - band, 0.0)

"""The size terms at a known particle spacing (topocut.reward.distance_matrix(spacing=); the pen's and the spoon's
tasks): the volume is the particle count times spacing^3 whatever the positions, the extents sqrt(12 var + s^2) with
that s; against closed forms worked out by hand.  spacing=None (the knife tasks) keeps the estimate: its numbers are
tests/test_reward*.py's and tests/test_answer_key.py's, bit for bit."""
import math

import numpy as np
import pytest

from topocut.reward import distance_matrix, piece_distance, spectral_distance
from topocut.reward.size import particle_spacing, size_descriptor, size_distance

S = 0.01


def _layer(staggered: bool) -> np.ndarray:
    """One particle layer (z = 0): 20 columns 0.8 S apart along x (the pen's layer pitch) by 3 rows S apart in y
    (60 particles); ``staggered``: the middle row moved half a pitch along x (the same material laid differently)."""
    px = 0.8 * S
    p = np.stack(np.meshgrid(np.arange(20) * px, [-S, 0.0, S], [0.0], indexing="ij"), -1).reshape(-1, 3)
    if staggered:
        p[p[:, 1] == 0.0, 0] += 0.5 * px
    return p


def test_a_layer_laid_differently_has_the_same_volume_and_the_extents_of_its_moments():
    a, b = _layer(False), _layer(True)
    # by hand: z is one layer (variance 0: e1 = s); the rows -S, 0, S (variance 2 S^2 / 3: e2 = sqrt(8 + 1) S = 3 S);
    # along x 20 points 0.8 S apart (variance 0.64 S^2 (20^2 - 1) / 12), the staggered middle row adds the variance
    # of the row offsets {0, 0.4 S, 0}: (2 / 9) 0.16 S^2; no covariance (the offsets do not follow y)
    e3_a = math.sqrt(0.64 * 399 + 1) * S
    e3_b = math.sqrt(0.64 * 399 + 12 * (2 / 9) * 0.16 + 1) * S
    for p, e3 in ((a, e3_a), (b, e3_b)):
        d = size_descriptor(p, S)
        np.testing.assert_allclose(d[:4], [S, 3 * S, e3, 60 * S ** 3], rtol=1e-9)
        np.testing.assert_allclose(d[4:], S, rtol=1e-9)  # every column one layer thick
    # d_size: only e3 differs; the fill takes its difference (the same volume); the profiles agree (a is flat:
    # e2 = 3 e1 >= 1.5 e1, so the profile counts, and is s everywhere) -> (3 + 3) (log e3_b / e3_a)^2
    want = 6 * math.log(e3_b / e3_a) ** 2
    assert float(size_distance(size_descriptor(b, S), size_descriptor(a, S))) == pytest.approx(want, rel=1e-6)
    assert want < 1e-5
    # the estimate (the median 4-NN distance / 0.97) is 1.03 S for one and 1.11 S for the other: a 25% volume
    # difference between the same 60 particles' worth of material
    assert particle_spacing(a) / S == pytest.approx(1.0 / 0.97, rel=1e-6)
    assert particle_spacing(b) / S > 1.1
    assert float(size_distance(size_descriptor(b), size_descriptor(a))) > 0.05


def test_distance_matrix_takes_the_spacing_for_both_sides_and_caches_apart():
    a, b = _layer(False), _layer(True)
    before = float(distance_matrix([b], [a])[0, 0])  # the estimate: goal a's size descriptor cached
    known = float(distance_matrix([b], [a], spacing=S)[0, 0])
    spec = spectral_distance(b, a)
    assert known - spec == pytest.approx(float(size_distance(size_descriptor(b, S), size_descriptor(a, S))), abs=1e-9)
    assert before - spec == pytest.approx(float(size_distance(size_descriptor(b), size_descriptor(a))), abs=1e-9)
    assert float(distance_matrix([b], [a])[0, 0]) == before  # the known spacing did not overwrite the cached goal
    assert piece_distance(b, a, spacing=S) == known
    with pytest.raises(ValueError, match="spacing=0"):
        distance_matrix([b], [a], spacing=0.0)


def test_a_box_pressed_together_keeps_its_volume_and_pays_in_extents_and_fill():
    """A 12 x 8 x 4 lattice box whose particles are pressed towards its centre by k (none lost, as particles a tool
    put back on its surface crowd there): at the known spacing its volume stays N s^3 and its extents are
    e_n = s sqrt(k^2 (n^2 - 1) + 1) for n layers, so d_size = 3 sum_n (log e_n / n s)^2 (extents)
    + 3 (sum_n log e_n / n s)^2 (fill: the same volume in a smaller box) + 3 (log e_4 / 4 s)^2 (profile along the
    thinnest side, every column a full stack).  The estimate scales the spacing by k too: 12 log(k)^2."""
    g = np.stack(np.meshgrid(np.arange(12), np.arange(8), np.arange(4), indexing="ij"), -1).reshape(-1, 3) * S
    k = 0.965
    p = (g - g.mean(0)) * k + g.mean(0)
    dlog = np.log([math.sqrt(k * k * (n * n - 1) + 1) / n for n in (4, 8, 12)])
    want = 3 * (dlog ** 2).sum() + 3 * dlog.sum() ** 2 + 3 * dlog[0] ** 2
    assert float(size_distance(size_descriptor(p, S), size_descriptor(g, S))) == pytest.approx(want, rel=1e-6)
    assert size_descriptor(p, S)[3] == size_descriptor(g, S)[3] == pytest.approx(len(g) * S ** 3)
    assert float(size_distance(size_descriptor(p), size_descriptor(g))) == pytest.approx(12 * math.log(k) ** 2,
                                                                                        rel=1e-6)

"""Host shortcuts on every cut of MPPI's rollouts and every score give exactly what they replace:
``plane_splits`` (a float32 test of the plane's sides, falling back to ``cut_mask``), ``fragments`` (one stable
sort of 16-bit labels), the blade's centring band (``pieces._in_band``: candidates first) and the engine's
``piece_agreement`` (one table of (label, piece) overlaps)."""
import numpy as np
import pytest

import topocut.sim.action as action_mod
from topocut.episode.scoring import fragments, piece_agreement
from topocut.sim.action import KnifeAction, cut_mask, plane_splits
from topocut.sim.pieces import _in_band


def _rule(x, a, board_z=0.05):
    m = cut_mask(x, a, board_z)
    return bool(0 < m.sum() < len(m))


def test_plane_splits_is_cut_masks_rule_and_falls_back_only_near_the_plane(monkeypatch):
    rng = np.random.default_rng(0)
    x = (rng.random((5000, 3)) * [0.1, 0.1, 0.05] + [0.45, 0.45, 0.05]).astype(np.float32)  # a 10 cm box
    calls = []
    monkeypatch.setattr(action_mod, "cut_mask", lambda *a, **k: calls.append(1) or cut_mask(*a, **k))
    cases = []
    for _ in range(40):  # planes through the box, and beside it on either side (the yaw sets which side is +n)
        yaw, tilt = rng.uniform(-1.5, 1.5), rng.uniform(-0.4, 0.4)
        for off in (rng.uniform(0.46, 0.54), 0.3, 0.7):
            cases.append(KnifeAction(off, rng.uniform(0.46, 0.54), yaw=yaw, tilt=tilt))
    for a in cases:
        assert plane_splits(x, a) == _rule(x, a), a
    assert calls == []  # every one of them clear of the plane by far more than float32 rounding
    # the box's face a float32 step past the plane x = 0.45 (every point on its +n side: False), then one point
    # moved onto float32(0.45), 1.2e-8 short of it (True): both within rounding, so cut_mask decides
    a = KnifeAction(0.45, 0.5)
    past = x.copy()
    past[0, 0] = np.nextafter(np.float32(0.45), np.float32(1))  # the rest lie 1.9e-5 or more past the plane
    on = past.copy()
    on[0, 0] = np.float32(0.45)
    assert (_rule(past, a), _rule(on, a)) == (False, True)
    assert (plane_splits(past, a), plane_splits(on, a)) == (False, True)
    assert len(calls) == 2
    assert plane_splits(x.astype(np.float64), cases[0]) == _rule(x, cases[0])  # float64 input: cut_mask
    assert plane_splits(np.zeros((0, 3), np.float32), cases[0]) is False


@pytest.mark.parametrize("top", [5, 40_000], ids=["16-bit", "wider"])
def test_fragments_are_each_labels_points_in_their_order(top):
    rng = np.random.default_rng(1)
    labels = rng.choice(np.array([-1, 0, 2, 3, top], np.int64), 3000, p=[0.1, 0.4, 0.3, 0.199, 0.001])
    labels[:3] = 3  # a piece of 3 points: below min_points
    labels[labels == 3] = np.where(np.arange((labels == 3).sum()) < 3, 3, 0)
    x = rng.random((3000, 3)).astype(np.float32)
    got = fragments(x, labels.astype(np.int32), min_points=4)
    want = [x[labels == c] for c in sorted(set(labels.tolist())) if c >= 0 and (labels == c).sum() >= 4]
    assert len(got) == len(want) and len(want) >= 3
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)


def test_in_band_is_the_term_by_term_rule_on_every_particle_and_at_its_edges():
    rng = np.random.default_rng(2)
    for _ in range(30):
        nrm = rng.normal(size=3)
        nrm /= np.linalg.norm(nrm)
        p0 = rng.uniform(0.2, 0.8, 3)
        x = rng.uniform(0.0, 1.0, (4000, 3))
        # particles on the band's edges and a rounding step either side of them (on the plane's normal through p0)
        t = np.concatenate([[-0.01, 0.01], np.nextafter(0.01, [0, 1]), -np.nextafter(0.01, [0, 1]), [0.0]])
        x[:len(t)] = p0 + t[:, None] * nrm
        r = x - p0
        want = np.flatnonzero(np.abs(r[:, 0] * nrm[0] + r[:, 1] * nrm[1] + r[:, 2] * nrm[2]) <= 0.01)
        np.testing.assert_array_equal(_in_band(x, p0, nrm, 0.01), x[want])  # the particles, in their order
        assert 1 <= len(want) < len(x)
    far = np.array([[5.0, 5.0, 5.0]])  # nothing within the band: empty
    assert _in_band(far, np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.01).shape == (0, 3)


def _agreement_by_masks(labels, piece, min_points=4):
    """The IoU rule worked out label by label with boolean masks."""
    n_sim = sum(int((piece == p).sum() >= min_points) for p in np.unique(piece))
    worst = 1.0
    if not (labels >= 0).any():
        return n_sim, float("nan")
    for lab in np.unique(labels[labels >= 0]):
        m = labels == lab
        if m.sum() < min_points:
            continue
        over = [(int((m & (piece == p)).sum()), -p) for p in np.unique(piece)]
        i, p = max(over)  # the most overlapped piece, the lowest id of equals
        worst = min(worst, i / int((m | (piece == -p)).sum()))
    return n_sim, worst


@pytest.mark.parametrize("ids", ["dense", "sparse"])
def test_piece_agreement_is_the_worst_iou_by_masks(ids):
    rng = np.random.default_rng(3)
    for _ in range(20):
        piece = rng.integers(0, rng.integers(1, 7), 2000)
        labels = np.where(rng.random(2000) < 0.95, piece + (rng.random(2000) < 0.1), -1)
        labels[rng.random(2000) < 0.002] = 9  # a tiny label: below min_points, not judged
        if ids == "sparse":
            labels = np.where(labels >= 0, labels * 1_000_003, -1)  # cluster ids past the dense table
        got = piece_agreement(labels, piece)
        want = _agreement_by_masks(labels, piece)
        assert got[0] == want[0] and got[1] == pytest.approx(want[1], rel=1e-12)
    assert np.isnan(piece_agreement(np.full(10, -1), np.zeros(10, int))[1])

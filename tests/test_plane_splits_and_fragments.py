"""Two host shortcuts on every cut of MPPI's rollouts and every score give exactly what they replace:
``plane_splits`` (a float32 test of the plane's sides, falling back to ``cut_mask``) and ``fragments`` (one stable
sort of 16-bit labels)."""
import numpy as np
import pytest

import topocut.sim.action as action_mod
from topocut.episode.scoring import fragments
from topocut.sim.action import KnifeAction, cut_mask, plane_splits


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

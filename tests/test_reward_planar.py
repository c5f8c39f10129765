"""The in-plane misfit and handedness (topocut.reward.planar): an L against itself moved on the board, against its
mirror image, and a brute-force check of the yaw search."""
import numpy as np
import pytest

from topocut.reward import RewardConfig, handedness, planar_misfit


def dense(poly, step=0.001) -> np.ndarray:
    """Points (n,2) every ~step along poly (m,2)."""
    poly = np.asarray(poly, np.float64)
    out = [a + (b - a) * np.arange(k)[:, None] / k
           for a, b in zip(poly[:-1], poly[1:]) for k in [int(np.ceil(np.linalg.norm(b - a) / step))]]
    return np.concatenate(out + [poly[-1:]])


L = dense(np.array([[0, 1], [0, 0], [0.6, 0]]) * 0.12)  # n,2: stem 12 cm, foot 7.2 cm


def rotate(x, deg):
    t = np.radians(deg)
    return x @ np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]]).T


def brute_misfit(x, y, step_deg=0.1):
    """The definition by exhaustion: every yaw on a 0.1° grid, all pairwise distances."""
    x, y = x - x.mean(0), y - y.mean(0)
    best = np.inf
    for t in np.arange(0, 360, step_deg):
        D = np.linalg.norm(rotate(x, t)[:, None] - y[None], axis=-1)  # n,m
        best = min(best, 0.5 * ((D.min(1) ** 2).mean() + (D.min(0) ** 2).mean()))
    return np.sqrt(best) / np.sqrt(((y ** 2).sum(1)).mean())


def test_L_moved_on_the_board_fits_and_is_not_mirrored():
    # a yaw off the search grid (5° steps, refined in 0.5° steps): at most 0.25° off, i.e. <= r * 0.0044 of misfit
    moved = rotate(L, 37.3) + [0.31, -0.2]
    assert planar_misfit(moved, L) < 0.005
    assert planar_misfit(L + [0.05, 0.02], L) < 1e-9  # a shift alone: centroids align it exactly
    assert handedness(moved, L) == 0.0
    # z is the board's normal: a cloud lifted or with a height profile is the same letter
    lifted = np.concatenate([moved, np.linspace(0.05, 0.07, len(moved))[:, None]], 1)
    assert planar_misfit(lifted, L) == pytest.approx(planar_misfit(moved, L), abs=1e-12)


def test_mirrored_L_costs_and_matches_the_brute_force_search():
    mirror = L * [-1, 1]
    expect = brute_misfit(mirror, L)
    assert expect > 0.2  # no turn on the board puts the foot of ⅃ where L's is
    assert planar_misfit(mirror, L) == pytest.approx(expect, abs=0.002)
    assert planar_misfit(mirror, L, mirror=True) < 1e-9  # its mirror image is L
    assert handedness(rotate(mirror, 80) + 0.4, L) == pytest.approx(expect, abs=0.002)


def test_a_letter_with_a_mirror_axis_has_no_handedness():
    V = dense(np.array([[0, 1], [0.3, 0], [0.6, 1]]) * 0.12)
    assert handedness(V * [-1, 1], V) < 1e-9
    t = np.radians(np.linspace(55, 305, 60))  # symmetric about the horizontal axis
    C = 0.06 * np.stack([np.cos(t), np.sin(t)], -1)
    assert handedness(C * [-1, 1], C) < 1e-9  # mirrored C = C turned 180° (on the yaw grid)


def test_bad_input_names_the_argument():
    with pytest.raises(ValueError, match="x: expected a non-empty"):
        planar_misfit(np.zeros((0, 3)), L)
    with pytest.raises(ValueError, match="y: all points coincide"):
        planar_misfit(L, np.zeros((5, 2)))
    with pytest.raises(ValueError, match=r"reward\.handedness_weight=-1"):
        RewardConfig(handedness_weight=-1).validate()

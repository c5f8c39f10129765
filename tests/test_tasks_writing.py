"""Cream writing: letter goals (hand-checked geometry), the pen's extrusion and stroke clusters."""
import numpy as np
import pytest

from topocut.tasks.config import PenConfig
from topocut.tasks.letters import LETTER_ASPECT, LETTERS, layout, letter_points, polyline_length, word_goal


def test_letter_L_bead_geometry():
    h, s, bz = 0.1, 0.01, 0.05
    (poly,) = layout("L", h, 0.05, center=(0.5, 0.5))
    w = LETTER_ASPECT * h  # 0.06
    np.testing.assert_allclose(poly, [[0.47, 0.55], [0.47, 0.45], [0.53, 0.45]], atol=1e-12)
    assert polyline_length(poly) == pytest.approx(h + w)
    pts = letter_points(poly, s, bz, bead=(3, 2))
    assert len(pts) == (round((h + w) / s) + 1) * 3 * 2  # 17 stations x 3 across x 2 layers
    np.testing.assert_allclose(np.unique(np.round(pts[:, 2].astype(float), 6)), [bz + 0.005, bz + 0.015])
    # every point lies within one spacing of the stroke (lateral offsets are -s, 0, +s)
    xy = pts[:, :2]
    d_stem = np.where((xy[:, 1] >= 0.45) & (xy[:, 1] <= 0.55), np.abs(xy[:, 0] - 0.47), np.inf)
    d_foot = np.where((xy[:, 0] >= 0.47) & (xy[:, 0] <= 0.53), np.abs(xy[:, 1] - 0.45), np.inf)
    assert np.minimum(d_stem, d_foot).max() <= s + 1e-6


def test_word_layout_and_closed_O():
    h, gap = 0.12, 0.06
    strokes = layout("CORL", h, gap)
    starts = [p[:, 0].min() for p in strokes]
    assert np.diff([strokes[i][0, 0] - LETTERS[c][0, 0] * h for i, c in enumerate("CORL")]) == pytest.approx(
        [LETTER_ASPECT * h + gap] * 3)
    assert min(starts) == pytest.approx(0.5 - (4 * LETTER_ASPECT * h + 3 * gap) / 2, abs=1e-3)
    np.testing.assert_allclose(strokes[1][0], strokes[1][-1], atol=1e-12)  # O ends where it starts
    # O is an ellipse with semi-axes (w/2, h/2): Ramanujan's perimeter within 1% of the 32-gon
    a, b = LETTER_ASPECT * h / 2, h / 2
    ram = np.pi * (3 * (a + b) - np.sqrt((3 * a + b) * (a + 3 * b)))
    assert polyline_length(strokes[1]) == pytest.approx(ram, rel=0.01)
    goals, _ = word_goal("CORL", h, gap, 0.01, 0.05)
    assert [len(g) for g in goals] == [(round(polyline_length(p) / 0.01) + 1) * 6 for p in strokes]


def test_identical_strokes_score_the_full_reward_per_letter():
    from topocut.tasks.writing_scene import letter_rewards

    goals, _ = word_goal("LO", 0.12, 0.06, 0.01, 0.05)
    x = np.concatenate(goals[::-1])  # strokes written in the other order: matching pairs them up
    stroke = np.repeat([0, 1], [len(goals[1]), len(goals[0])])
    res = letter_rewards(x, stroke, goals)
    assert res["per_letter"] == pytest.approx([1.0, 1.0]) and sorted(res["matching"]) == [(0, 1), (1, 0)]


@pytest.fixture(scope="module")
def pen():
    from topocut.sim import SimConfig
    from topocut.sim.pen import CreamPen

    return CreamPen(SimConfig(n_grid=48), PenConfig(max_particles=2000, settle_substeps=200), batch_size=1)


def test_extrusion_rate_position_and_velocity(pen):
    pen.reset((0.4, 0.5))
    vel = np.array([[0.6, -0.3]])
    pen.pos = np.array([[0.41, 0.52]])
    assert pen.emit() == pen.m == 5  # nozzle radius 1 spacing: the centre and 4 neighbours
    st = pen.env.get_state(0)
    s, p = pen.spacing, pen.pen
    np.testing.assert_allclose(st["x"], [0.41, 0.52, pen.cfg.board_z + p.height] + pen.layer, atol=1e-6)
    np.testing.assert_allclose(st["v"], np.tile([0.0, 0.0, -p.extrude_speed], (5, 1)), atol=1e-6)  # laid at rest
    assert (st["material"] == 1).all() and np.allclose(st["sigma_y"], p.yield_stress)
    # a stroke of T substeps extrudes a layer per spacing of column: N = m (1 + floor(T dt v_e / s)) up to one layer
    pen.reset((0.4, 0.5))
    T = 160
    added = [pen.step(vel, True) for _ in range(T)]
    col = T * pen.dt * p.extrude_speed / s  # column length in spacings (~ 5.5)
    assert set(added) <= {0, 5} and added[0] == 5
    assert 5 * col < sum(added) <= 5 * (col + 1) and pen.n == sum(added)
    gaps = np.diff(np.flatnonzero(added))
    assert gaps.min() >= np.floor(s / (p.extrude_speed * pen.dt)) and gaps.max() <= np.ceil(s / (p.extrude_speed * pen.dt))
    np.testing.assert_allclose(pen.pos[0], [0.4 + 0.6 * T * pen.dt, 0.5 - 0.3 * T * pen.dt], atol=1e-9)


def test_pen_lifted_between_strokes_gives_two_clusters(pen):
    from topocut.tasks.writing_scene import cluster_check

    pen.reset((0.4, 0.5))
    pen.move([0.08, 0.0], True)
    pen.move([0.06, 0.0], False)  # lifted: no particles, the stroke ends
    n1 = pen.n
    pen.move([0.08, 0.0], True)
    pen.settle()
    x, stroke = pen.particles()
    assert pen.num_strokes == 2 and (stroke[:n1] == 0).all() and (stroke[n1:] == 1).all()
    assert abs(n1 - (pen.n - n1)) <= pen.m  # equal strokes, equal cream
    check = cluster_check(x[0], stroke)
    assert check["clusters"] == 2 and check["agree"], {k: v for k, v in check.items() if k != "labels"}
    # the cream came to rest on the board along the pen's path
    assert np.abs(pen.solver.v.to_numpy()[0, :pen.n]).max() < 0.05
    assert x[0][:, 2].max() < pen.cfg.board_z + 0.05 and x[0][:, 0].min() > 0.38 and x[0][:, 0].max() < 0.65

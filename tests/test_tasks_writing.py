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
    # the default pen: a layer (the plus of 5) every 1.2 * 0.01 / 1.5 = 8 mm of stroke: 0, 8, ..., 160 mm
    (pts,), _ = word_goal("L", h, 0.05, s, bz)
    assert len(pts) == 21 * 5
    np.testing.assert_allclose(pts[:, 2], bz + s / 2)  # one layer on the board
    np.testing.assert_allclose(pts[:5, :2], [0.47, 0.55] + np.array([[-s, 0], [0, -s], [0, 0], [0, s], [s, 0]]),
                               atol=1e-6)  # the first layer: the nozzle's plus at the stroke's start
    np.testing.assert_allclose(pts[-5:, :2].mean(0), [0.53, 0.45], atol=1e-6)  # 160 mm: the stroke's end
    # every point lies within one spacing of the stroke (the plus reaches s from the nozzle's axis)
    xy = pts[:, :2]
    d_stem = np.where((xy[:, 1] >= 0.45 - s) & (xy[:, 1] <= 0.55 + s), np.abs(xy[:, 0] - 0.47), np.inf)
    d_foot = np.where((xy[:, 0] >= 0.47 - s) & (xy[:, 0] <= 0.53 + s), np.abs(xy[:, 1] - 0.45), np.inf)
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
    goals, _ = word_goal("CORL", h, gap, 0.01, 0.05)  # a plus of 5 every 8 mm (the default pen's flux)
    assert [len(g) for g in goals] == [(int(polyline_length(p) / 0.008) + 1) * 5 for p in strokes]


def test_identical_strokes_score_the_full_reward_per_letter():
    from topocut.tasks.writing_scene import letter_rewards

    goals, _ = word_goal("LO", 0.12, 0.06, 0.01, 0.05)
    x = np.concatenate(goals[::-1])  # strokes written in the other order: matching pairs them up
    stroke = np.repeat([0, 1], [len(goals[1]), len(goals[0])])
    res = letter_rewards(x, stroke, goals, spacing=0.01)
    assert res["per_letter"] == pytest.approx([1.0, 1.0]) and sorted(res["matching"]) == [(0, 1), (1, 0)]
    assert res["total"] == pytest.approx(1.0) and res["extra"] == []


def test_a_bead_laid_across_the_nozzle_differently_has_its_letters_size_at_the_pens_spacing():
    """The I's bead with the nozzle's plus turned 45° against the stroke (as a diagonal stroke meets the plus): the
    same stations and count, and the plus's offsets {0, (±s, 0), (0, ±s)} and the turned ones {0, (±a, ±a)},
    a = s / √2, have the same second moments (variance 2 s² / 5 along either axis, no covariance), so at the pen's
    spacing the size terms read the same piece (d_size 0); the estimated spacing (median 4-NN distance / 0.97) reads
    0.62 s for one and 0.74 s for the other, so its volumes differed by 68%."""
    from topocut.reward import spectral_distance
    from topocut.reward.size import particle_spacing, size_descriptor, size_distance
    from topocut.tasks.letters import letter_points, pen_bead
    from topocut.tasks.writing_scene import letter_distances

    s, bz = 0.01, 0.05
    (goal,), (poly,) = word_goal("I", 0.12, 0.06, s, bz)
    layer, pitch = pen_bead(s)
    a = np.sqrt(0.5)
    turned = letter_points(poly, layer[:, :2] @ np.array([[a, -a], [a, a]]).T, pitch, bz + s / 2)
    assert len(turned) == len(goal) == 16 * 5  # 120 mm of stroke: a layer at 0, 8, ..., 120 mm
    got, want = size_descriptor(turned, s), size_descriptor(goal, s)
    # by hand: one layer (e1 = s), across the stroke sqrt(12 * 2 s^2 / 5 + s^2) = sqrt(5.8) s, along it
    # sqrt(12 (0.8 s)^2 (16^2 - 1) / 12 + 12 * 2 s^2 / 5 + s^2) = 13 s; volume 80 s^3
    for d in (got, want):
        np.testing.assert_allclose(d[:4], [s, np.sqrt(5.8) * s, 13 * s, 80 * s ** 3], rtol=1e-5)
    assert float(size_distance(got, want)) < 1e-9
    D, H = letter_distances([turned], [goal], spacing=s)
    assert H[0, 0] == 0.0 and D[0, 0] == pytest.approx(spectral_distance(turned, goal), abs=1e-9)
    assert particle_spacing(goal) / s == pytest.approx(0.62, abs=0.01)
    assert particle_spacing(turned) / s == pytest.approx(0.74, abs=0.01)


def test_missing_and_mirrored_letters_cost_the_word():
    from topocut.reward import RewardConfig
    from topocut.tasks.writing_scene import letter_rewards, word_score

    assert word_score([1.0, 0.25]) == pytest.approx(0.5) and word_score([0.9, 0.0]) == 0.0  # geometric mean
    goals, _ = word_goal("LR", 0.12, 0.06, 0.01, 0.05)
    # one letter missing: the L scores in full, the R earns 0, so the word earns 0 (a mean would pay 0.5)
    res = letter_rewards(goals[0], np.zeros(len(goals[0]), int), goals, spacing=0.01)
    assert res["per_letter"] == pytest.approx([1.0, 0.0]) and res["total"] == 0.0
    # the R's stroke mirrored about a vertical axis, off to the right: the same cloud turned over, so d_spec and d_size
    # are 0, but on the board it fits the mirror image better than the R: its handedness costs
    mirrored = goals[1] * [-1, 1, 1] + [1.2, 0, 0]
    res = letter_rewards(np.concatenate([goals[0], mirrored]), np.repeat([0, 1], [len(goals[0]), len(mirrored)]),
                         goals, spacing=0.01)
    assert res["handedness"][0] == 0.0 and res["handedness"][1] > 0.05
    assert res["distance"][1] == pytest.approx(RewardConfig().handedness_weight * res["handedness"][1], abs=1e-6)
    assert res["per_letter"] == pytest.approx([1.0, 0.0]) and res["total"] == 0.0  # d > 0.2575: R's zero


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


def test_goal_bead_holds_what_the_pen_lays(pen):
    """The goal's bead is the pen's: the same particles per unit of stroke (m v_e / (s v_p)), within one layer."""
    from topocut.tasks.letters import pen_bead

    pen.reset((0.4, 0.5))
    pen.move([0.1, 0.03], True)  # one straight stroke of 10.4 cm
    layer, pitch = pen_bead(pen.spacing, pen.pen)
    goal = letter_points(np.array([[0.4, 0.5], [0.5, 0.53]]), layer, pitch, pen.cfg.board_z)
    flux = pen.m * pen.pen.extrude_speed / (pen.spacing * pen.pen.speed) * np.hypot(0.1, 0.03)  # particles
    assert abs(len(goal) - flux) <= pen.m and abs(pen.n - len(goal)) <= pen.m


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

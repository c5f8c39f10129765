"""Open-loop imitation error (topocut.eval.open_loop, experiments/open_loop.py) against geometry worked by hand."""
import math
import runpy
import sys
from pathlib import Path

import numpy as np
import pytest

from topocut.eval.open_loop import BAND, normal_angle_deg, open_loop, partition_error, plane_gap, summarize
from topocut.policies.base import history_from_actions
from topocut.sim.action import KnifeAction

RNG = np.random.default_rng(0)
POINTS = np.column_stack([RNG.uniform(0.3, 0.7, 4000), RNG.uniform(0.3, 0.7, 4000),
                          RNG.uniform(0.05, 0.25, 4000)])  # N,3: a box on the board


def test_plane_angle_is_unsigned_and_in_degrees():
    a = KnifeAction(0.5, 0.5, yaw=0.0)
    assert normal_angle_deg(a, KnifeAction(0.4, 0.5, yaw=math.radians(30))) == pytest.approx(30.0)
    assert normal_angle_deg(a, KnifeAction(0.4, 0.5, yaw=math.radians(150))) == pytest.approx(30.0)  # same plane as -30
    assert normal_angle_deg(a, KnifeAction(0.5, 0.5, yaw=math.pi)) == pytest.approx(0.0, abs=1e-6)
    assert normal_angle_deg(a, KnifeAction(0.5, 0.5, yaw=math.pi / 2)) == pytest.approx(90.0)
    # tilt: the normal (cos t, 0, sin t) against (1, 0, 0)
    assert normal_angle_deg(a, KnifeAction(0.5, 0.5, yaw=0.0, tilt=math.radians(20))) == pytest.approx(20.0)


def test_partition_error_counts_the_points_between_two_parallel_cuts():
    x = POINTS[:, 0]
    err = partition_error(POINTS, KnifeAction(0.5, 0.5), KnifeAction(0.42, 0.5))
    assert err == pytest.approx(np.mean((x > 0.42) & (x <= 0.5)))  # ~0.2 of the box's width
    assert 0.15 < err < 0.25
    # the sides are matched the better way: the same plane with its normal reversed is no error
    assert partition_error(POINTS, KnifeAction(0.5, 0.5), KnifeAction(0.5, 0.5, yaw=math.pi)) == 0.0
    # a crossing cut (x = 0.5 against y = 0.5) disagrees on two opposite quadrants: half the points
    y = POINTS[:, 1]
    cross = partition_error(POINTS, KnifeAction(0.5, 0.5), KnifeAction(0.5, 0.5, yaw=math.pi / 2))
    assert cross == pytest.approx(min(np.mean((x > 0.5) != (y > 0.5)), np.mean((x > 0.5) == (y > 0.5))))
    assert cross == pytest.approx(0.5, abs=0.03)


def test_plane_gap_is_the_distance_from_the_demonstrators_cut_to_the_policys_plane():
    demo = KnifeAction(0.5, 0.5)
    assert plane_gap(POINTS, KnifeAction(0.42, 0.5), demo) == pytest.approx(0.08)  # parallel: 8 cm everywhere
    near = np.abs(POINTS[:, 0] - 0.5) <= BAND
    crossing = plane_gap(POINTS, KnifeAction(0.5, 0.5, yaw=math.pi / 2), demo)
    assert crossing == pytest.approx(np.mean(np.abs(POINTS[near, 1] - 0.5)))  # ~0.1: E|y - 0.5| on [0.3, 0.7]
    tilted = KnifeAction(0.5, 0.5, tilt=math.radians(10))  # through the board line x = 0.5: |z - board| sin 10°
    assert plane_gap(POINTS, tilted, demo) == pytest.approx(np.mean(np.abs(POINTS[near, 2] - 0.05)) * math.sin(
        math.radians(10)))
    assert crossing == pytest.approx(0.1, abs=0.01)
    assert math.isnan(plane_gap(POINTS, demo, KnifeAction(0.9, 0.5)))  # the demonstrator's plane misses the box


def test_a_cut_shifted_along_its_normal_moves_its_plane_by_the_offset():
    for a in (KnifeAction(0.5, 0.4, yaw=0.7), KnifeAction(0.5, 0.4, yaw=-0.3, tilt=0.4)):
        b = a.shifted(0.006)
        assert b.normal == pytest.approx(a.normal) and (b.yaw, b.tilt) == (a.yaw, a.tilt)
        # every point of a's plane is 6 mm behind b's: signed distance n . (p - p_b) = -0.006
        p = a.plane_point() + 0.1 * a.blade_axis + 0.05 * a.travel
        assert float((p - b.plane_point()) @ b.normal) == pytest.approx(-0.006)
    assert partition_error(POINTS, KnifeAction(0.5, 0.5).shifted(-0.08), KnifeAction(0.42, 0.5)) == 0.0


def _step(episode, k, demo: KnifeAction, previous=(), task="slice"):
    return {"x_t": POINTS.astype(np.float32), "f_t": np.zeros(len(POINTS), np.int32),
            "history": history_from_actions(list(previous)), "goal": POINTS[:500].astype(np.float32),
            "goal_labels": np.zeros(500, np.int32), "action": demo.to_vector(), "episode": episode, "step": k,
            "task": task, "object": "cube"}


class _Fixed:
    """Cuts at x = c whatever it sees; records the seeds it was reset with."""

    def __init__(self, c):
        self.c, self.seeds = c, []

    def reset(self, goal, seed=None):
        assert goal.points.shape == (500, 3)
        self.seeds.append(seed)

    def act(self, obs):
        return None if self.c is None else KnifeAction(self.c, 0.5)


def test_open_loop_compares_each_cut_with_the_demonstrators_and_the_previous_cut_floor():
    first, second = KnifeAction(0.4, 0.5), KnifeAction(0.6, 0.5)
    steps = [_step(3, 0, first), _step(3, 1, second, previous=[first]), _step(3, 2, second, previous=[first, second])]
    x = POINTS[:, 0]
    recs = open_loop(_Fixed(0.4), steps)
    assert [r["cut"] for r in recs] == ["1", "2", "3+"]
    assert recs[0]["partition_error"] == 0.0 and recs[0]["angle_deg"] == pytest.approx(0.0)
    assert recs[0]["gap_mm"] == pytest.approx(0.0, abs=1e-3) and recs[1]["gap_mm"] == pytest.approx(200.0)
    assert recs[1]["pred"] == pytest.approx([0.4, 0.5, 0.0, 0.0]) and recs[1]["demo"][0] == pytest.approx(0.6)
    between = np.mean((x > 0.4) & (x <= 0.6))
    assert recs[1]["partition_error"] == pytest.approx(min(between, 1 - between))
    assert math.isnan(recs[0]["prev_partition_error"])  # no previous cut on the first
    assert recs[1]["prev_partition_error"] == pytest.approx(min(between, 1 - between))  # the floor replays 0.4
    assert recs[2]["prev_partition_error"] == pytest.approx(0.0, abs=1e-9)  # ... and here the demo's own 0.6
    stopped = open_loop(_Fixed(None), steps[:1])[0]  # a policy that stops cuts nothing
    assert stopped["stopped"] and stopped["partition_error"] == pytest.approx(min(np.mean(x > 0.4), np.mean(x <= 0.4)))
    p = _Fixed(0.5)
    open_loop(p, steps)
    assert len(set(p.seeds)) == 3  # a seed per step, not one for the whole run


def test_summarize_averages_an_episode_first_then_bootstraps_over_episodes():
    recs = [{"task": "slice", "episode": 0, "cut": "3+", "angle_deg": 10.0, "partition_error": 0.1,
             "gap_mm": 4.0, "prev_partition_error": 0.3},
            {"task": "slice", "episode": 0, "cut": "3+", "angle_deg": 30.0, "partition_error": 0.3,
             "gap_mm": 6.0, "prev_partition_error": 0.5},
            {"task": "slice", "episode": 1, "cut": "3+", "angle_deg": 50.0, "partition_error": 0.2,
             "gap_mm": 2.0, "prev_partition_error": math.nan},
            {"task": "dice", "episode": 2, "cut": "1", "angle_deg": 5.0, "partition_error": 0.0,
             "gap_mm": math.nan, "prev_partition_error": math.nan}]
    rows = {(r["task"], r["cut"]): r for r in summarize(recs)}
    later = rows["slice", "3+"]
    assert later["n"] == 2 and later["angle_deg"] == pytest.approx((20.0 + 50.0) / 2)  # episode 0's mean is 20
    assert later["partition_error"] == pytest.approx((0.2 + 0.2) / 2)
    assert later["gap_mm"] == pytest.approx((5.0 + 2.0) / 2)
    assert later["prev_partition_error"] == pytest.approx(0.4)  # episode 1 has no floor: only episode 0's 0.4
    assert later["angle_deg_lo"] <= later["angle_deg"] <= later["angle_deg_hi"]
    every = rows["all", "all"]
    assert every["n"] == 3 and every["angle_deg"] == pytest.approx((20.0 + 50.0 + 5.0) / 3)
    assert math.isnan(rows["dice", "1"]["prev_partition_error"])
    assert list(rows)[-1] == ("all", "all")  # "all" rows after the named ones


def test_cli_refuses_a_scripted_policy_with_exit_2(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["open_loop.py", "--root", str(tmp_path), "--policy", "oracle"])
    with pytest.raises(SystemExit) as e:
        runpy.run_path(str(Path(__file__).parents[1] / "experiments" / "open_loop.py"), run_name="__main__")
    assert e.value.code == 2 and "--policy 'oracle': one of" in capsys.readouterr().err

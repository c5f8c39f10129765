"""benchmarks/paper_cost.py: the projection's arithmetic by hand, the paper's counts from the config, and one real run
of every stage on the CPU at the smallest sizes, its JSON's projections recomputed from its own terms."""
import json
import subprocess
import sys
from collections import namedtuple
from pathlib import Path

import pytest

from benchmarks import paper_cost as pc

REPO = Path(__file__).resolve().parents[1]
PAPER = ["stage=all", "scale=paper", "device=cuda", "reward=torch", "trainer=gpu", "logger=csv", "progress=false"]


def test_list_schedule_hands_each_unit_to_the_first_free_worker():
    # 2 workers: [3] | [1, 1, 1] -> both free at 3
    assert pc.list_schedule([3, 1, 1, 1], 2) == 3
    # a worker's first unit costs 0.5 more: 3.5 | 1.5, 2.5, 3.5
    assert pc.list_schedule([3, 1, 1, 1], 2, first_extra=0.5) == 3.5
    # the long unit last: 1, 1 -> then 1 on the first free, 3 on the other: max(1 + 1, 1 + 3) = 4
    assert pc.list_schedule([1, 1, 1, 3], 2) == 4
    assert pc.list_schedule([3, 1, 1, 1], 1) == 6
    assert pc.list_schedule([2, 5], 16) == 5
    assert pc.list_schedule([], 4) == 0.0


def test_fit_epochs_takes_the_difference_and_the_intercept():
    assert pc.fit_epochs(1, 10.0, 3, 16.0) == (3.0, 7.0)  # 6 s over 2 epochs; 10 - 1 x 3
    assert pc.fit_epochs(1, 10.0, 6, 35.0) == (5.0, 5.0)
    assert pc.fit_epochs(1, 10.0, 2, 9.0) == (4.5, 0.0)  # no positive difference: w2 / k2, no intercept


def test_epoch_cost_splits_an_epoch_into_a_fixed_part_and_a_part_per_episode():
    assert pc.epoch_cost([(128, 3.2)]) == (0.0, 0.025)  # one size: all of it per episode
    # 64 episodes 2.0 s, 256 episodes 5.0 s: 3 s over 192 episodes, 2.0 - 64 x 3 / 192 = 1.0 s fixed
    assert pc.epoch_cost([(256, 5.0), (64, 2.0)]) == pytest.approx((1.0, 3.0 / 192))
    assert pc.epoch_cost([(64, 2.0), (256, 1.9)]) == (0.0, 1.9 / 256)  # no positive slope: the larger size alone


def test_the_target_is_judged_on_make_paper_whole_only():
    def result(*stages_hours):
        rows = [{"stage": st, "measured": "", "rate_s": 1.0, "rate_unit": "s", "count": 1, "count_unit": "",
                 "processes": 1, "fixed_s": 0.0, "projected_s": h * 3600, "complete": True, "detail": {},
                 "share": 0.0} for st, h in stages_hours]
        return {"rows": rows, "total_s": sum(h for _, h in stages_hours) * 3600}

    whole = [("simulate", 0.1), ("demonstrations", 1.0), ("merge", 0.1), ("pretrain", 0.2), ("bc", 0.5),
             ("eval", 0.9)]
    assert pc.unmeasured(result(*whole)) == []
    assert "Target <= 3 h on one GPU: met (0.93x the target)" in pc.markdown(result(*whole))
    assert "**make paper**" in pc.markdown(result(*whole))
    assert "not met (1.27x the target)" in pc.markdown(result(*whole[:-1], ("eval", 1.0 + 0.9)))
    part = result(*whole[:3])  # the demonstrations alone under 3 h decide nothing
    assert pc.unmeasured(part) == ["pretrain", "bc", "eval"]
    md = pc.markdown(part)
    assert "not decided: pretrain, bc, eval not measured (the stages measured 0.40x the target)" in md
    assert "**the stages measured**" in md and "**make paper**" not in md
    assert "not met: the stages measured alone take 1.33x the target" in pc.markdown(result(("eval", 4.0)))


@pytest.mark.parametrize("sizes", [["64", "128", "256"], ["64", "64"], ["1"]])
def test_train_episodes_takes_one_or_two_different_sizes(sizes, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        pc.main(["--out", str(tmp_path), "--train-episodes", *sizes])
    assert e.value.code == 2
    assert "--train-episodes" in capsys.readouterr().err and not list(tmp_path.iterdir())  # nothing written


def test_demo_costs_by_hand():
    parts = [("dice", 0, 10), ("slice", 60, 7), ("stick", 11, 3)]
    t, h = {"dice": 30.0, "slice": 10.0, "stick": 20.0}, {"dice": 5.0, "slice": 2.0, "stick": 4.0}
    costs, work = pc.demo_costs(parts, t, h, 10, overhead=1.0)
    # dice e0-9: 10 x 30 + one comparison (e0); slice e60-66: 7 x 10 + one (e60); stick e11-13: none
    assert costs == [1 + 300 + 5, 1 + 70 + 2, 1 + 60]
    assert work == 305 + 72 + 60
    assert pc.demo_costs(parts, t, h, 0, 0.0)[1] == 300 + 70 + 60  # heuristic_every=0: no comparisons
    assert pc.demo_costs([("slice", 0, 3)], t, h, 1, 0.0)[1] == 3 * (10 + 2)  # every episode


def test_demo_rates_by_hand():
    """Two parts in one process (pid 1): the first has two episodes, compilation in its first; the second one."""
    first = {"task": "dice", "pid": 1, "started": 0.0, "seconds": 40.0, "records": [
        {"started": 2.0, "time_s": 10.0}, {"started": 1.0, "time_s": 20.0, "heuristic_time_s": 5.0}]}
    later = {"task": "dice", "pid": 1, "started": 50.0, "seconds": 13.0, "records": [{"started": 51.0, "time_s": 12.0}]}
    r = pc.demo_rates([later, first])
    assert r["t"] == {"dice": (10.0 + 12.0) / 2}  # the first part's first episode left out
    assert r["h"] == {"dice": 5.0}  # no steady comparison: every one there is
    assert r["overhead"] == 13.0 - 12.0  # from the later part: 40 - 35 = 5 is the first's
    # the first episode over t + h (20 + 5 - 11 - 5 = 9) and the first part's overhead over the later's (5 - 1 = 4)
    assert r["extra"] == 9.0 + 4.0
    alone = pc.demo_rates([{"task": "slice", "pid": None, "started": 0.0, "seconds": None,
                            "records": [{"started": 0.0, "time_s": 7.0}]}])
    assert alone == {"t": {"slice": 7.0}, "h": {"slice": 0.0}, "overhead": 0.0, "extra": 0.0}
    # a part stopped at --minutes before its first episode ended has no rate (paper_cost bounds it from below)
    open_part = {"task": "dice", "pid": 2, "started": 0.0, "seconds": None, "records": []}
    some = pc.demo_rates([dict(later), open_part])
    assert some["t"] == {"dice": 12.0} and "slice" not in some["t"]
    none = pc.demo_rates([{"task": "slice", "pid": 3, "started": 0.0, "seconds": None, "records": []}])
    assert none["t"] == {}


def test_unit_costs_sum_each_units_batch_time_over_the_seeds(tmp_path):
    Spec = namedtuple("Spec", "key")
    a, b = Spec("slice_cube_000"), Spec("slice_donut_000")
    (tmp_path / "policies.json").write_text(json.dumps({
        "oracle": {"policy": "oracle"}, "mppi": {"policy": "mppi"}, "dp3@s0": {"policy": "dp3"},
        "dp3@s1": {"policy": "dp3"}}))
    for run, spec, t in (("oracle", a, 4.0), ("oracle", b, 4.0), ("dp3@s0", a, 3.0), ("dp3@s0", b, 3.0),
                         ("dp3@s1", a, 5.0), ("dp3@s1", b, 5.0), ("mppi", a, 9.0)):
        (tmp_path / "episodes" / run).mkdir(parents=True, exist_ok=True)
        (tmp_path / "episodes" / run / f"{spec.key}.json").write_text(json.dumps({"time_s": t}))
    units = [("oracle", [a, b]), ("dp3", [a, b]), ("mppi", [a]), ("mppi", [b])]
    costs, first = pc.unit_costs(tmp_path, units)
    assert costs == [4.0, 3.0 + 5.0, 9.0, None]  # mppi's second episode did not finish
    assert first is not None


def test_make_row_projects_fixed_plus_count_times_rate_over_processes():
    row = pc.make_row("eval", "x", 30.0, "s", 6075, "episodes", 16, 120.0)
    assert row["projected_s"] == 120.0 + 6075 * 30.0 / 16


def test_the_paper_counts_come_from_the_config():
    """scale=paper: 1,005 demonstrations in 105 parts, the protocol's 405 specs x 15 runs = 6,075 episodes."""
    cfg = pc.compose(PAPER)
    parts = pc.demo_parts(cfg["dict"])
    assert (len(parts), sum(n for *_, n in parts)) == (105, 1005)
    specs, units, runs = pc.eval_units(cfg)
    assert (len(specs), runs, len(specs) * runs) == (405, 15, 6075)
    assert len(units) == 6 * 26 + 405  # six batched policies in batches of 16 specs, MPPI one spec a unit
    assert pc.compose([*PAPER, "sim.n_grid=64"])["dict"]["sim"]["n_grid"] == 64  # --set reaches the projection


# the smallest sizes (tests/test_stages.py's FAST): each stage takes seconds
TINY = ["sim.n_grid=20", "sim.cut_substeps=40", "sim.dwell_time=0.0005", "sim.push_time=0.002", "sim.settle_time=0.002",
        "sim.batch_size=2", "planner.num_samples=2", "planner.horizon=1", "planner.iterations=1", "task.max_cuts=1",
        "data.points_per_step=128", "topology.resolution=32", "object.randomize_pose=false", "eval.max_cuts=1",
        "eval.gifs=0", "eval.videos=0", "eval.bootstrap_resamples=100", "policy.train.num_points=64",
        "policy.train.num_goal_points=64", "eval.policies=[oracle,mppi,dp3]"]


@pytest.fixture(scope="module")
def cpu_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("paper_cost")
    cmd = [sys.executable, "benchmarks/paper_cost.py", "--scale", "smoke", "--device", "cpu", "--out", str(out),
           "--episodes", "2", "--epochs", "1", "2", "--train-episodes", "2", "--eval-episodes", "1", "--set", *TINY]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return out, json.loads((out / "paper_cost.json").read_text()), proc.stdout


def test_a_cpu_run_measures_every_stage(cpu_run):
    out, result, stdout = cpu_run
    rows = {r["stage"]: r for r in result["rows"]}
    # make run's one smoke cell: no parts, so no merge
    assert list(rows) == ["simulate", "demonstrations", "pretrain", "bc", "eval"]
    for r in rows.values():
        assert r["complete"] and r["rate_s"] > 0 and r["count"] > 0 and r["projected_s"] > 0, r
    table = (out / "paper_cost.md").read_text()
    assert all(f"| {s} |" in table for s in rows) and "make paper" in stdout


def test_a_cpu_runs_projections_recompute_from_its_own_terms(cpu_run):
    _, result, _ = cpu_run
    rows = {r["stage"]: r for r in result["rows"]}
    for r in rows.values():
        assert r["projected_s"] == pytest.approx(r["fixed_s"] + r["count"] * r["rate_s"] / r["processes"])
    assert result["total_s"] == pytest.approx(sum(r["projected_s"] for r in rows.values()))
    assert sum(r["share"] for r in rows.values()) == pytest.approx(1.0)
    # the smoke config's full sizes: 2 demonstrations of one cell; 4 epochs of them; 2 specs x 3 policies, 1 seed
    assert rows["simulate"]["count"] == 1 and rows["simulate"]["fixed_s"] == 0
    demo = rows["demonstrations"]
    d = demo["detail"]
    assert demo["count"] == 2 and demo["processes"] == 1
    # heuristic_every=1 at smoke: every episode has its comparison, one part on one worker
    assert demo["rate_s"] == pytest.approx(d["t"]["slice"] + d["h"]["slice"])
    assert d["schedule_s"] == pytest.approx(d["extra"] + d["overhead"] + 2 * demo["rate_s"])
    assert demo["fixed_s"] == pytest.approx(d["start_up_s"] + d["schedule_s"] - 2 * demo["rate_s"])
    for stage in ("pretrain", "bc"):
        r, d = rows[stage], rows[stage]["detail"]
        assert r["count"] == 4 * 2 and d["epochs"] == [1, 2] and d["train_episodes"] == 2
        w1, w2 = d["walls_s"]
        per = w2 - w1 if w2 > w1 else w2 / 2
        assert d["epoch_s"] == pytest.approx(per) and r["rate_s"] == pytest.approx(per / 2)
        assert r["fixed_s"] == pytest.approx(max(0.0, w1 - per) if w2 > w1 else 0.0)
    ev = rows["eval"]
    u = ev["detail"]["unit_s"]
    assert ev["count"] == 2 * 3 and set(u) == {"oracle", "mppi", "dp3"}
    # batches of sim.batch_size=2 specs: oracle and dp3 one unit each, MPPI one unit a spec
    assert ev["rate_s"] * ev["count"] == pytest.approx(u["oracle"] + u["dp3"] + 2 * u["mppi"])
    assert ev["fixed_s"] == pytest.approx(ev["detail"]["start_up_s"] + u["oracle"] + u["dp3"] + 2 * u["mppi"]
                                          - ev["rate_s"] * ev["count"])  # one process: the units one after another

"""Evaluation statistics: bootstrap intervals, paired differences and ties, training-seed pooling, the report's
interval columns, and a bit-reproducible evaluation on the CPU."""
from __future__ import annotations

import csv
import json
import math
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from tests.stage_runner import run as run_stage
from topocut.data.store import ArtifactStore, MissingArtifact
from topocut.eval import stats
from topocut.eval.report import CSV_COLUMNS, load_episodes, summarize, write_report

REPO = Path(__file__).resolve().parents[1]


# -- bootstrap ------------------------------------------------------------------------------------------
def test_bootstrap_interval_contains_the_mean_and_has_the_normal_width():
    x = np.random.default_rng(3).gamma(2.0, 0.5, size=200)  # skewed, like final rewards
    iv = stats.bootstrap_mean(x, label="a")
    mean = float(np.mean(x))
    half = 1.96 * np.std(x, ddof=1) / np.sqrt(len(x))  # normal approximation, computed here with numpy alone
    assert iv.n == 200 and iv.mean == pytest.approx(mean) and iv.lo < mean < iv.hi
    assert 0.8 < (iv.hi - iv.lo) / (2 * half) < 1.25
    assert abs((iv.lo + iv.hi) / 2 - mean) < 0.25 * half
    assert stats.bootstrap_mean(x, label="a") == iv  # seeded: a report is reproducible
    assert stats.bootstrap_mean(x, label="b") != iv  # another estimate draws other resamples
    # a smaller sample has a wider interval, about sqrt(n) wider
    small = stats.bootstrap_mean(x[:50], label="a")
    assert 1.4 < (small.hi - small.lo) / (iv.hi - iv.lo) < 2.8
    wide = stats.bootstrap_mean(x, label="a", confidence=0.99)
    assert wide.lo < iv.lo and wide.hi > iv.hi


def test_bootstrap_edge_cases():
    assert math.isnan(stats.bootstrap_mean([]).mean)
    one = stats.bootstrap_mean([0.7])
    assert one.mean == 0.7 and math.isnan(one.lo) and one.tie is None  # no interval from one episode
    same = stats.bootstrap_mean([0.1] * 5)
    assert (same.mean, same.lo, same.hi) == (0.1, 0.1, 0.1)
    assert math.isnan(stats.bootstrap_mean([1.0, math.nan]).lo)


def test_paired_difference_of_identical_policies_is_exactly_zero_and_a_tie():
    rng = np.random.default_rng(0)
    a = {("slice", "in", "cube", s): float(v) for s, v in enumerate(rng.uniform(0, 3, 12))}
    d = stats.paired_difference(a, dict(a))
    assert (d.mean, d.lo, d.hi, d.n) == (0.0, 0.0, 0.0, 12) and d.tie is True
    assert stats.paired_difference(a, {("other",): 1.0}) == stats.NAN_INTERVAL  # no shared scene


def test_pairing_finds_a_small_consistent_gap_the_cell_intervals_cannot():
    rng = np.random.default_rng(1)
    scenes = rng.uniform(0.0, 3.0, 30)  # scene-to-scene spread much larger than the gap
    a = {i: float(v) for i, v in enumerate(scenes)}
    b = {i: float(v + 0.1 + rng.normal(0, 0.02)) for i, v in enumerate(scenes)}
    ia, ib = stats.bootstrap_mean(list(a.values())), stats.bootstrap_mean(list(b.values()))
    assert ib.lo < ia.hi  # the two cells' intervals overlap
    d = stats.paired_difference(b, a)
    assert d.tie is False and 0.08 < d.lo < d.mean < d.hi < 0.12
    noise = {i: float(v + rng.normal(0, 0.3)) for i, v in enumerate(scenes)}  # no gap, only noise
    assert stats.paired_difference(noise, a).tie is True


# -- the report ---------------------------------------------------------------------------------------
def _ep(policy, task, split, obj, seed, reward, nc, status="ok"):
    return {"policy": policy, "status": status, "final_reward": reward, "final_cut_count": nc,
            "spec": {"task": task, "object": obj, "split": split, "episode": seed % 100, "seed": seed}}


def _episodes(gap=0.5, n=8, policies=("oracle", "pddp", "same")):
    rng = np.random.default_rng(2)
    eps = []
    for split, obj in (("in", "cube"), ("out", "donut")):
        for i in range(n):
            seed = 1000 * (split == "out") + i
            r = float(rng.uniform(1.0, 3.0))
            for p in policies:
                v = r if p in ("oracle", "same") else r - gap
                eps.append(_ep(p, "slice", split, obj, seed, v, int(round(2 * v))))
    return eps


def _write(tmp_path, episodes):
    for e in episodes:
        p = tmp_path / "episodes" / e["policy"] / f"{e['spec']['task']}_{e['spec']['object']}_{e['spec']['seed']}.json"
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(json.dumps(e))


def test_summary_marks_ties_and_gaps_against_the_reference():
    rows = {(r["policy"], r["split"], r["task"]): r for r in summarize(_episodes(), "oracle")}
    same, pddp = rows["same", "in", "slice"], rows["pddp", "in", "slice"]
    assert same["dR_hat_mean"] == 0.0 and same["dR_hat_lo"] == same["dR_hat_hi"] == 0.0
    assert same["dR_hat_tie"] is True and same["dN_C_tie"] is True and same["pairs"] == 8
    assert pddp["dR_hat_tie"] is False and pddp["dR_hat_hi"] < 0 and pddp["pairs"] == 8
    ref = pddp["reference_R_mean"]  # normalize_by=task: one mean over both splits
    assert pddp["dR_hat_mean"] == pytest.approx(-0.5 / ref)
    assert pddp["R_hat_lo"] < pddp["R_hat_mean"] < pddp["R_hat_hi"]
    assert all(r["dR_hat_tie"] is None and r["pairs"] == 0 for k, r in rows.items() if k[0] == "oracle")
    # aggregates: over both splits (16 scenes), over every task
    assert rows["pddp", "all", "slice"]["pairs"] == 16 and rows["pddp", "all", "all"]["episodes"] == 16
    # another comparison policy
    rows = {(r["policy"], r["split"]): r for r in summarize(_episodes(), "oracle", compare_to="pddp")
            if r["task"] == "slice"}
    assert rows["oracle", "in"]["dR_hat_tie"] is False and rows["oracle", "in"]["compared_to"] == "pddp"
    assert rows["pddp", "in"]["pairs"] == 0


def test_training_seeds_pool_into_one_row_paired_by_scene():
    base = _episodes(gap=0.0, n=6, policies=("oracle",))
    eps = list(base)
    for s, offset in ((0, -0.1), (1, 0.0), (2, 0.1)):  # three checkpoints: their per-scene mean is the oracle's
        eps += [dict(e, policy=f"pddp@s{s}", final_reward=e["final_reward"] + offset) for e in base]
    rows = {(r["policy"], r["split"], r["task"]): r for r in summarize(eps, "oracle")}
    r = rows["pddp", "in", "slice"]
    assert (r["train_seeds"], r["episodes"], r["pairs"]) == (3, 18, 6)
    assert r["dR_hat_mean"] == pytest.approx(0.0, abs=1e-12) and r["dR_hat_tie"] is True
    ref = r["reference_R_mean"]
    assert r["R_hat_seed_sd"] == pytest.approx(0.1 / ref)  # sd of the three seeds' cell means
    assert not any(p.startswith("pddp@") for p, _, _ in rows)
    assert rows["oracle", "in", "slice"]["train_seeds"] == 0


def test_report_files_carry_intervals_differences_and_ties(tmp_path):
    eps = _episodes()
    eps += [dict(e, policy=f"dp3@s{s}") for s in (0, 1) for e in eps if e["policy"] == "pddp"]
    _write(tmp_path, eps)
    (tmp_path / "policies.json").write_text(json.dumps(
        {"pddp": {"policy": "pddp", "train_seed": 4, "checkpoint": "checkpoint/pddp:v001@x"}}))
    assert {(e["policy"], e["train_seed"]) for e in load_episodes(tmp_path)} == {
        ("oracle", None), ("same", None), ("pddp", 4), ("dp3", 0), ("dp3", 1)}
    out = write_report(tmp_path, "oracle", console=False)
    with open(out["csv"]) as f:
        reader = csv.DictReader(f)
        header, rows = reader.fieldnames, list(reader)
    assert header == CSV_COLUMNS
    for m in ("R_hat", "N_C", "R"):
        assert {f"{m}_mean", f"{m}_lo", f"{m}_hi"} <= set(header)
    for m in ("dR_hat", "dN_C"):
        assert {f"{m}_mean", f"{m}_lo", f"{m}_hi", f"{m}_tie"} <= set(header)
    cell = {(r["policy"], r["split"], r["task"]): r for r in rows}
    assert cell["same", "in", "slice"]["dR_hat_tie"] == "True" and cell["pddp", "in", "slice"]["dR_hat_tie"] == "False"
    assert cell["dp3", "in", "slice"]["train_seeds"] == "2" and cell["pddp", "in", "slice"]["train_seeds"] == "1"
    assert float(cell["pddp", "in", "slice"]["R_hat_lo"]) < float(cell["pddp", "in", "slice"]["R_hat_hi"])
    with open(out["objects_csv"]) as f:
        objects = list(csv.DictReader(f))
    assert {(r["policy"], r["object"]) for r in objects} >= {("pddp", "cube"), ("pddp", "donut")}
    md = out["md"].read_text()
    ours = md.split("### Paper (Table 1)")[0]
    num = r"-?\d+\.\d\d"
    assert re.search(rf"\| PDDP \(Ours\) \(1 seed\) \| {num} \[{num}, {num}\] \| {num} \[{num}, {num}\] \|", ours)
    assert "| DP3 (2 seeds) |" in ours and "95% percentile-bootstrap" in ours
    diff = ours.split("### Difference from")[1].split("### Aggregates")[0]
    assert re.search(r"\| same \| ≈ \+0\.00 \[\+0\.00, \+0\.00\] \|", diff)
    assert re.search(r"\| PDDP \(Ours\) \(1 seed\) \| -0\.\d\d \[-0\.\d\d, -0\.\d\d\] \|", diff)
    # the report is reproducible to the bit (seeded resamples)
    first = out["csv"].read_bytes(), out["md"].read_bytes()
    write_report(tmp_path, "oracle", console=False)
    assert (out["csv"].read_bytes(), out["md"].read_bytes()) == first


# -- several training seeds in the eval stage -------------------------------------------------------------
def _ckpt(store, name, seed, trainer="a", data="dataset/demos:v001@abc"):
    w, _ = store.begin("checkpoint", name, {"trainer": trainer, "seed": seed}, {"dataset": data},
                       extra={"seed": seed})
    (w.path / "model.ckpt").write_bytes(f"{name}{seed}{trainer}".encode())
    return w.commit({"policy": name, "seed": seed})


def test_eval_finds_each_training_seeds_checkpoint_of_the_same_run(tmp_path, monkeypatch):
    import topocut.policies.baselines.module as baselines
    from topocut.eval.runner import build_policies, seed_checkpoints

    store = ArtifactStore(tmp_path)
    _ckpt(store, "dp3", 0)  # v001
    _ckpt(store, "dp3", 1)  # v002
    _ckpt(store, "dp3", 0, trainer="b")  # v003: another training config
    _ckpt(store, "dp3", 1, data="dataset/demos:v002@def")  # v004: another dataset
    _ckpt(store, "dp3", 2)  # v005: the latest, v001 and v002's training run
    got = [(s, p.name) for s, p in seed_checkpoints(store, "dp3", "latest", [0, 1, 2])]
    assert got == [(0, "v001"), (1, "v002"), (2, "v005")]
    assert [(s, p.name) for s, p in seed_checkpoints(store, "dp3", "v003", [0])] == [(0, "v003")]
    assert [(s, p.name) for s, p in seed_checkpoints(store, "dp3")] == [(2, "v005")]  # one seed: the latest
    with pytest.raises(MissingArtifact, match=r"none was trained with seed 2.*-m stage=bc seed=1,2"):
        seed_checkpoints(store, "dp3", "v004", [1, 2])
    with pytest.raises(MissingArtifact, match=r"none was trained with seed 3, 4"):
        seed_checkpoints(store, "dp3", "latest", [2, 3, 4])

    monkeypatch.setattr(baselines, "load_pose_policy", lambda path, **kw: Path(path).read_bytes())
    ctx = SimpleNamespace(store=store, seed=0, device="cpu")
    runs = {}
    policies, inputs = build_policies(ctx, ["oracle", "dp3"], None, None, None, None, None, {}, train_seeds=3,
                                      runs=runs)
    assert list(policies) == ["oracle", "dp3@s0", "dp3@s1", "dp3@s2"] and policies["dp3@s2"] == b"dp32a"
    assert inputs["dp3@s1"].startswith("checkpoint/dp3:v002@") and "oracle" not in inputs
    assert runs["dp3@s0"]["policy"] == "dp3" and runs["dp3@s0"]["train_seed"] == 0
    assert runs["oracle"] == {"policy": "oracle", "train_seed": None, "checkpoint": None}


def test_train_seeds_config_is_three_at_paper_scale_and_checked():
    from hydra import compose, initialize_config_dir

    from pipelines.all import CONF_DIR
    from topocut.config import register_configs
    from topocut.eval import EvalConfig

    register_configs()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        smoke = compose(config_name="config", overrides=["stage=eval"])
        paper = compose(config_name="config", overrides=["stage=eval", "scale=paper"])
    assert smoke.eval.train_seeds == 1 and paper.eval.train_seeds == 3
    with pytest.raises(ValueError, match="eval.train_seeds=0"):
        EvalConfig(train_seeds=0).validate()
    with pytest.raises(ValueError, match="eval.confidence=1.5"):
        EvalConfig(confidence=1.5).validate()
    with pytest.raises(ValueError, match="eval.compare_to='mppi'"):
        EvalConfig(compare_to="mppi").validate()
    assert EvalConfig(compare_to="pddp").validate().comparison == "pddp" and EvalConfig().comparison == "oracle"


# -- determinism ---------------------------------------------------------------------------------------
TINY = ["stage=eval", "device=cpu", "logger=none", "progress=false", "eval.policies=[oracle,heuristic]",
        "eval.seen=[cube]", "eval.unseen=[]", "eval.tasks=[slice]", "eval.episodes_per_cell=2", "eval.max_cuts=1",
        "eval.gifs=0", "eval.videos=0", "eval.num_points=128", "eval.cpu_threads=1", "sim.n_grid=20", "sim.cut_substeps=40",
        "sim.dwell_time=0.0005", "sim.push_time=0.002", "sim.settle_time=0.002", "topology.resolution=32"]


def _eval_once(root: Path) -> Path:
    """One `python -m topocut.run stage=eval` in a fresh process, as a user re-runs a command."""
    import os
    import sys

    env = dict(os.environ, WANDB_MODE="disabled", TOPOCUT_OUTPUTS=str(root), HYDRA_FULL_ERROR="0")
    env.pop("CUDA_VISIBLE_DEVICES", None)
    proc = run_stage([sys.executable, "-m", "topocut.run", *TINY, f"outputs_root={root}"], cwd=REPO, env=env,
                     timeout=300)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-4000:]
    (path,) = (root / "eval" / "table1").glob("v*")
    return path


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("determinism")
    return _eval_once(root / "a"), _eval_once(root / "b")


def _number(v: str):
    try:
        return float(v)
    except ValueError:
        return v


def _floats(path: Path) -> list[list]:
    with open(path) as f:
        return [[_number(v) for v in row] for row in csv.reader(f)]


def test_same_config_and_seed_on_the_cpu_gives_the_same_numbers(two_runs):
    """A tiny evaluation on the simulator (oracle and heuristic, one object, two episodes, one cut), run twice
    from scratch, each in its own process and store (eval.cpu_threads=1: Taichi's atomic adds in one thread's
    order): the same actions, cut counts and statuses, and every number of results.csv equal to 1e-12."""
    a, b = two_runs
    discrete = lambda d: [(e["run"], e["spec"], e["status"], e["actions"], e["cut_counts"], e["num_pieces"])  # noqa: E731
                          for e in load_episodes(d)]
    assert discrete(a) == discrete(b) and len(discrete(a)) == 4
    for name in ("results.csv", "results_objects.csv"):
        fa, fb = _floats(a / name), _floats(b / name)
        assert len(fa) == len(fb) > 1
        for ra, rb in zip(fa, fb):
            assert [type(v) for v in ra] == [type(v) for v in rb]
            np.testing.assert_allclose([v for v in ra if isinstance(v, float)], [v for v in rb if isinstance(v, float)],
                                       rtol=1e-12, atol=1e-15)
            assert [v for v in ra if not isinstance(v, float)] == [v for v in rb if not isinstance(v, float)]
    with open(a / "results.csv") as f:
        heur = next(r for r in csv.DictReader(f) if r["policy"] == "heuristic" and r["split"] == "in")
    assert heur["pairs"] == "2" and heur["compared_to"] == "oracle"


def test_same_config_and_seed_on_the_cpu_gives_a_bit_identical_csv(two_runs):
    a, b = two_runs
    assert (a / "results.csv").read_bytes() == (b / "results.csv").read_bytes()

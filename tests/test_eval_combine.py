"""Several evaluation artifacts of one protocol make one Table 1 (topocut.eval.combine, experiments/table1.py)."""
import csv
import json
import runpy
import sys
from pathlib import Path

import numpy as np
import pytest

from topocut.eval.combine import combine, protocol

CONFIG = {"eval": {"policies": ["oracle"], "reference": "oracle", "normalize_by": "task", "train_seeds": 1,
                   "episodes_per_cell": 4, "gifs": 1, "tasks": ["slice"]},
          "sim": {"n_grid": 64, "tuning": {"check_every": 200}}, "seed": 0}


def _artifact(root, name, runs: dict, config=None, seeds=None):
    """An eval artifact: manifest.json with ``config``, episodes/<run>/<key>.json with the given final rewards
    (one per scene), policies.json naming the learned runs' seeds."""
    d = root / name
    for run, rewards in runs.items():
        (d / "episodes" / run).mkdir(parents=True)
        for i, r in enumerate(rewards):
            spec = {"task": "slice", "split": "in" if i % 2 == 0 else "out", "object": "cube" if i % 2 == 0 else
                    "donut", "episode": i, "seed": 1000 + i}
            (d / "episodes" / run / f"slice_{i:03d}.json").write_text(json.dumps(
                {"policy": run, "status": "ok", "final_reward": r, "final_cut_count": 2 + i % 3, "spec": spec}))
    (d / "manifest.json").write_text(json.dumps({"config": config or CONFIG}))
    (d / "policies.json").write_text(json.dumps({
        run: {"policy": run.split("@")[0], "train_seed": s, "checkpoint": None} for run, s in (seeds or {}).items()}))
    return d


def _rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


ORACLE = [0.8, 0.6, 0.9, 0.5, 0.7, 0.4]
SEED0 = [0.4, 0.3, 0.6, 0.2, 0.5, 0.1]
SEED1 = [0.6, 0.5, 0.8, 0.4, 0.7, 0.3]


def test_two_artifacts_make_one_table_with_pooled_and_per_seed_rows(tmp_path):
    a = _artifact(tmp_path, "a", {"oracle": ORACLE, "heuristic": [0.2] * 6})
    cfg_b = json.loads(json.dumps(CONFIG))
    cfg_b["eval"].update(policies=["pddp"], train_seeds=2, gifs=0)  # which policies ran: not the protocol
    b = _artifact(tmp_path, "b", {"pddp@s0": SEED0, "pddp@s1": SEED1}, cfg_b, seeds={"pddp@s0": 0, "pddp@s1": 1})
    out = combine([a, b], tmp_path / "t1")
    assert out["runs"] == ["heuristic", "oracle", "pddp@s0", "pddp@s1"]
    rows = {(r["policy"], r["split"]): r for r in _rows(out["csv"]) if r["object"] == "all" and r["task"] == "slice"}
    ref = np.mean(ORACLE)  # R̂ is normalised by the oracle's mean over the task (both splits)
    seen = [0, 2, 4]
    pooled_seen = np.mean([(SEED0[i] + SEED1[i]) / 2 for i in seen]) / ref
    assert float(rows["pddp", "in"]["R_hat_mean"]) == pytest.approx(pooled_seen)
    assert int(rows["pddp", "in"]["train_seeds"]) == 2
    assert float(rows["heuristic", "out"]["R_hat_mean"]) == pytest.approx(0.2 / ref)
    text = out["seeds_md"].read_text()
    for name, vals in (("seed 0", SEED0), ("seed 1", SEED1)):
        line = next(ln for ln in text.splitlines() if name in ln)
        assert f"{np.mean([vals[i] for i in seen]) / ref:.2f}" in line.split("|")[2]
    assert "pddp@s0" in json.loads((out["csv"].parent / "sources.json").read_text())[str(b)]
    assert not (tmp_path / "t1.partial").exists()


def test_per_seed_rows_use_the_artifacts_reference(tmp_path):
    cfg = json.loads(json.dumps(CONFIG))
    cfg["eval"]["reference"] = "heuristic"
    a = _artifact(tmp_path, "a", {"heuristic": [0.5] * 6, "pddp@s0": SEED0}, cfg, seeds={"pddp@s0": 0})
    text = combine([a], tmp_path / "t1")["seeds_md"].read_text()
    line = next(ln for ln in text.splitlines() if "seed 0" in ln)
    assert f"{np.mean([SEED0[i] for i in (0, 2, 4)]) / 0.5:.2f}" in line.split("|")[2]  # R̂ / the heuristic's 0.5


def test_a_different_protocol_or_a_run_in_two_artifacts_is_refused(tmp_path):
    a = _artifact(tmp_path, "a", {"oracle": ORACLE})
    cfg = json.loads(json.dumps(CONFIG))
    cfg["sim"]["tuning"]["check_every"] = 100
    b = _artifact(tmp_path, "b", {"pddp@s0": SEED0}, cfg)
    with pytest.raises(ValueError, match="'sim.tuning.check_every' is 100"):
        combine([a, b], tmp_path / "t1")
    c = _artifact(tmp_path, "c", {"oracle": ORACLE, "pddp@s0": SEED0})
    with pytest.raises(ValueError, match="run 'oracle' is in both"):
        combine([a, c], tmp_path / "t1")
    assert not (tmp_path / "t1").exists()
    assert "sim.tuning.check_every" in protocol({"config": CONFIG}) and "eval.policies" not in protocol(
        {"config": CONFIG})


def test_a_piece_without_the_reference_takes_it_from_the_piece_that_ran_it(tmp_path):
    # The eval stage refuses a reference outside eval.policies, so a piece of learned policies is its own reference
    a = _artifact(tmp_path, "a", {"oracle": ORACLE, "heuristic": [0.2] * 6})
    cfg = json.loads(json.dumps(CONFIG))
    cfg["eval"].update(policies=["pddp"], reference="pddp", compare_to="pddp")
    b = _artifact(tmp_path, "b", {"pddp@s0": SEED0}, cfg, seeds={"pddp@s0": 0})
    with pytest.raises(ValueError, match=r"differ in eval.reference \(oracle, pddp\); pass reference="):
        combine([a, b], tmp_path / "t1")
    for order in ([a, b], [b, a]):  # whichever comes first, the named reference normalises and is compared with
        rows = {(r["policy"], r["split"]): r for r in _rows(combine(order, tmp_path / "t1", reference="oracle")["csv"])
                if r["object"] == "all" and r["task"] == "slice"}
        assert float(rows["pddp", "in"]["R_hat_mean"]) == pytest.approx(np.mean(SEED0[0::2]) / np.mean(ORACLE))
        assert rows["pddp", "in"]["compared_to"] == "oracle"
    rows = {(r["policy"], r["split"]): r for r in _rows(combine([a, b], tmp_path / "t2", reference="heuristic")["csv"])
            if r["object"] == "all" and r["task"] == "slice"}
    assert float(rows["pddp", "out"]["R_hat_mean"]) == pytest.approx(np.mean(SEED0[1::2]) / 0.2)
    with pytest.raises(ValueError, match="reference 'dp3' is not among the combined policies"):
        combine([a, b], tmp_path / "t3", reference="dp3")
    with pytest.raises(ValueError, match="compare_to 'mppi' is not among the combined policies"):
        combine([a, b], tmp_path / "t3", reference="oracle", compare_to="mppi")
    with pytest.raises(ValueError, match="'oracle' is not among the combined policies"):
        c = _artifact(tmp_path, "c", {"dp3@s0": SEED1}, json.loads(json.dumps(CONFIG)), seeds={"dp3@s0": 0})
        combine([c], tmp_path / "t4")
    assert "eval.reference" not in protocol({"config": cfg})


def test_cli_exits_2_naming_the_problem(tmp_path, monkeypatch, capsys):
    a = _artifact(tmp_path, "a", {"oracle": ORACLE})
    (tmp_path / "empty").mkdir()
    monkeypatch.setattr(sys, "argv", ["table1.py", "--out", str(tmp_path / "t1"), str(a), str(tmp_path / "empty")])
    with pytest.raises(SystemExit) as e:
        runpy.run_path(str(Path(__file__).parents[1] / "experiments" / "table1.py"), run_name="__main__")
    assert e.value.code == 2 and "empty: no manifest.json" in capsys.readouterr().err


def test_flatten_joins_nested_keys():
    from topocut.utils.progress import flatten

    nested = {"a": {"b": 1, "c": {"d": [2]}, "e": {}}, "f": 3}
    assert flatten(nested) == {"a/b": 1, "a/c/d": [2], "a/e": {}, "f": 3}
    assert flatten(nested, sep=".")["a.c.d"] == [2]

"""Table 2 collector: one row per perception checkpoint configuration, read back from the store."""
import json

import pytest

from experiments.table2 import collect, markdown
from topocut.data.store import ArtifactStore


def _ckpt(store, name, model, metrics, params):
    w, _ = store.begin("checkpoint", name, {"model": model}, {"dataset": "dataset/demos:v001"})
    (w.path / "metrics.json").write_text(json.dumps({"metrics": metrics}))
    return w.commit({"parameters": params})


def test_rows_follow_configs_and_reruns_keep_the_newest(tmp_path):
    store = ArtifactStore(tmp_path)
    g = {"model": "graph_transformer", "sort": True, "noise": True, "num_points": 256}
    _ckpt(store, "perception", g, {"val/cluster_acc_seen": 0.5, "val/cluster_acc_unseen": 0.4}, 10)
    _ckpt(store, "perception", {**g, "num_points": 128, "sort": False},
          {"val/cluster_acc_seen": 0.7, "val/cluster_acc_unseen": 0.6, "val/chamfer": 0.004}, 10)
    _ckpt(store, "perception-pointnet", {**g, "model": "pointnet", "num_points": 512},
          {"val/cluster_acc_seen": 0.8, "val/cluster_acc_unseen": 0.75}, 99)
    # a rerun of the first config with another seed in the trainer section: same row key, newer version wins
    w, _ = store.begin("checkpoint", "perception", {"model": g, "seed": 1}, {"dataset": "dataset/demos:v001"})
    (w.path / "metrics.json").write_text(json.dumps({"metrics": {"val/cluster_acc_seen": 0.9}}))
    w.commit({"parameters": 10})
    rows = collect(tmp_path)
    assert [(r["model"], r["points"], r["sort"]) for r in rows] == [
        ("graph_transformer", 128, False), ("graph_transformer", 256, True), ("pointnet", 512, True)]
    assert rows[1]["seen"] == 0.9 and rows[1]["version"] == "perception/v003" and rows[1]["unseen"] is None
    assert rows[2]["parameters"] == 99 and rows[0]["chamfer"] == 0.004
    text = markdown(rows)
    assert text.count("\n") == 2 + 3 and "| pointnet | yes | yes | 512 | 0.800 | 0.750 | — | — |" in text


def _run(store, model, trainer, metrics, seed=0):
    w, _ = store.begin("checkpoint", "perception", {"model": model, "trainer": trainer, "seed": seed},
                       {"dataset": "dataset/demos:v001"})
    (w.path / "metrics.json").write_text(json.dumps({"metrics": metrics}))
    return w.commit({"parameters": 10})


def test_runs_differing_in_any_setting_get_their_own_rows_and_noise_means_jitter(tmp_path):
    store = ArtifactStore(tmp_path)
    g = {"model": "graph_transformer", "sort": True, "noise": True, "noise_std": 0.002, "num_points": 256}
    t = {"max_epochs": 20, "held_out_objects": ["donut", "burger"], "batch_size": 16, "num_workers": 0}
    _run(store, g, t, {"val/cluster_acc_seen": 0.5})  # v001
    _run(store, g, {**t, "max_epochs": 40}, {"val/cluster_acc_seen": 0.6})  # v002: longer
    _run(store, g, {**t, "held_out_objects": []}, {"val/cluster_acc_seen": 0.7})  # v003: nothing held out
    _run(store, {**g, "hidden": 64}, t, {"val/cluster_acc_seen": 0.8})  # v004: a smaller network
    _run(store, {**g, "noise_std": 0.0}, t, {"val/cluster_acc_seen": 0.3})  # v005: noise on, but std 0
    _run(store, {**g, "noise": False}, t, {"val/cluster_acc_seen": 0.35})  # v006: the same run as v005
    _run(store, g, {**t, "num_workers": 4}, {"val/cluster_acc_seen": 0.55}, seed=1)  # v007: rerun of v001
    rows = collect(tmp_path)
    got = {r["version"]: (r["noise"], r["held_out"], r["epochs"], r["other"], r["seen"]) for r in rows}
    assert got == {
        "perception/v002": (True, "burger,donut", 40, "model.hidden=96", 0.6),
        "perception/v003": (True, "none", 20, "model.hidden=96", 0.7),
        "perception/v004": (True, "burger,donut", 20, "model.hidden=64", 0.8),
        "perception/v006": (False, "burger,donut", 20, "model.hidden=96", 0.35),
        "perception/v007": (True, "burger,donut", 20, "model.hidden=96", 0.55)}
    assert "| graph_transformer | yes | no | 256 | 0.350 |" in markdown(rows)


def test_noise_std_is_listed_when_noisy_runs_differ_in_it(tmp_path):
    store = ArtifactStore(tmp_path)
    g = {"model": "graph_transformer", "sort": True, "noise": True, "noise_std": 0.002, "num_points": 256}
    _run(store, g, {}, {})
    _run(store, {**g, "noise_std": 0.01}, {}, {})
    assert sorted(r["other"] for r in collect(tmp_path)) == ["model.noise_std=0.002", "model.noise_std=0.01"]


def test_rows_carry_the_mask_rule_floor_and_what_the_model_adds_to_it(tmp_path):
    """on_rule_errors_*: F's accuracy where the rule is wrong; err_reduction_*: logged, or for a checkpoint from
    before it was logged, 1 - (1 - acc) / (1 - rule) from its accuracies (seen 0.96 vs 0.92: half the errors)."""
    store = ArtifactStore(tmp_path)
    g = {"model": "graph_transformer", "sort": True, "noise": True, "num_points": 256}
    _run(store, g, {}, {"val/cluster_acc_seen": 0.96, "val/mask_rule_acc_seen": 0.92,
                        "val/cluster_acc_unseen": 0.9, "val/mask_rule_acc_unseen": 1.0})
    _run(store, {**g, "num_points": 128}, {}, {"val/cluster_acc_seen": 0.9, "val/mask_rule_acc_seen": 0.95,
                                               "val/cluster_acc_rule_wrong_seen": 0.25,
                                               "val/cluster_err_reduction_seen": -1.0})
    old, new = collect(tmp_path)[::-1]
    assert old["err_reduction_seen"] == pytest.approx(0.5) and old["err_reduction_unseen"] is None  # rule: no error
    assert old["on_rule_errors_seen"] is None  # not recoverable from accuracies
    assert new["on_rule_errors_seen"] == 0.25 and new["err_reduction_seen"] == -1.0
    text = markdown([new])
    assert "on_rule_errors_seen" in text and "| 0.250 | — | -1.000 | — |" in text

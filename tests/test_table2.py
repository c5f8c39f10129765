"""Table 2 collector: one row per perception checkpoint configuration, read back from the store."""
import json

from topocut.data.store import ArtifactStore
from topocut.models.table2 import collect, markdown


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

"""The stages' small decisions, without running a stage: version pinning in stage=all, DDP refusal, the
MPPI episode log, teleop task checks, and which datasets are shards of a merge."""
from pathlib import Path
from types import SimpleNamespace

import pytest

from topocut.data.store import ArtifactStore


def test_stage_all_pins_the_versions_its_stages_produced():
    from pipelines.all import produced_versions

    cfg = SimpleNamespace(data={"dataset": "demos", "encoder": "perception"})
    assert produced_versions("mppi", {"dataset": "/o/dataset/demos/v007", "reused": True}, cfg) == \
        {"data.version": "v007"}
    assert produced_versions("pretrain", {"checkpoint": "/o/checkpoint/perception/v003"}, cfg) == \
        {"data.encoder_version": "v003"}
    # a checkpoint under another name (perception-pointnet) is not the encoder bc reads: no pin
    assert produced_versions("pretrain", {"checkpoint": "/o/checkpoint/perception-pointnet/v001"}, cfg) == {}
    assert produced_versions("simulate", {"artifact": "/o/sim/x/v001"}, cfg) == {}
    bc = {"pddp": {"checkpoint": "/o/checkpoint/pddp/v004", "val/loss": 0.1},
          "dp3": {"checkpoint": "/o/checkpoint/dp3/v002", "reused": True}, "3dda": {"rank": 1}}
    pins = produced_versions("bc", bc, cfg)
    assert pins == {"++eval.checkpoints": "{pddp:v004,dp3:v002}"}
    assert produced_versions("bc", {"3dda": {"rank": 1}}, cfg) == {}


def test_stage_all_pins_parse_as_hydra_overrides():
    """3dda is not a valid key in a dotted override; the one dict override parses and sets every version."""
    import os

    from hydra import compose, initialize_config_dir

    from pipelines.all import CONF_DIR
    from topocut.config import register_configs

    register_configs()
    pins = {"++eval.checkpoints": "{3dda:v001,pddp:v004}"}
    with initialize_config_dir(config_dir=os.fspath(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=[f"{k}={v}" for k, v in pins.items()] + ["stage=eval"])
    assert dict(cfg.eval.checkpoints) == {"3dda": "v001", "pddp": "v004"}


def test_eval_loads_the_pinned_checkpoint_version_and_records_it(tmp_path, monkeypatch):
    import topocut.policies.baselines.module as baselines
    from pipelines.eval import build_policies

    store = ArtifactStore(tmp_path)
    for i in range(3):  # checkpoint/dp3/v001..v003
        w, _ = store.begin("checkpoint", "dp3", {"i": i})
        (w.path / "model.ckpt").write_bytes(bytes([i]))
        w.commit()
    monkeypatch.setattr(baselines, "load_pose_policy", lambda path, **kw: Path(path).read_bytes())
    ctx = SimpleNamespace(store=store, seed=0, device="cpu")
    args = (None, None, None, None, None, {})
    policies, inputs = build_policies(ctx, ["dp3"], *args, versions={"dp3": "v002"})
    assert policies["dp3"] == bytes([1]) and inputs["dp3"].startswith("checkpoint/dp3:v002@")
    policies, inputs = build_policies(ctx, ["dp3"], *args)  # unpinned: the latest
    assert policies["dp3"] == bytes([2]) and inputs["dp3"].startswith("checkpoint/dp3:v003@")


def test_stage_all_refuses_a_multi_process_trainer():
    from pipelines.all import run

    with pytest.raises(ValueError, match="trainer.strategy=ddp with trainer.devices=2.*stage=pretrain trainer=ddp"):
        run(None, ["pretrain"], trainer=SimpleNamespace(strategy="ddp", devices=2))


def test_mppi_episode_log_keeps_the_last_record_of_each_episode(tmp_path):
    from pipelines.mppi import read_records

    log = tmp_path / "episodes.jsonl"
    assert read_records(log) == []
    log.write_text('{"episode": 0, "final_reward": 0.1}\n{"episode": 1, "final_reward": 0.2}\n'
                   '{"episode": 1, "final_reward": 0.3}\n\n')  # episode 1 re-run after a crash
    assert read_records(log) == [{"episode": 0, "final_reward": 0.1}, {"episode": 1, "final_reward": 0.3}]


def test_teleop_log_replays_only_under_its_task():
    from pipelines.teleop import check_task

    check_task({"task": "slice"}, "slice", "log.json")
    with pytest.raises(ValueError, match="log.json: the log was recorded for task 'dice'.*task=dice"):
        check_task({"task": "dice"}, "slice", "log.json")


def test_merge_takes_shards_by_manifest_not_by_name_prefix(tmp_path):
    from pipelines.merge import shards_of

    store = ArtifactStore(tmp_path)

    def commit(name, **extra):
        w, _ = store.begin("dataset", name, {"name": name}, extra=extra)
        (w.path / "f.txt").write_text(name)
        return w.commit()

    a = commit("demos-slice-cube-s0-aaaaaaaa", shard_of="demos")
    b = commit("demos-slice-cube-s0-bbbbbbbb", shard_of="demos")  # same job, another planner setting
    commit("demos-paper", shard_of=None)  # merged elsewhere; starts with "demos-" but is no shard
    commit("demos-paper-dice-ham-s1-cccccccc", shard_of="demos-paper")
    commit("demos")  # the merged dataset itself
    assert shards_of(store, "demos") == {Path(a).parent.name: a, Path(b).parent.name: b}
    assert list(shards_of(store, "demos-paper")) == ["demos-paper-dice-ham-s1-cccccccc"]

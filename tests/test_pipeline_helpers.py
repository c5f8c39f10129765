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
    assert produced_versions("bc", bc, cfg, policies=["oracle", "dp3"]) == {"++eval.checkpoints": "{dp3:v002}"}
    assert produced_versions("bc", bc, cfg, policies=["oracle"]) == {}


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
    from topocut.eval.runner import build_policies

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


@pytest.mark.parametrize("jobs", [1, 2])
def test_stage_all_at_paper_shape_runs_a_shard_per_cell_one_merge_and_a_bc_per_seed(tmp_path, monkeypatch, jobs):
    """make paper's plan, with the stages replaced by recorders: every (task, object) cell writes its own shard,
    the merge takes exactly those, bc runs once per training seed, and each later stage reads the versions the
    earlier ones wrote; the user's other overrides reach every run, their task= gives way to the cells'.
    data.jobs=2, trainer.jobs=2: the cells and the seeds run two at a time through joblib (its threading backend
    here, so that the recorder in this process sees them; the pipeline asks for loky's worker processes) and the
    plan is the same."""
    import joblib

    import topocut.run
    from pipelines.all import run

    calls = []
    backends = []
    real = joblib.Parallel

    def parallel(n_jobs, backend):
        backends.append((n_jobs, backend))
        return real(n_jobs=n_jobs, backend="threading")

    monkeypatch.setattr(joblib, "Parallel", parallel)

    def fake(cfg, run_dir, overrides):
        stage, i = cfg.stage.name, len(calls)
        calls.append((run_dir.name, cfg, overrides))
        if stage == "mppi":
            return {"dataset": f"/o/dataset/demos-{cfg.task.name}-{cfg.object.name}-s0-k/v001"}
        if stage == "merge":
            return {"dataset": "/o/dataset/demos/v005"}
        if stage == "pretrain":
            return {"checkpoint": "/o/checkpoint/perception/v002"}
        if stage == "bc":
            return {"pddp": {"checkpoint": f"/o/checkpoint/pddp/v00{i}", "seed": cfg.seed}}
        return {}

    monkeypatch.setattr(topocut.run, "run_stage", fake)
    user = ["task=slice", "planner.iterations=1", "seed=4", "eval.train_seeds=3", "data.tasks=[slice,dice]",
            "data.objects=[cake,cube]", "stage=all",
            "stage.run.sequence=[mppi,pretrain,bc,eval]"]
    config = {"data": {"tasks": ["slice", "dice"], "objects": ["cake", "cube"], "jobs": jobs}, "trainer": {"jobs": jobs},
              "task": {"name": "slice"},
              "object": {"name": "cake"}, "seed": 4, "eval": {"train_seeds": 3, "policies": ["oracle", "pddp"]}}
    ctx = SimpleNamespace(overrides=user, config=config, run_dir=tmp_path)
    out = run(ctx, ["mppi", "pretrain", "bc", "eval"])
    labels = [c[0] for c in calls]
    cells = ["mppi-slice-cake", "mppi-slice-cube", "mppi-dice-cake", "mppi-dice-cube"]
    seeds = ["bc-s4", "bc-s5", "bc-s6"]
    in_order = (lambda x: sorted(x)) if jobs > 1 else (lambda x: x)  # several at once: any order
    assert in_order(labels[:4]) == in_order(cells) and labels[4:6] == ["merge", "pretrain"]
    assert in_order(labels[6:9]) == in_order(seeds) and labels[9:] == ["eval"]
    assert backends == ([(2, "loky"), (2, "loky")] if jobs > 1 else [])
    labels = cells + labels[4:6] + seeds + labels[9:]
    cfgs = {c[0]: c[1] for c in calls}
    assert [(cfgs[k].task.name, cfgs[k].object.name, cfgs[k].data.shard) for k in labels[:4]] == \
        [("slice", "cake", True), ("slice", "cube", True), ("dice", "cake", True), ("dice", "cube", True)]
    assert cfgs["mppi-dice-cube"].task.max_cuts >= 3  # the dice cell composes dice's own config
    assert list(cfgs["merge"].stage.run.only) == [f"demos-{t}-{o}-s0-k" for t, o in
                                                  [("slice", "cake"), ("slice", "cube"), ("dice", "cake"),
                                                   ("dice", "cube")]]
    assert not cfgs["merge"].data.shard and cfgs["pretrain"].data.version == "v005"
    assert [cfgs[f"bc-s{s}"].seed for s in (4, 5, 6)] == [4, 5, 6]
    assert all(cfgs[f"bc-s{s}"].data.encoder_version == "v002" for s in (4, 5, 6))
    ev = cfgs["eval"]
    assert ev.seed == 4 and ev.eval.train_seeds == 3 and ev.data.version == "v005"
    bc_versions = {c[0]: i for i, c in enumerate(calls) if c[0].startswith("bc-")}  # the fake's version: call index
    # the last seed's checkpoint: eval finds its siblings by manifest
    assert dict(ev.eval.checkpoints) == {"pddp": f"v00{bc_versions['bc-s6']}"}
    assert all(c.planner.iterations == 1 for _, c, _ in calls)
    assert set(out["wall_s"]) == set(labels) | ({"mppi-at-once", "bc-at-once"} if jobs > 1 else set())


def test_stage_all_refuses_an_unknown_cell():
    from hydra import compose, initialize_config_dir

    from pipelines.all import CONF_DIR
    from topocut.config import ConfigError, validate

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["stage=all", "data.objects=[cake,pizza]"])
        with pytest.raises(ConfigError, match="data.objects.*'pizza'.*valid: .*cake"):
            validate(cfg)
        cfg = compose(config_name="config", overrides=["stage=all", "data.tasks=[slice,scooping]"])
        with pytest.raises(ConfigError, match="data.tasks.*'scooping'.*valid: slice, stick, dice, pyramid"):
            validate(cfg)


def test_eval_jobs_cut_the_work_into_tasks_and_leave_the_artifact_key_alone():
    """eval.jobs: the work as (policy, specs) tasks: a batched policy's are run_evaluation's batches of
    sim.batch_size consecutive specs (each episode keeps its batch-mates), MPPI's (uses_simulator) one spec each,
    batch by batch with every policy on it; the number of processes does not key the evaluation artifact."""
    import dataclasses

    from pipelines.eval import artifact_config
    from topocut.eval.config import EvalConfig
    from topocut.eval.runner import eval_tasks, runs_one_at_a_time

    assert {n for n in ("oracle", "heuristic", "mppi", "pddp", "dp3", "mypkg.mod:Mine")
            if runs_one_at_a_time(n)} == {"mppi"}
    from topocut.planning import HeuristicPolicy, MPPIPolicy  # the registry's sim_state input = the engine's rule

    assert MPPIPolicy.uses_simulator and not getattr(HeuristicPolicy, "uses_simulator", False)
    specs = list(range(5))
    tasks = eval_tasks(specs, ["oracle", "mppi"], 2, {"mppi"})
    assert tasks == [("oracle", [0, 1]), ("mppi", [0]), ("mppi", [1]),
                     ("oracle", [2, 3]), ("mppi", [2]), ("mppi", [3]),
                     ("oracle", [4]), ("mppi", [4])]
    assert [len(s) for n, s in tasks if n == "oracle"] == [2, 2, 1]
    assert [len(s) for n, s in tasks if n == "mppi"] == [1] * 5
    specs = list(range(11))
    tasks = eval_tasks(specs, ["oracle", "heuristic", "mppi"], 4, {"mppi"})
    pairs = [(n, s) for n, part in tasks for s in part]
    assert sorted(pairs) == sorted((n, s) for n in ("oracle", "heuristic", "mppi") for s in specs)  # each once
    assert [s for n, s in tasks if n == "heuristic"] == [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 10]]
    assert [n for n, _ in tasks[:6]] == ["oracle", "heuristic", "mppi", "mppi", "mppi", "mppi"]
    assert max(part[0] for _, part in tasks[:6]) < min(part[0] for _, part in tasks[6:])  # batch by batch
    ev = EvalConfig()
    keys = [artifact_config(dataclasses.replace(ev, jobs=j), None, None, None, None, None, None, {}, 0) for j in (1, 8)]
    assert keys[0] == keys[1] and "jobs" not in keys[0]["eval"]
    with pytest.raises(ValueError, match="eval.jobs=0"):
        dataclasses.replace(ev, jobs=0).validate()

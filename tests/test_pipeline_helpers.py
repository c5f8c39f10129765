"""The stages' small decisions, without running a stage: version pinning in stage=all, DDP refusal, the
MPPI episode log, teleop task checks, and which datasets are shards of a merge."""
from pathlib import Path
from types import SimpleNamespace

import pytest

from tests.stage_runner import run as run_stage
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
    from topocut.data.collection import read_records

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
    from topocut.data.collection import shards_of

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


def test_merge_of_every_shard_takes_them_cell_by_cell_then_by_first_episode(tmp_path):
    """Shards carried from two machines (each its own episode range of every cell) sort as one run's parts."""
    from types import SimpleNamespace

    from topocut.data.collection import cell_order, shards_of

    store = ArtifactStore(tmp_path)
    made = []
    for task, obj, first in (("slice", "cube", 33), ("dice", "cake", 0), ("slice", "cube", 0), ("slice", "cake", 10),
                             ("dice", "cake", 33), ("scoop", "cake", 0), ("slice", "cake", 0), ("dice", "cake", 10)):
        config = {"task": {"name": task}, "object": {"name": obj}, **({"first_episode": first} if first else {})}
        name = f"demos-{task}-{obj}-s0-{len(made):08d}"  # names in no useful order
        w, _ = store.begin("dataset", name, config, extra={"shard_of": "demos"})
        w.commit()
        made.append((task, obj, first))
    data = SimpleNamespace(tasks=["slice", "dice"], objects=["cake", "cube"])
    order = cell_order(store, shards_of(store, "demos"), data)
    got = [(store.manifest(store.resolve("dataset", n, verify=False))["config"]["task"]["name"],
            store.manifest(store.resolve("dataset", n, verify=False))["config"]["object"]["name"],
            store.manifest(store.resolve("dataset", n, verify=False))["config"].get("first_episode", 0)) for n in order]
    assert got == [("slice", "cake", 0), ("slice", "cake", 10), ("slice", "cube", 0), ("slice", "cube", 33),
                   ("dice", "cake", 0), ("dice", "cake", 10), ("dice", "cake", 33), ("scoop", "cake", 0)]


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

    def parallel(n_jobs, backend, batch_size="auto"):
        backends.append((n_jobs, backend, batch_size))
        return real(n_jobs=n_jobs, backend="threading", batch_size=batch_size)

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
    assert backends == ([(2, "loky", 1), (2, "loky", 1)] if jobs > 1 else [])  # runs handed out one by one
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
    from topocut.planning import GoalPlanesPolicy, MPPIPolicy  # the registry's sim_state input = the engine's rule

    assert MPPIPolicy.uses_simulator and not getattr(GoalPlanesPolicy, "uses_simulator", False)
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


@pytest.mark.parametrize("jobs", [1, 3])
def test_stage_all_cuts_cells_into_parts_costliest_first_and_merges_them_all(tmp_path, monkeypatch, jobs):
    """data.episodes_per_job=2 over 5 episodes: each cell runs as parts e0-1, e2-3, e4 (data.first_episode,
    data.episodes), handed to the workers one by one (batch_size=1) part index first, the dice cells before the slice
    ones within an index; one merge takes exactly every part's shard, cell by cell in episode order."""
    import joblib

    import topocut.run
    from pipelines.all import demo_runs, run

    calls, backends, handed = [], [], []
    real = joblib.Parallel

    def parallel(n_jobs, backend, batch_size="auto"):
        backends.append((n_jobs, backend, batch_size))
        inner = real(n_jobs=n_jobs, backend="threading", batch_size=batch_size)

        def call(tasks):
            tasks = list(tasks)
            handed.append([args[1].name for _, args, _ in tasks])  # _timed_stage(cfg, run_dir, overrides)
            return inner(tasks)
        return call

    monkeypatch.setattr(joblib, "Parallel", parallel)

    def fake(cfg, run_dir, overrides):
        calls.append((run_dir.name, cfg, overrides))
        if cfg.stage.name == "mppi":
            return {"dataset": f"/o/dataset/demos-{cfg.task.name}-{cfg.object.name}-e{cfg.data.first_episode}/v001"}
        return {"dataset": "/o/dataset/demos/v005"} if cfg.stage.name == "merge" else {}

    monkeypatch.setattr(topocut.run, "run_stage", fake)
    user = ["data.tasks=[slice,dice]", "data.objects=[cake,cube]", "data.episodes=5", "data.episodes_per_job=2",
            "stage=all", "stage.run.sequence=[mppi,pretrain]"]
    config = {"data": {"tasks": ["slice", "dice"], "objects": ["cake", "cube"], "jobs": jobs, "episodes": 5,
                       "episodes_per_job": 2, "first_episode": 0},
              "task": {"name": "slice"}, "object": {"name": "cake"}, "seed": 0, "eval": {"policies": ["oracle"]}}
    order = [f"mppi-{t}-{o}-{e}" for e in ("e0-1", "e2-3", "e4-4") for t in ("dice", "slice") for o in ("cake", "cube")]
    assert [label for label, _, _ in demo_runs(config)] == order
    out = run(SimpleNamespace(overrides=user, config=config, run_dir=tmp_path), ["mppi", "pretrain"])
    labels = [c[0] for c in calls]
    assert sorted(labels[:12]) == sorted(order) and labels[12:] == ["merge", "pretrain"]
    if jobs > 1:  # handed out in that order, one run at a time, to 3 workers
        assert backends == [(3, "loky", 1)] and handed == [order]
    else:
        assert backends == [] and labels[:12] == order
    cfgs = {c[0]: c[1] for c in calls}
    for t in ("slice", "dice"):
        for o in ("cake", "cube"):  # every episode of the cell exactly once, in shards of its own name
            parts = sorted((c.data.first_episode, c.data.episodes) for c in cfgs.values()
                           if c.stage.name == "mppi" and (c.task.name, c.object.name) == (t, o))
            assert parts == [(0, 2), (2, 2), (4, 1)]
            assert [e for f, n in parts for e in range(f, f + n)] == list(range(5))
    assert all(c.data.shard for c in cfgs.values() if c.stage.name == "mppi")
    assert cfgs["mppi-dice-cube-e4-4"].task.max_cuts >= 3  # a dice part composes dice's own config
    assert list(cfgs["merge"].stage.run.only) == [f"demos-{t}-{o}-e{f}" for t in ("slice", "dice")
                                                  for o in ("cake", "cube") for f in (0, 2, 4)]
    assert cfgs["pretrain"].data.version == "v005"
    assert set(out["wall_s"]) == set(labels) | ({"mppi-at-once"} if jobs > 1 else set())


def test_stage_all_parts_keep_the_unsplit_plan_by_default_and_refuse_a_bad_size():
    from hydra import compose, initialize_config_dir

    from pipelines.all import CONF_DIR, EPISODE_COST, demo_runs
    from topocut.config import ConfigError

    config = {"data": {"tasks": ["slice", "dice"], "objects": ["cake"], "episodes": 67}, "task": {"name": "slice"},
              "object": {"name": "cake"}}
    assert demo_runs(config) == [("mppi-slice-cake", {"task": "slice", "object": "cake", "data.shard": "true"}, (0, 0)),
                                 ("mppi-dice-cake", {"task": "dice", "object": "cake", "data.shard": "true"}, (1, 0))]
    # a user's data.first_episode: the parts cut the cell's range from there
    config["data"].update(episodes=3, episodes_per_job=2, first_episode=10, tasks=["pyramid", "slice"])
    runs = demo_runs(config)
    assert [(label, own["data.first_episode"], own["data.episodes"]) for label, own, _ in runs] == \
        [("mppi-pyramid-cake-e10-11", 10, 2), ("mppi-slice-cake-e10-11", 10, 2),  # unmeasured pyramid: costliest
         ("mppi-pyramid-cake-e12-12", 12, 1), ("mppi-slice-cake-e12-12", 12, 1)]
    assert max(EPISODE_COST, key=EPISODE_COST.get) == "dice"
    with pytest.raises(ConfigError, match="data.episodes_per_job: 0 is not valid"):
        demo_runs({**config, "data": {**config["data"], "episodes_per_job": 0}})
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        paper = compose(config_name="config", overrides=["stage=all", "scale=paper"])
    from omegaconf import OmegaConf

    runs = demo_runs(OmegaConf.to_container(paper, resolve=True))  # make paper: 15 cells x 7 parts
    assert paper.data.episodes_per_job == 10 and len(runs) == 105
    assert [own["data.episodes"] for _, own, _ in runs] == [10] * 90 + [7] * 15
    assert [own["task"] for _, own, _ in runs[:15]] == ["dice"] * 5 + ["stick"] * 5 + ["slice"] * 5


def test_stage_all_gives_each_demonstration_cell_its_own_task_parameters():
    """data.task_overrides: each cell's stage=mppi run gets its task's keys (composed there as that task's config);
    a key the task lacks, or an unknown task, is refused with the key's name and what is valid."""
    from hydra import compose, initialize_config_dir

    from pipelines.all import CONF_DIR, _compose, demo_runs
    from topocut.config import ConfigError, register_configs, validate

    register_configs()  # the task group's schemas (topocut.run does this on import)
    config = {"data": {"tasks": ["slice", "stick", "dice"], "objects": ["cake"], "episodes": 2,
                       "task_overrides": {"stick": {"thickness": 0.05, "width": 0.04}, "dice": {"size": 0.05}}},
              "task": {"name": "slice"}, "object": {"name": "cake"}}
    own = {label: o for label, o, _ in demo_runs(config)}
    assert own["mppi-slice-cake"] == {"task": "slice", "object": "cake", "data.shard": "true"}
    assert own["mppi-stick-cake"]["task.thickness"] == 0.05 and own["mppi-stick-cake"]["task.width"] == 0.04
    assert own["mppi-dice-cake"]["task.size"] == 0.05 and "task.width" not in own["mppi-dice-cake"]
    cell = _compose(["stage=mppi"] + [f"{k}={v}" for k, v in own["mppi-stick-cake"].items()])
    assert cell.task.name == "stick" and cell.task.width == 0.04 and cell.task.thickness == 0.05
    for bad, match in (({"dice": {"width": 0.05}}, r"data.task_overrides.dice.width: not a parameter of task=dice"),
                       ({"dicer": {"size": 0.05}}, r"data.task_overrides.dicer: unknown task")):
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose(config_name="config", overrides=["stage=all", f"++data.task_overrides={_yaml(bad)}"])
        with pytest.raises(ConfigError, match=match):
            validate(cfg)


def _yaml(d: dict) -> str:
    return "{" + ",".join(f"{k}:{_yaml(v) if isinstance(v, dict) else v}" for k, v in d.items()) + "}"


def test_mppi_keeps_one_simulator_per_process_for_equal_configs():
    """The process's env cache (topocut.sim.env.cached_env, stage=mppi's): parts of the same sim config (and batch size) reuse the env; another config
    destroys the held env's solver before building its own."""
    import dataclasses

    from topocut.sim import env as simenv
    from topocut.sim.config import SimConfig

    built, destroyed = [], []

    class Solver:
        def destroy(self):
            destroyed.append(self)

    class Env:
        def __init__(self, sim, batch_size):
            self.sim, self.batch_size, self.solver = sim, batch_size, Solver()
            built.append(self)

    simenv.release_env()
    try:
        sim = SimConfig(n_grid=32)
        a = simenv.cached_env(sim, 4, make=Env)
        assert simenv.cached_env(SimConfig(n_grid=32), 4, make=Env) is a and len(built) == 1  # equal, not the same
        held = a.solver
        sim.n_grid = 40  # the caller's object changed after the fact: the key kept its own copy
        b = simenv.cached_env(sim, 4, make=Env)
        assert b is not a and destroyed == [held] and a.solver is None
        c = simenv.cached_env(sim, 2, make=Env)  # another batch size
        d = simenv.cached_env(dataclasses.replace(sim, tuning={"warp_scatter": "off"}), 2, make=Env)
        assert len({id(x) for x in (a, b, c, d)}) == 4 and len(destroyed) == 3
        assert simenv.cached_env(dataclasses.replace(sim, tuning={"warp_scatter": "off"}), 2, make=Env) is d
    finally:
        simenv.release_env()
    assert len(destroyed) == 4 and all(x.solver is None for x in built)


def test_stage_merge_of_every_shard_gives_the_episodes_in_one_runs_order(tmp_path):
    """stage=merge with no stage.run.only, for real: shards committed in scrambled order (as two machines' carried
    episode ranges arrive) merge cell by cell (data.tasks x data.objects), each cell's parts by first episode."""
    import sys

    from test_contracts import REPO, _env
    from test_episodes import make_episode

    from topocut.data.episodes import EpisodeDataset, EpisodeWriter

    store = ArtifactStore(tmp_path)
    # (task, object, first episode); each shard one episode whose seed is its place in one run's order
    want = [("slice", "cake", 0), ("slice", "cake", 33), ("slice", "cube", 0), ("dice", "cake", 0), ("dice", "cake", 33)]
    for i in (4, 1, 3, 0, 2):
        task, obj, first = want[i]
        config = {"task": {"name": task}, "object": {"name": obj}, **({"first_episode": first} if first else {})}
        w, _ = store.begin("dataset", f"demos-{chr(ord('a') + (7 * i) % 5)}", config, extra={"shard_of": "demos"})
        EpisodeWriter(w.path / "data.zarr", points_per_step=32).add_episode(*make_episode(1, 20, seed=i, task=task,
                                                                                            obj=obj))
        w.commit()
    proc = run_stage([sys.executable, "-m", "topocut.run", "stage=merge", "logger=none", "progress=false",
                      "data.tasks=[slice,dice]", "data.objects=[cake,cube]", f"outputs_root={tmp_path}"],
                     cwd=REPO, env=_env(tmp_path), timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    ds = EpisodeDataset(store.resolve("dataset", "demos") / "data.zarr")
    assert [ds.meta(e)["seed"] for e in range(ds.num_episodes)] == [0, 1, 2, 3, 4]

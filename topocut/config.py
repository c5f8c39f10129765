"""Typed config schemas (Hydra ConfigStore) and cross-field checks.

Every group in ``conf/`` merges onto a dataclass defined next to the code that
uses it, so a misspelt key or a wrong type fails at composition time, before
anything is simulated.  ``validate`` adds the checks no single dataclass can
make alone, naming the full key path in its message.
"""
from __future__ import annotations

import difflib
import inspect
import os
from dataclasses import dataclass, field, fields, is_dataclass
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, OmegaConf

from topocut.eval.config import EvalConfig
from topocut.models.config import DynamicsConfig
from topocut.planning.config import MPPIConfig
from topocut.policies.config import PDDPConfig, PolicyTrainConfig, SamplerConfig
from topocut.reward.config import RewardConfig
from topocut.sim.config import SimConfig
from topocut.sim.objects import OBJECTS
from topocut.tasks.config import TaskConfig
from topocut.topology.config import TopologyConfig
from topocut.topology.observation import ObservationConfig
from topocut.utils.logger import LoggerConfig

STAGES = ("simulate", "mppi", "teleop", "merge", "pretrain", "bc", "eval", "all")
PROFILERS = ("none", "simple", "advanced", "pytorch")  # trainer.profiler: Lightning's, by its own names


class ConfigError(ValueError):
    """A composed config that is well-typed but inconsistent."""


@dataclass
class ObjectConfig:
    name: str = "cake"
    randomize_pose: bool = True  # translation, yaw and scale drawn from the seed (docs/sim.md)
    translation: float = 0.03  # ± scene units
    yaw_deg: float = 15.0  # ± degrees
    scale_min: float = 0.8
    scale_max: float = 1.2


@dataclass
class StageConfig:
    name: str = MISSING
    run: Any = MISSING  # a partial over pipelines.<stage>.run with explicit sub-configs


@dataclass
class TrainerConfig:
    accelerator: str = "cpu"
    devices: Any = 1
    strategy: str = "auto"  # "ddp" for several GPUs
    precision: str = "32-true"
    max_epochs: int = 20
    max_steps: int = -1
    batch_size: int = 16
    num_workers: int = 0
    val_fraction: float = 0.2
    log_every_n_steps: int = 5
    # Lightning's profiler of the fit: none | simple (seconds per hook: batch fetch, training_step, backward,
    # optimizer step, validation, checkpoint) | advanced (cProfile per hook) | pytorch (operators, CUDA kernels);
    # its report goes to fit-profile.txt in the run's directory. Costs little for simple, much for the others
    profiler: str = "none"
    held_out_objects: list[str] = field(default_factory=lambda: ["donut", "burger", "sushi", "steak"])
    # stage=all: training seeds (eval.train_seeds) trained at once, each stage=bc in its own process on the same
    # device (joblib's loky workers; scale=paper: 3).  Not part of a checkpoint's key
    jobs: int = 1


@dataclass
class DataConfig:
    dataset: str = "demos"  # name written by mppi/merge and read by pretrain/bc/eval
    version: str = "latest"
    episodes: int = 2  # episodes per mppi run (job)
    # stage=mppi writes episodes first_episode .. first_episode + episodes - 1 (seeds demo_episode_seed(seed, e)): a part
    # of a larger run (stage=all's data.episodes_per_job); keys an artifact only when nonzero
    first_episode: int = 0
    points_per_step: int = 2048
    encoder: str = "perception"  # checkpoint name of the pretrained encoder Φ
    encoder_version: str = "latest"
    # stage=all's demonstration cells: one mppi run per (task, object), each a shard of ``dataset``, then one
    # merge. [] = the run's own task / object (one cell, no shard). scale=paper: 3 tasks x the 5 seen objects.
    tasks: list[str] = field(default_factory=list)
    objects: list[str] = field(default_factory=list)
    # stage=all's demonstration cells: task parameters per task over conf/task/<task>.yaml, as eval.task_overrides
    # is the evaluation's (`data.task_overrides={stick:{thickness:0.05,width:0.05},dice:{size:0.05}}`): each task
    # takes only the keys it reads (issue #50), so `task.width=...` on stage=all's command line (its own task:
    # slice) is refused.  A lone stage=mppi run takes `task.<key>=...` itself.
    task_overrides: dict[str, dict[str, Any]] = field(default_factory=dict)
    shard: bool = False  # stage=mppi writes a shard of ``dataset`` (set by stage=all's cells; multiruns always do)
    # stage=all: demonstration cells made at once, each in its own process (joblib's loky workers).  One process
    # leaves a GPU mostly idle (its host work): on one H100, steady rates of 2.4 cuts/s with 8 processes, 3.9 with
    # 16, 6.2 with 16 under CUDA MPS (docs/benchmarks.md, "Demonstrations from several processes"); 1: one cell after
    # another, in-process
    jobs: int = 1
    # stage=all: cut each cell into stage=mppi runs of at most this many episodes (data.first_episode / episodes),
    # handed to the data.jobs processes as they free up, so that the costly cells (dice) do not run long after the
    # others; null: one run per cell.  scale=paper: 10 (docs/data.md)
    episodes_per_job: int | None = None
    # stage=mppi also runs the heuristic on every n-th episode (index multiple of n) from the same state, for
    # docs/data.md's comparison; 0: never.  scale=paper: 10 (H100, 16 processes: a comparison cost 5-12 s beside
    # a 15-40 s MPPI episode, a quarter of the demonstrations' time; the 405-episode protocol compares the two anyway)
    heuristic_every: int = 1


@dataclass
class PolicyConfig:
    """PDDP: the network and diffusion (``net``), its training (``train``) and its sampler."""

    net: PDDPConfig = field(default_factory=PDDPConfig)
    train: PolicyTrainConfig = field(default_factory=PolicyTrainConfig)
    sampler: SamplerConfig = field(default_factory=SamplerConfig)


@dataclass
class TopoCutConfig:
    stage: StageConfig = field(default_factory=StageConfig)
    task: TaskConfig = field(default_factory=TaskConfig)
    object: ObjectConfig = field(default_factory=ObjectConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    topology: TopologyConfig = field(default_factory=TopologyConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    planner: MPPIConfig = field(default_factory=MPPIConfig)
    observation: ObservationConfig = field(default_factory=ObservationConfig)
    model: DynamicsConfig = field(default_factory=DynamicsConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    trainer: TrainerConfig = field(default_factory=TrainerConfig)
    data: DataConfig = field(default_factory=DataConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    seed: int = 0
    device: str = "auto"
    outputs_root: str = "outputs"
    progress: bool = True


def register_configs() -> None:
    cs = ConfigStore.instance()
    cs.store(name="base_config", node=TopoCutConfig)
    # the task group's schemas: conf/task/<task>.yaml starts from base_<task> (its task's dataclass), so a key the
    # task does not read (task=pyramid task.width=...) is refused while composing, naming the pyramid's keys
    from topocut.tasks import TASKS, task_config_class

    for name in TASKS:
        cs.store(group="task", name=f"base_{name}", node=task_config_class(name))
    # ${pid:} in hydra.run.dir: two runs started in the same second get directories of their own
    if not OmegaConf.has_resolver("pid"):
        OmegaConf.register_new_resolver("pid", lambda: os.getpid())


def _check_task_overrides(key: str, overrides) -> None:
    """Each entry names a registered task and only keys of that task's own config (its dataclass)."""
    from topocut.tasks import TASKS, task_config_class, task_keys

    for task, over in (overrides or {}).items():
        _check(task in TASKS, f"{key}.{task}", f"unknown task; valid: {', '.join(TASKS)}")
        params = [k for k in task_keys(task) if k not in ("name", "stage")]
        bad = [k for k in (over or {}) if k not in params]
        _check(not bad, f"{key}.{task}.{bad[0] if bad else ''}", f"not a parameter of task={task}; valid keys of "
               f"{task_config_class(task).__name__}: {', '.join(params)}")


def _check(cond: bool, key: str, msg: str) -> None:
    if not cond:
        raise ConfigError(f"{key}: {msg}")


def unknown_key_error(full_key: str, schema: type) -> ConfigError:
    """The message for a key its group's dataclass does not declare, listing the ones it does."""
    valid = [f.name for f in fields(schema)]
    group, _, leaf = full_key.rpartition(".")
    close = difflib.get_close_matches(leaf, valid, n=1)
    # a key one level down, such as sim.warp_scatter for sim.tuning.warp_scatter (moved into sim.tuning)
    nested = [f"{f.name}.{leaf}" for f in fields(schema)
              if is_dataclass(f.default_factory) and leaf in {g.name for g in fields(f.default_factory)}]
    close = close or nested
    hint = f" (did you mean {group + '.' if group else ''}{close[0]}?)" if close else ""
    where = group or "the root config"
    if issubclass(schema, TaskConfig) and group == "task":  # each task has keys of its own: say whose these are
        from topocut.tasks import tasks_with_key

        task = next((f.default for f in fields(schema) if f.name == "name"), "")
        owners = tasks_with_key(leaf)
        hint = hint or (f" (a key of task={', '.join(owners)})" if owners else "")
        where = f"task={task} ({schema.__name__})" if task else f"task ({schema.__name__})"
    return ConfigError(f"{full_key}: unknown key{hint}; valid keys of {where}: {', '.join(valid)}")


def check_known_keys(node: DictConfig, prefix: str = "") -> None:
    """Every key must be declared by its group's dataclass.  Hydra's ``+key=value`` adds a key the schema lacks
    without complaint (OmegaConf then drops it when building the dataclass), so ``+planner.num_sample=64`` would
    run with the default silently.  Dicts the schema leaves open (eval.checkpoints, eval.task_overrides) take
    any key; stage.run is checked against the stage function's signature."""
    schema = OmegaConf.get_type(node)
    if not is_dataclass(schema):
        return
    valid = {f.name for f in fields(schema)}
    for key in node.keys():
        if key not in valid:
            raise unknown_key_error(f"{prefix}{key}", schema)
        if not OmegaConf.is_interpolation(node, key) and not OmegaConf.is_missing(node, key):
            child = node[key]
            if isinstance(child, DictConfig):
                check_known_keys(child, f"{prefix}{key}.")


def composition_error(e: Exception) -> ConfigError:
    """One line for what Hydra refuses while composing (an unknown option or key, a value of the wrong type),
    in the words ``validate`` uses: the key, and what is valid."""
    from hydra.errors import MissingConfigException

    if isinstance(e, MissingConfigException) and e.missing_cfg_file and e.options:
        group, _, option = e.missing_cfg_file.rpartition("/")
        return ConfigError(f"{group}={option}: no such option; valid: {', '.join(e.options)}")
    cause = e.__cause__
    key, schema = getattr(cause, "full_key", None), getattr(cause, "object_type", None)
    if key and is_dataclass(schema) and key.rpartition(".")[2] not in {f.name for f in fields(schema)}:
        return unknown_key_error(key, schema)  # not Hydra's advice to add it with '+': it would be refused then
    if key and "not in struct" in str(cause):  # a key of stage.run: its valid ones are the stage's arguments
        return ConfigError(f"{key}: unknown key; `python -m topocut.run {key.split('.')[0]}=... --cfg job` "
                           "prints the valid ones")
    first = str(e).splitlines()[0]
    return ConfigError(f"{first}: {str(cause).splitlines()[0]}" if cause is not None else first)


def check_device(cfg: DictConfig, device: str) -> None:
    """A training stage's Lightning accelerator must exist on the device this run resolved to."""
    trains = isinstance(cfg.stage.run, DictConfig) and "trainer" in cfg.stage.run
    _check(not trains or device == "cuda" or cfg.trainer.accelerator not in ("gpu", "cuda"), "trainer.accelerator",
           f"{cfg.trainer.accelerator} needs a CUDA device, but this run's device is {device} (device={cfg.device}); "
           "use trainer=cpu, or device=cuda on a machine with a GPU")


def validate(cfg: DictConfig) -> None:
    """Cross-field checks; raises ConfigError naming the full key path."""
    check_known_keys(cfg)
    _check(cfg.stage.name in STAGES, "stage.name", f"{cfg.stage.name!r} is not a stage; valid: {', '.join(STAGES)}")
    _check(cfg.object.name in OBJECTS, "object.name",
           f"unknown object {cfg.object.name!r}; valid: {', '.join(OBJECTS)}")
    _check(cfg.device in ("auto", "cpu", "cuda"), "device", f"{cfg.device!r}; valid: auto, cpu, cuda")
    for group in ("object", "eval"):  # pose randomisation ranges (topocut.sim.objects.random_pose)
        node = cfg[group]
        _check(0 < node.scale_min <= node.scale_max, f"{group}.scale_min",
               f"{node.scale_min} is not valid; need 0 < {group}.scale_min <= {group}.scale_max={node.scale_max}")
        _check(0 <= node.translation < 0.5, f"{group}.translation",
               f"{node.translation} is not valid; must lie in [0, 0.5) (scene units; the board is the unit square)")
        _check(0 <= node.yaw_deg <= 180, f"{group}.yaw_deg", f"{node.yaw_deg} is not valid; must lie in [0, 180]")
    from topocut.data.store import InvalidName, check_name

    for key, kind in (("data.dataset", "dataset"), ("data.encoder", "checkpoint"), ("eval.name", "eval")):
        try:  # a name is one directory under <outputs_root>/<kind>: `../x` or `/tmp/x` would write elsewhere
            check_name(kind, OmegaConf.select(cfg, key), key)
        except InvalidName as e:
            raise ConfigError(str(e)) from e
    _check(0.0 <= cfg.trainer.val_fraction < 1.0, "trainer.val_fraction", "must lie in [0, 1)")
    from topocut.tasks import CUTTING_TASKS

    for key, names, valid, what in (("trainer.held_out_objects", cfg.trainer.held_out_objects, OBJECTS, "object"),
                                    ("data.objects", cfg.data.objects, OBJECTS, "object"),
                                    ("data.tasks", cfg.data.tasks, CUTTING_TASKS, "knife task")):
        bad = [o for o in names if o not in valid]
        _check(not bad, key, f"unknown {what} {bad[0]!r}; valid: {', '.join(valid)}" if bad else "")
    _check_task_overrides("data.task_overrides", cfg.data.task_overrides)
    for key, value, lo in (("data.episodes", cfg.data.episodes, 1), ("data.points_per_step", cfg.data.points_per_step, 1),
                           ("data.jobs", cfg.data.jobs, 1), ("trainer.jobs", cfg.trainer.jobs, 1),
                           ("trainer.batch_size", cfg.trainer.batch_size, 1),
                           ("trainer.num_workers", cfg.trainer.num_workers, 0)):
        _check(value >= lo, key, f"{value} is not valid; must be >= {lo}")
    _check(cfg.trainer.max_epochs >= 1 or (cfg.trainer.max_epochs == -1 and cfg.trainer.max_steps > 0),
           "trainer.max_epochs", f"{cfg.trainer.max_epochs} is not valid; must be >= 1 (or -1 with trainer.max_steps > 0)")
    from topocut.policies.config import LOSSES, MASK_LABELS, SAMPLES

    for key, choices in (("sample", SAMPLES), ("mask_label", MASK_LABELS), ("loss", LOSSES)):  # stage=bc's, up front
        value = cfg.policy.train[key]
        _check(value in choices, f"policy.train.{key}", f"{value!r} is not valid; valid: {', '.join(choices)}")
    _check(cfg.trainer.profiler in PROFILERS, "trainer.profiler",
           f"{cfg.trainer.profiler!r} is not a profiler; valid: {', '.join(PROFILERS)}")
    _check(cfg.trainer.max_steps == -1 or cfg.trainer.max_steps >= 1, "trainer.max_steps",
           f"{cfg.trainer.max_steps} is not valid; -1 (no limit) or >= 1")
    # Taichi's random_seed is an int32 and episode seeds are mixed modulo 2**31 - 1 (mix_seed)
    _check(0 <= cfg.seed < 2 ** 31 - 1, "seed", f"{cfg.seed} is not valid; must lie in [0, 2**31 - 1)")
    if "max_cuts" in cfg.task:  # the knife tasks' (KnifeTaskConfig); cream writing and scooping cut nothing
        _check_task_cuts(cfg.task.name, cfg.task.max_cuts)
    sim = OmegaConf.to_object(cfg.sim)
    try:
        sim.validate()
    except ValueError as e:
        msg = str(e)
        raise ConfigError(msg if msg.startswith("sim.") else f"sim: {msg}") from e
    for group, node in (("planner", cfg.planner), ("observation", cfg.observation), ("policy.net", cfg.policy.net),
                        ("eval", cfg.eval), ("reward", cfg.reward), ("task", cfg.task), ("topology", cfg.topology),
                        ("model", cfg.model)):
        obj = OmegaConf.to_object(node)
        try:
            obj.validate()
        except ValueError as e:
            msg = str(e)
            raise ConfigError(msg if msg.startswith(group.split(".")[0]) else f"{group}: {msg}") from e
    _check_stage_args(cfg)
    _check_video_encoder(cfg)


def _check_video_encoder(cfg: DictConfig) -> None:
    """eval.videos > 0 in a run that evaluates (stage=eval, or stage=all with eval in its sequence) needs an MP4
    encoder: refused up front, naming the key, where the machine has none (the lent GPU machines have no ffmpeg)."""
    stage = cfg.stage.name
    evaluates = stage == "eval" or (stage == "all" and "eval" in list(cfg.stage.run.get("sequence", [])))
    if not evaluates or cfg.eval.videos <= 0:
        return
    from topocut.eval.videos import encoder_problem

    problem = encoder_problem()
    _check(problem is None, "eval.videos",
           f"{cfg.eval.videos} films MP4s, which needs matplotlib, imageio and imageio-ffmpeg's binary ({problem}); "
           "install them (pip install matplotlib imageio imageio-ffmpeg) or set eval.videos=0")


def _check_task_cuts(name: str, max_cuts: int) -> None:
    """task.max_cuts against the task's own minimum (``min_cuts``: dice 3, stick 2, ...), asked of the task."""
    from topocut.tasks import check_max_cuts, get_task

    try:
        check_max_cuts(max_cuts, get_task(name))
    except ValueError as e:
        msg = str(e)
        raise ConfigError(msg.replace(f"task.max_cuts={max_cuts} ", f"task.max_cuts: {max_cuts} ", 1)) from e


def task_for_stage(task, stage: str):
    """The task object (topocut.tasks.get_task) a stage runs; a stage the task has no pipeline for is a
    ConfigError (exit status 2) naming task and stage.name and the tasks that run it."""
    from topocut.tasks import task_for_stage as lookup

    try:
        return lookup(task, stage)
    except ValueError as e:
        raise ConfigError(str(e)) from e


def _check_stage_args(cfg: DictConfig) -> None:
    """The stage's arguments must bind to its function's signature (typos in stage.run.* fail here)."""
    from hydra.utils import get_method

    run = cfg.stage.run
    target = run.get("_target_")
    try:
        fn = get_method(target)
    except Exception as e:  # noqa: BLE001 - hydra raises several types here
        raise ConfigError(f"stage.run._target_: cannot import {target!r} ({e})") from e
    params = inspect.signature(fn).parameters
    for key in run:
        if key.startswith("_"):
            continue
        _check(key in params, f"stage.run.{key}",
               f"not an argument of {target}; valid: {', '.join(p for p in params if p != 'ctx')}")


def to_dataclass(node: Any) -> Any:
    """A DictConfig node of a structured config -> its dataclass instance (others pass through)."""
    if isinstance(node, DictConfig):
        return OmegaConf.to_object(node)
    return node


def asdict_shallow(obj: Any) -> dict:
    return {f.name: getattr(obj, f.name) for f in fields(obj)} if is_dataclass(obj) else dict(obj)

"""Typed config schemas (Hydra ConfigStore) and cross-field checks.

Every group in ``conf/`` merges onto a dataclass defined next to the code that
uses it, so a misspelt key or a wrong type fails at composition time, before
anything is simulated.  ``validate`` adds the checks no single dataclass can
make alone, naming the full key path in its message.
"""
from __future__ import annotations

import inspect
from dataclasses import dataclass, field, fields, is_dataclass
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, OmegaConf

from topocut.eval.config import EvalConfig
from topocut.goals.config import TaskConfig
from topocut.models.config import DynamicsConfig
from topocut.planning.config import MPPIConfig
from topocut.policies.config import PDDPConfig, PolicyTrainConfig, SamplerConfig
from topocut.reward.config import RewardConfig
from topocut.sim.config import SimConfig
from topocut.sim.objects import OBJECTS
from topocut.topology.config import TopologyConfig
from topocut.topology.observation import ObservationConfig
from topocut.utils.logger import LoggerConfig

STAGES = ("simulate", "mppi", "teleop", "merge", "pretrain", "bc", "eval", "all")


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
    held_out_objects: list[str] = field(default_factory=lambda: ["donut", "burger", "sushi", "steak"])


@dataclass
class DataConfig:
    dataset: str = "demos"  # name written by mppi/merge and read by pretrain/bc/eval
    version: str = "latest"
    episodes: int = 2  # episodes per mppi run (job)
    points_per_step: int = 2048
    encoder: str = "perception"  # checkpoint name of the pretrained encoder Φ
    encoder_version: str = "latest"


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
    scale_name: str = "smoke"
    seed: int = 0
    device: str = "auto"
    outputs_root: str = "outputs"
    progress: bool = True


def register_configs() -> None:
    ConfigStore.instance().store(name="base_config", node=TopoCutConfig)


def _check(cond: bool, key: str, msg: str) -> None:
    if not cond:
        raise ConfigError(f"{key}: {msg}")


def validate(cfg: DictConfig) -> None:
    """Cross-field checks; raises ConfigError naming the full key path."""
    _check(cfg.stage.name in STAGES, "stage.name", f"{cfg.stage.name!r} is not a stage; valid: {', '.join(STAGES)}")
    _check(cfg.object.name in OBJECTS, "object.name",
           f"unknown object {cfg.object.name!r}; valid: {', '.join(OBJECTS)}")
    _check(cfg.device in ("auto", "cpu", "cuda"), "device", f"{cfg.device!r}; valid: auto, cpu, cuda")
    _check(cfg.object.scale_min <= cfg.object.scale_max, "object.scale_min",
           f"{cfg.object.scale_min} exceeds object.scale_max={cfg.object.scale_max}")
    _check(0.0 <= cfg.trainer.val_fraction < 1.0, "trainer.val_fraction", "must lie in [0, 1)")
    bad = [o for o in cfg.trainer.held_out_objects if o not in OBJECTS]
    _check(not bad, "trainer.held_out_objects", f"unknown object {bad[0]!r}; valid: {', '.join(OBJECTS)}" if bad else "")
    for key, value, lo in (("data.episodes", cfg.data.episodes, 1), ("data.points_per_step", cfg.data.points_per_step, 1),
                           ("trainer.batch_size", cfg.trainer.batch_size, 1),
                           ("trainer.num_workers", cfg.trainer.num_workers, 0)):
        _check(value >= lo, key, f"{value} is not valid; must be >= {lo}")
    _check(cfg.trainer.max_epochs >= 1 or (cfg.trainer.max_epochs == -1 and cfg.trainer.max_steps > 0),
           "trainer.max_epochs", f"{cfg.trainer.max_epochs} is not valid; must be >= 1 (or -1 with trainer.max_steps > 0)")
    _check(cfg.trainer.max_steps == -1 or cfg.trainer.max_steps >= 1, "trainer.max_steps",
           f"{cfg.trainer.max_steps} is not valid; -1 (no limit) or >= 1")
    # Taichi's random_seed is an int32 and episode seeds are mixed modulo 2**31 - 1 (mix_seed)
    _check(0 <= cfg.seed < 2 ** 31 - 1, "seed", f"{cfg.seed} is not valid; must lie in [0, 2**31 - 1)")
    _check(cfg.task.name not in ("stick", "dice") or cfg.task.max_cuts >= 2, "task.max_cuts",
           f"task={cfg.task.name} needs at least 2 cuts (the slab, then its width); got {cfg.task.max_cuts}")
    sim = OmegaConf.to_object(cfg.sim)
    try:
        sim.validate()
    except ValueError as e:
        msg = str(e)
        raise ConfigError(msg if msg.startswith("sim.") else f"sim: {msg}") from e
    for group, node in (("planner", cfg.planner), ("observation", cfg.observation), ("policy.net", cfg.policy.net),
                        ("eval", cfg.eval), ("reward", cfg.reward), ("task", cfg.task), ("topology", cfg.topology)):
        obj = OmegaConf.to_object(node)
        try:
            obj.validate()
        except ValueError as e:
            msg = str(e)
            raise ConfigError(msg if msg.startswith(group.split(".")[0]) else f"{group}: {msg}") from e
    _check_stage_args(cfg)


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

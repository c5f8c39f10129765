"""Evaluation protocol configuration (Hydra group ``eval``; docs/evaluation.md).

Defaults are the paper's protocol (§4, Table 1): 9 objects (5 seen, 4 unseen)
x 3 goal types x 15 episodes = 405 episodes per policy, five sequential cuts
each, object pose randomised from the episode's seed.  ``smoke()`` is the
one-object-per-split variant used by CI.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from topocut.eval import stats
from topocut.policies import registry
from topocut.utils.checks import check_choice
from topocut.utils.import_path import is_import_path

SPLITS = ("in", "out")  # in-distribution (seen objects) / out-of-distribution (unseen objects)
TASKS = ("slice", "stick", "dice")


def table_tasks(present) -> list:
    """The tasks a table shows, in column order: the protocol's TASKS, then any other task in ``present`` (a
    task of your own, eval.tasks=[module.path:ClassName]) in the order first seen."""
    extra = [t for t in dict.fromkeys(present) if t not in TASKS]
    return [*TASKS, *extra]
OBSERVATIONS = ("particles", "depth")
NORMALIZE_BY = ("task", "task_split")
POLICY_NAMES = registry.names()  # topocut/policies/registry.py: the one list
LEARNED = registry.learned()  # loaded from bc checkpoints


@dataclass
class EvalConfig:
    name: str = "table1"  # artifact name eval/<name>
    seen: list[str] = field(default_factory=lambda: ["cake", "cube", "ditto", "ham", "potato"])
    unseen: list[str] = field(default_factory=lambda: ["donut", "burger", "sushi", "steak"])
    tasks: list[str] = field(default_factory=lambda: list(TASKS))
    episodes_per_cell: int = 15  # episodes per (task, object)
    max_cuts: int = 5  # sequential cuts per episode
    seed: int = 0  # base seed; each episode's seed (and so its pose) is derived from it
    # pose randomisation (topocut.sim.objects.random_pose)
    randomize_pose: bool = True
    translation: float = 0.03  # ± scene units
    yaw_deg: float = 15.0  # ± degrees
    scale_min: float = 0.8
    scale_max: float = 1.2
    # what is evaluated and against what
    policies: list[str] = field(default_factory=lambda: ["oracle", "dp3", "3dda", "pddp_noperc", "pddp"])
    reference: str = "oracle"  # policy whose final reward normalises R (oracle = goal.planes executed exactly;
    #                            "teleop" = replayed human logs written as episodes/teleop/*.json)
    normalize_by: str = "task"  # "task": one reference mean per task (both splits); "task_split": per split
    compare_to: str = ""  # policy the report's paired differences (Δ columns) compare with; "" = eval.reference
    # training seeds pooled per learned policy: 1 = the pinned/latest checkpoint, whatever seed trained it; k > 1 =
    # the checkpoints trained with seeds seed, seed+1, ..., seed+k-1 (`-m stage=bc seed=0,1,2`) beside that one
    # (same training config and inputs), each evaluated on every episode and pooled into one row per cell
    train_seeds: int = 1
    # report statistics (topocut.eval.stats): percentile-bootstrap intervals over episode specs, by default with the
    # settings the report's functions take when called without them
    confidence: float = stats.CONFIDENCE
    bootstrap_resamples: int = stats.RESAMPLES
    bootstrap_seed: int = stats.SEED
    # Taichi CPU threads when the eval stage starts Taichi: 1 = reproducible CPU runs (docs/evaluation.md), 0 = all cores
    cpu_threads: int = 0
    # processes evaluating at once (joblib's loky workers, each its own simulator and policies; tasks of one
    # batch of sim.batch_size specs, the one a single process runs, or one spec for MPPI, handed out as workers
    # free up).  Not part of the artifact's key: the episodes are the same however many processes run them
    jobs: int = 1
    observation: str = "particles"  # particles (FPS of particles) | depth (topocut.topology.observation)
    num_points: int = 2048  # observation points handed to the policy (matches data.points_per_step)
    min_fragment_points: int = 4  # smaller labelled clusters are debris, not pieces
    stop_on_success: bool = False  # the paper runs all five cuts; True stops once the task's threshold is met
    gifs: int = 0  # episodes per task of one policy run rendered to GIF, and the figure (topocut.eval.sequences)
    # rollout videos (topocut.eval.videos): the first `videos` episodes of every policy run as MP4, each cut shown
    # in motion by `video_frames_per_cut` frames; 0 films none.  Not part of the artifact's key (no episode changes)
    videos: int = 0
    video_frames_per_cut: int = 8
    # checkpoint version per learned policy (`+eval.checkpoints.pddp=v003`); a policy not named here loads its latest
    # version (stage=all pins what its bc stage wrote)
    checkpoints: dict[str, str] = field(default_factory=dict)
    # task parameters over conf/task/<task>.yaml, per task (`eval.task_overrides={slice:{thickness:0.05}}`): the
    # smoke scale's 48³ grid cannot resolve 3 cm slabs (docs/evaluation.md), so it evaluates 5 cm ones
    task_overrides: dict[str, dict[str, Any]] = field(default_factory=dict)
    # constructor arguments of your own policy classes (`module.path:ClassName` entries of eval.policies), keyed by
    # class name: `+eval.policy_kwargs.MyPolicy={ckpt:/path,steps:10}` (docs/evaluation.md)
    policy_kwargs: dict[str, dict[str, Any]] = field(default_factory=dict)

    def validate(self) -> EvalConfig:
        check_choice("eval.observation", self.observation, OBSERVATIONS)
        check_choice("eval.normalize_by", self.normalize_by, NORMALIZE_BY)
        bad = [t for t in self.tasks if t not in TASKS and not is_import_path(t)]
        if bad:
            raise ValueError(f"eval.tasks: unknown task {bad[0]!r}; valid: {', '.join(TASKS)}, or a knife task of "
                             "your own as module.path:ClassName (docs/architecture.md)")
        if self.episodes_per_cell < 1 or self.max_cuts < 1:
            raise ValueError(f"eval.episodes_per_cell={self.episodes_per_cell} and eval.max_cuts={self.max_cuts} "
                             "must be >= 1")
        for key, value, what in (("eval.gifs", self.gifs, "episodes per task rendered to GIF"),
                                 ("eval.videos", self.videos, "episodes per policy filmed to MP4")):
            if value < 0:
                raise ValueError(f"{key}={value} is not valid; must be >= 0 ({what}; 0: none)")
        if self.video_frames_per_cut < 1:
            raise ValueError(f"eval.video_frames_per_cut={self.video_frames_per_cut} is not valid; must be >= 1 "
                             "(frames during each cut of a video; eval.videos=0 turns the videos off)")
        if self.jobs < 1:
            raise ValueError(f"eval.jobs={self.jobs} must be >= 1 (processes evaluating at once)")
        if self.train_seeds < 1 or self.bootstrap_resamples < 1 or self.cpu_threads < 0:
            raise ValueError(f"eval.train_seeds={self.train_seeds} and eval.bootstrap_resamples="
                             f"{self.bootstrap_resamples} must be >= 1, eval.cpu_threads={self.cpu_threads} >= 0")
        if not 0.0 < self.confidence < 1.0:
            raise ValueError(f"eval.confidence={self.confidence} must lie in (0, 1), e.g. 0.95")
        if self.scale_min > self.scale_max:
            raise ValueError(f"eval.scale_min={self.scale_min} exceeds eval.scale_max={self.scale_max}")
        if "teleop" in self.policies:
            raise ValueError("eval.policies: 'teleop' is not a policy the eval stage can run (a human drives it); "
                             "replay the logs into episodes/teleop/*.json and set eval.reference=teleop")
        # registered names, or 'module.path:ClassName' of your own policy class (imported and checked here)
        registry.check(self.policies, "eval.policies", POLICY_NAMES, external=True, kwargs=self.policy_kwargs)
        bad = [p for p in self.checkpoints if p not in self.policies or p not in LEARNED]
        if bad:
            raise ValueError(f"eval.checkpoints.{bad[0]}: only learned policies in eval.policies load checkpoints "
                             f"({', '.join(p for p in self.policies if p in LEARNED) or 'none here'})")
        if self.reference not in self.policies and self.reference != "teleop":
            raise ValueError(f"eval.reference={self.reference!r} must be one of eval.policies "
                             f"({', '.join(self.policies)}) or 'teleop' (replayed human logs); a piece of a larger "
                             f"table runs with eval.reference={self.policies[0]} and joins the reference's piece "
                             "through experiments/table1.py --reference")
        if self.compare_to and self.compare_to not in self.policies and self.compare_to != self.reference:
            raise ValueError(f"eval.compare_to={self.compare_to!r} must be one of eval.policies "
                             f"({', '.join(self.policies)}), eval.reference, or empty (= eval.reference)")
        from topocut.sim.objects import OBJECTS  # pure numpy: no Taichi import here

        for key, names in (("eval.seen", self.seen), ("eval.unseen", self.unseen)):
            bad = [o for o in names if o not in OBJECTS]
            if bad:
                raise ValueError(f"{key}: unknown object {bad[0]!r}; valid: {', '.join(OBJECTS)}")
        from topocut.tasks import task_config_class, task_keys

        for task, over in self.task_overrides.items():
            if task not in TASKS and task not in self.tasks:
                raise ValueError(f"eval.task_overrides.{task}: unknown task; valid: {', '.join(TASKS)} and the "
                                 "entries of eval.tasks")
            # the task's own keys (its dataclass: dice has size, no thickness), but what the evaluation sets itself
            params = [k for k in task_keys(task) if k not in ("name", "max_cuts", "stage")]
            bad = [k for k in over if k not in params]
            if bad:
                why = " (eval.max_cuts sets it)" if bad[0] == "max_cuts" else ""
                raise ValueError(f"eval.task_overrides.{task}.{bad[0]}: not a parameter of task={task}{why}; valid "
                                 f"keys of {task_config_class(task).__name__}: {', '.join(params)}")
        overlap = set(self.seen) & set(self.unseen)
        if overlap:
            raise ValueError(f"eval.seen and eval.unseen share objects {sorted(overlap)}")
        if not self.seen and not self.unseen:
            raise ValueError("eval.seen and eval.unseen are both empty: nothing to evaluate")
        return self

    @property
    def comparison(self) -> str:
        """The policy the paired differences compare with."""
        return self.compare_to or self.reference

    @property
    def num_episodes(self) -> int:
        return (len(self.seen) + len(self.unseen)) * len(self.tasks) * self.episodes_per_cell


def smoke(**overrides) -> EvalConfig:
    """One object per split x 3 tasks x 1 episode (6 episodes per policy)."""
    base = dict(seen=["cube"], unseen=["donut"], episodes_per_cell=1)
    base.update(overrides)
    return EvalConfig(**base)

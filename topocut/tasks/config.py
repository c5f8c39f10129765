"""Task configuration (paper §4 task setup and the appendix's additional tasks; docs/reward.md#goals, docs/tasks.md).

The cutting tasks (slice, stick, dice, pyramid) use the knife; cream_writing uses a cream pen
(``PenConfig``) and scooping a spoon and a cup (``SpoonConfig``).  What a task needs is the task's to say
(``topocut.tasks.get_task(name)``): its stages (``check_stage`` refuses the others: cream writing has simulate
and mppi, scooping simulate), its fewest cuts (``min_cuts``) and its tool's fields (pen, spoon).
"""
from __future__ import annotations

from dataclasses import dataclass, field

from topocut.sim.tools import PenConfig, SpoonConfig  # noqa: F401 - re-exported: the tools' settings live with the simulator

CUTTING_TASKS = ("slice", "stick", "dice", "pyramid")
TASKS = CUTTING_TASKS + ("cream_writing", "scooping")  # the registry's names (topocut.tasks.get_task)


@dataclass
class TaskConfig:
    name: str = "slice"  # slice | stick | dice | pyramid | cream_writing | scooping
    thickness: float = 0.03  # slice thickness (scene units), along the object's longest horizontal axis
    width: float = 0.03  # stick width, along the other horizontal axis
    size: float = 0.03  # dice side; pyramid: leg length of the corner tetrahedron
    max_cuts: int = 5  # cuts per episode; also bounds the number of goal pieces
    # the least total spectral reward (in [0, r_max]) a success needs: knife tasks also need every goal piece made
    # (N_C = G; KnifeTask.success, docs/tasks.md#success); cream writing and scooping the total alone (their yaml: 0.95)
    success_threshold: float = 0.5
    push: bool = False  # after each cut the blade slides the cut-off side aside (stick and dice in the paper)
    num_goal_points: int = 2048  # Goal.points/labels are FPS-downsampled to this many points (0: keep all)
    sample_tilt: bool = False  # MPPI also samples the knife tilt (pyramid: the goal plane is tilted)
    # -- cream writing -----------------------------------------------------------
    word: str = "CORL"  # letters written, one stroke (cluster) each; topocut.tasks.letters.LETTERS
    letter_height: float = 0.12  # cap height of a letter [units]; width is LETTER_ASPECT times it
    letter_gap: float = 0.06  # space between letters [units] (>= ~5 spacings, or discovery joins them)
    pen: PenConfig = field(default_factory=PenConfig)
    # -- scooping ----------------------------------------------------------------
    spoon: SpoonConfig = field(default_factory=SpoonConfig)
    # the stage running this task: conf/task/{cream_writing,scooping}.yaml fill it from ${stage.name} so that
    # validate() refuses a stage without a pipeline for the task ("" = not checked)
    stage: str = ""

    def validate(self) -> TaskConfig:
        from topocut.tasks import get_task

        task = get_task(self.name)  # unknown names fail here with the list of tasks
        for k in ("thickness", "width", "size", "letter_height"):
            if getattr(self, k) <= 0:
                raise ValueError(f"task.{k}={getattr(self, k)} must be > 0")
        if self.max_cuts < 1:  # the task's own minimum (min_cuts): topocut.config.validate and make_goal
            raise ValueError(f"task.max_cuts={self.max_cuts} must be >= 1")
        if self.num_goal_points < 0:
            raise ValueError(f"task.num_goal_points={self.num_goal_points} must be >= 0")
        if self.stage:
            check_stage(self.stage, self.name)
        tool_fields = {"pen": self._validate_writing, "spoon": self._validate_scooping}.get(task.tool)
        if tool_fields is not None:
            tool_fields()
        return self

    def _validate_writing(self) -> None:
        from topocut.tasks.letters import LETTERS

        bad = [c for c in self.word.upper() if c not in LETTERS]
        if not self.word or bad:
            raise ValueError(f"task.word={self.word!r}: no stroke for {bad or 'an empty word'}; "
                             f"valid letters: {''.join(sorted(LETTERS))}")
        if self.letter_gap < 0:
            raise ValueError(f"task.letter_gap={self.letter_gap} must be >= 0")
        p = self.pen
        for k in ("height", "nozzle_radius", "extrude_speed", "speed", "travel_speed", "step", "yield_stress", "mu",
                  "lam"):
            if getattr(p, k) <= 0:
                raise ValueError(f"task.pen.{k}={getattr(p, k)} must be > 0")
        if p.max_particles < 100:
            raise ValueError(f"task.pen.max_particles={p.max_particles} must be >= 100")

    def _validate_scooping(self) -> None:
        s = self.spoon
        for k in ("radius", "thickness", "depth", "advance", "speed", "cup_radius", "cup_height", "cup_wall",
                  "yield_stress"):
            if getattr(s, k) <= 0:
                raise ValueError(f"task.spoon.{k}={getattr(s, k)} must be > 0")
        if not -1.0 < s.opening < 1.0:
            raise ValueError(f"task.spoon.opening={s.opening} must lie in (-1, 1)")
        if s.depth >= 2 * s.radius:
            raise ValueError(f"task.spoon.depth={s.depth} must be < the bowl's diameter 2*radius={2 * s.radius}")
        if len(s.block) != 3 or min(s.block) <= 0:
            raise ValueError(f"task.spoon.block must be 3 positive sizes (x, y, z), got {list(s.block)}")
        for k in ("block_center", "cup_center"):
            if len(getattr(s, k)) != 2:
                raise ValueError(f"task.spoon.{k} must be (x, y), got {list(getattr(s, k))}")
        if not s.scoops or any(len(a) != 2 for a in s.scoops):
            raise ValueError(f"task.spoon.scoops must be a non-empty list of (x, y) offsets, got {s.scoops}")
        gap = abs(s.cup_center[0] - s.block_center[0]) - s.block[0] / 2 - s.cup_radius - s.cup_wall
        if gap < 0:
            raise ValueError(f"task.spoon.cup_center={list(s.cup_center)} puts the cup inside the block "
                             f"(x gap {gap:.3f} < 0)")


def check_max_cuts(max_cuts: int, task) -> None:
    """Refuse a cut budget below the task's ``min_cuts`` (dice with 2 cuts cannot free a die)."""
    if max_cuts < task.min_cuts:
        raise ValueError(f"task.max_cuts={max_cuts} is too few for task={task.name}: it needs at least "
                         f"{task.min_cuts} ({task.min_cuts_why}); set task.max_cuts>={task.min_cuts}")


def check_stage(stage: str, task: str) -> None:
    """Refuse stage x task combinations without a pipeline (e.g. stage=bc task=scooping): the task's ``stages``."""
    from topocut.tasks import get_task

    allowed = get_task(task).stages
    if stage not in allowed:
        others = [n for n in TASKS if stage in get_task(n).stages]
        raise ValueError(f"task={task} runs with stage in ({', '.join(allowed)}) only, got stage={stage} "
                         f"(stage.name); tasks for stage={stage}: {', '.join(others) or 'none'}")

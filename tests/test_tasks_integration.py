"""Stages, MPPI and evaluation ask the task (issue #29): no branch on a task's name, the task's cut minimum in
config validation, dice at smoke scale, and the oracle's Turn steps executed between cuts wherever the ideal
sequence runs (the episode runner, MPPI's rollouts, the evaluation), on fakes that record what ran."""
from __future__ import annotations

import ast
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from topocut.config import ConfigError, register_configs, validate
from topocut.sim.action import KnifeAction
from topocut.tasks import TASKS, Cut, Turn, get_task, truncate_steps, turns_after

REPO = Path(__file__).resolve().parents[1]
CONF = str(REPO / "conf")
register_configs()


def _compose(*overrides):
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


# -- no branch on a task's name ---------------------------------------------------------------------------
def _name_branches(path: Path) -> list[str]:
    """Comparisons (==, !=, in, not in) against a task-name string literal, or a tuple/list/set of them."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if not isinstance(node, ast.Compare):
            continue
        for side in [node.left, *node.comparators]:
            elts = side.elts if isinstance(side, (ast.Tuple, ast.List, ast.Set)) else [side]
            if any(isinstance(e, ast.Constant) and e.value in TASKS for e in elts):
                out.append(f"{path.relative_to(REPO)}:{node.lineno}: {ast.unparse(node)}")
    return out


def test_stages_planning_and_evaluation_never_branch_on_a_task_name():
    files = [p for d in ("pipelines", "topocut/eval", "topocut/planning") for p in sorted((REPO / d).rglob("*.py"))]
    assert len(files) > 10
    hits = [h for p in files for h in _name_branches(p)]
    assert not hits, "ask topocut.tasks.get_task(name) instead:\n" + "\n".join(hits)
    # the scan finds what it looks for
    probe = REPO / "tests" / "_probe_branch.py"
    try:
        probe.write_text('if task.name == "cream_writing" or name in ("stick", "dice"):\n    pass\n')
        assert len(_name_branches(probe)) == 2
    finally:
        probe.unlink()


# -- cut minimum, dice at smoke scale -----------------------------------------------------------------------
def test_config_refuses_dice_with_two_cuts_naming_task_max_cuts():
    assert [get_task(n).min_cuts for n in ("slice", "stick", "dice", "pyramid")] == [1, 2, 3, 1]
    with pytest.raises(ConfigError, match=r"^task\.max_cuts: 2 is too few for task=dice: it needs at least 3 "
                                          r"\(a slab cut, a stick cut and a chop.*\); set task\.max_cuts>=3"):
        validate(_compose("task=dice", "task.max_cuts=2"))
    with pytest.raises(ConfigError, match=r"task\.max_cuts: 1 .*task=stick.*at least 2"):
        validate(_compose("task=stick", "task.max_cuts=1"))
    validate(_compose("task=slice", "task.max_cuts=1"))


def test_pyramid_at_smoke_scale_keeps_its_own_corner():
    """The smoke scale's 5 cm pieces are the slice / stick / dice sizes (conf/scale_task/smoke_<task>.yaml), not
    the pyramid's leg: at smoke scale the pyramid keeps its own 10 cm corner and one cut (PyramidConfig's defaults;
    no smoke_pyramid.yaml), which the 48^3 grid resolves (~150 particles; a 5 cm leg leaves a tenth of the volume,
    (0.05 / 0.1)^3 = 1/8)."""
    from omegaconf import OmegaConf

    from topocut.sim.config import SimConfig
    from topocut.tasks import make_goal

    cfg = _compose("stage=mppi", "task=pyramid", "object=cube", "scale=smoke")
    validate(cfg)
    assert (cfg.task.size, cfg.task.max_cuts) == (0.1, 1)
    assert _compose("stage=mppi", "task=pyramid", "scale=smoke", "task.size=0.08").task.size == 0.08  # still wins
    task = OmegaConf.to_object(cfg.task)  # a PyramidConfig (the task group's schema)
    goal = make_goal(task, "cube", spacing=SimConfig(n_grid=cfg.sim.n_grid).spacing, board_z=0.05)
    n = len(goal.fragments[0])  # the tetrahedron: leg^3 / 6 of volume, a particle per spacing^3
    assert 0.6 * (0.1 ** 3 / 6) / SimConfig(n_grid=48).spacing ** 3 < n < 1.4 * (0.1 ** 3 / 6) / SimConfig(n_grid=48).spacing ** 3


@pytest.mark.parametrize("stage", ["simulate", "mppi", "all"])
def test_dice_smoke_config_composes_and_validates(stage):
    cfg = _compose(f"stage={stage}", "task=dice", "scale=smoke", "logger=csv")
    validate(cfg)
    assert cfg.task.max_cuts == 3 and cfg.task.size == 0.05  # conf/scale_task/smoke_dice.yaml
    # slice and stick take 2 cuts at smoke scale (a cheap pipeline: smoke_<task>.yaml), the paper scale the tasks' 5
    assert _compose(f"stage={stage}", "task=slice").task.max_cuts == 2
    assert _compose(f"stage={stage}", "task=dice", "scale=paper").task.max_cuts == 5
    # make run's path: the whole pipeline at smoke scale on the slice task
    run = _compose("scale=smoke", "task=slice", "stage=all", "logger=csv")
    validate(run)
    assert list(run.stage.run.sequence) == ["simulate", "mppi", "pretrain", "bc", "eval"]


def test_a_stage_the_task_lacks_is_refused_before_anything_runs():
    import pipelines.mppi

    with pytest.raises(ConfigError, match=r"task=scooping runs with stage in \(simulate\) only, got stage=mppi "
                                          r"\(stage\.name\); tasks for stage=mppi: slice, stick, dice, pyramid, "
                                          r"cream_writing"):
        pipelines.mppi.run(None, None, None, SimpleNamespace(name="scooping"), None, None, None, None)


# -- the oracle's steps --------------------------------------------------------------------------------------
def _act(x):
    return KnifeAction(x, 0.5, 0.0, 0.0)


TURN = Turn("slab", (0.0, 1.0, 0.0), float(np.pi / 2), (0.7, 0.5, 0.1), (0.85, 0.5, 0.07))
STEPS = [Cut(_act(0.7)), TURN, Cut(_act(0.6)), Cut(_act(0.5))]


def _goal(steps=STEPS):
    return SimpleNamespace(steps=steps, planes=[s.action for s in steps if s.kind == "cut"], task="dice",
                           fragments=[np.zeros((4, 3))], points=np.zeros((4, 3), np.float32),
                           labels=np.zeros(4, np.int32))


def test_turns_after_and_truncated_steps():
    g = _goal()
    assert turns_after(g, 0) == [] and turns_after(g, 1) == [TURN] and turns_after(g, 2) == []
    assert turns_after(SimpleNamespace(planes=[]), 1) == []  # a goal without steps has no turn
    assert truncate_steps(STEPS, 1) == STEPS[:1]  # no turn after the last cut
    assert truncate_steps(STEPS, 2) == STEPS[:3] and truncate_steps(STEPS, 9) == STEPS
    dice = get_task("dice").make_goal(_task_cfg("dice", max_cuts=3, size=0.032), "cube", spacing=0.008)
    assert [s.kind for s in dice.steps] == ["cut", "turn", "cut", "cut"] and dice.turns_after(1) == dice.turns


def _task_cfg(name, **kw):
    from topocut.tasks import task_config

    return task_config(name, **kw)


class FakeEnv:
    """Records cut / push / turn; a turn clears the sweeps (as CuttingEnv.turn) and moves every particle."""

    def __init__(self, batch_size=1, n=6):
        self.batch_size, self.n, self.calls = batch_size, n, []
        self.x = np.zeros((batch_size, n, 3), np.float32)
        self.sweeps = [[] for _ in range(batch_size)]

    def cut(self, action):
        self.calls.append("cut")
        self.sweeps = [["sweep"] for _ in range(self.batch_size)]

    def push(self):
        self.calls.append("push")

    def turn(self, turn, select=None):
        self.calls.append("turn")
        self.x = self.x + 1.0
        self.sweeps = [[] for _ in range(self.batch_size)]
        return np.ones((self.batch_size, self.n), bool)

    def state(self):
        return SimpleNamespace(x=self.x.copy(), damage=np.zeros((self.batch_size, self.n), bool),
                               sweeps=[list(s) for s in self.sweeps])

    def get_state(self, b=0):
        return {"x": self.x[b].copy()}

    def set_state(self, state, b=None):
        self.x[:] = state["x"]


class FakeScorer:
    """Labels: previous + 1 (so a relabel is visible); records (sweeps, previous) of every discovery."""

    def __init__(self):
        self.seen = []

    def labels(self, x, damage, sweeps, previous=None):
        self.seen.append((sweeps, None if previous is None else int(previous[0])))
        return np.zeros(len(x), np.int32) if previous is None else np.asarray(previous) + 1

    def reward(self, x, labels):
        return 0.1, False

    def rewards(self, xs, labels):
        return np.full(len(xs), 0.1)


def test_episode_runner_turns_between_the_cuts_and_keeps_the_ids():
    from topocut.planning import GoalPlanesPolicy, run_episode

    env, scorer = FakeEnv(), FakeScorer()
    steps, summary = run_episode(env, _goal(), GoalPlanesPolicy(_goal()), max_cuts=3, push=True, scorer=scorer)
    assert env.calls == ["cut", "push", "turn", "cut", "push", "cut", "push"]
    assert summary["turns"] == [1] and summary["num_cuts"] == 3 and summary["status"] == "ok"
    # discovery: start; each cut with its sweep where the blade left the pieces, then after its push (no sweep, the
    # cut's labels as the previous ones); after the turn (no sweep, previous labels)
    assert scorer.seen == [(None, None), (["sweep"], 0), ([], 1), ([], 2), (["sweep"], 3), ([], 4), (["sweep"], 5),
                           ([], 6)]
    # the record after the turn starts from the turned state
    assert (steps[0]["x_t1"] == 0).all() and (steps[1]["x_t"] == 1).all()
    # a budget that ends at the turn's cut skips it
    env = FakeEnv()
    run_episode(env, _goal(), GoalPlanesPolicy(_goal()), max_cuts=1, scorer=FakeScorer())
    assert env.calls == ["cut"]


def test_mppi_rollouts_turn_between_their_cuts_where_the_episode_would():
    from topocut.planning.rollout import make_sim_rollout

    seqs = np.stack([[a.to_vector() for a in (_act(0.7), _act(0.6))]] * 2).astype(np.float32)  # K=2, H=2
    env = FakeEnv(batch_size=2)
    make_sim_rollout(env, env.get_state(0), _goal(), scorer=FakeScorer())(seqs)
    assert env.calls == ["cut", "turn", "cut"]  # the turn after the episode's first cut, inside the horizon
    env = FakeEnv(batch_size=2)
    make_sim_rollout(env, env.get_state(0), _goal(), scorer=FakeScorer(), cuts_done=1)(seqs)
    assert env.calls == ["cut", "cut"]  # planning cuts 2 and 3: no turn between them
    env = FakeEnv(batch_size=2)
    make_sim_rollout(env, env.get_state(0), _goal(), scorer=FakeScorer())(seqs[:, :1])
    assert env.calls == ["cut"]  # a turn at the horizon's end changes nothing the reward sees


def test_evaluation_runs_the_oracle_steps_and_asks_the_task_for_success():
    from topocut.eval import episode_specs, evaluate_episode, smoke
    from topocut.planning import GoalPlanesPolicy

    spec = episode_specs(smoke())[0]
    env, seen = FakeEnv(), []

    def discover(x, damage, sweeps, previous, cfg):
        seen.append((list(sweeps) if sweeps is not None else None, None if previous is None else int(previous[0])))
        return np.zeros(len(x), np.int32) if previous is None else np.asarray(previous) + 1

    def reward(frags, goal_frags, cfg):  # the one goal piece is made by the third cut
        n = env.calls.count("cut")
        return SimpleNamespace(total=0.2 * n, cut_count=1 if n >= 3 else 0, per_goal=np.zeros(1))

    env.reset = lambda *a, **k: None
    cfg = SimpleNamespace(name="dice", push=False, success_threshold=0.5)  # 0.2 a cut: 0.6 after the third
    res = evaluate_episode(spec, GoalPlanesPolicy(), env, cfg, max_cuts=3, spacing=0.01, goal_fn=lambda *a: _goal(),
                           discover_fn=discover, reward_fn=reward)
    assert env.calls == ["cut", "turn", "cut", "cut"] and res.turns == [1] and res.num_cuts == 3
    assert seen[2] == ([], 1)  # after the turn: no sweep, the previous labels
    # the task's success: N_C = G and the total at the threshold (0.4 with N_C = 0, then 0.6 with N_C = G)
    assert res.successes == [False, False, True] and res.asdict()["success"]


def test_a_simulated_dice_episode_lays_the_slab_flat_and_keeps_its_cluster():
    """The heuristic (the oracle's planes) on the cube at n_grid 48, two cuts: the slab cut, the goal's turn
    (CuttingEnv.turn), the first stick cut.  The slab lies flat beyond the cube, its cluster id kept."""
    from topocut.sim.env import CuttingEnv

    if not hasattr(CuttingEnv, "turn"):
        pytest.skip("CuttingEnv.turn not provided yet")
    from topocut.planning import GoalPlanesPolicy, Scorer, run_episode
    from topocut.sim import SimConfig
    from topocut.sim.objects import ObjectPose
    from topocut.topology import TopologyConfig

    sim = SimConfig(n_grid=48, cut_substeps=60, dwell_time=0.0005, settle_time=0.004)
    task = _task_cfg("dice", size=0.05, max_cuts=3)
    goal = get_task("dice").make_goal(task, "cube", ObjectPose(), spacing=sim.spacing, board_z=sim.board_z)
    env = CuttingEnv(sim, batch_size=1)
    env.reset("cube", ObjectPose(), seed=0)
    x0 = env.state().x[0].copy()
    scorer = Scorer(goal, topo_cfg=TopologyConfig(resolution=48))
    labels_seen = []
    real = scorer.labels
    scorer.labels = lambda *a: labels_seen.append(real(*a)) or labels_seen[-1]
    steps, summary = run_episode(env, goal, GoalPlanesPolicy(goal), max_cuts=2, scorer=scorer)
    assert summary["status"] == "ok", summary.get("error")
    assert summary["turns"] == [1] and summary["num_cuts"] == 2
    a1 = goal.axes[0]
    after_cut, after_turn = labels_seen[1], labels_seen[2]
    x_cut, x_turn = steps[0]["x_t1"], steps[1]["x_t"]
    slab = int(np.argmax([(x_cut[after_cut == c] @ a1).mean() for c in range(after_cut.max() + 1)]))
    moved = np.linalg.norm(x_turn - x_cut, axis=1) > 0.02
    np.testing.assert_array_equal(after_turn, after_cut)  # a rigid turn: every id kept
    assert (after_cut[moved] == slab).mean() > 0.95  # what moved is the slab
    s = x_turn[after_turn == slab]
    assert (s @ a1).min() > (x0 @ a1).max()  # laid beyond the cube
    assert np.ptp(s[:, 2]) < 0.5 * np.ptp(x_cut[after_cut == slab][:, 2])  # its thickness now vertical

"""The episode engine (topocut.episode.run_episodes) batches episodes of different objects, poses and tasks in
one simulator batch, and each episode's log equals the same episode run alone (batch_size 1).

Scenes are independent (tests/test_sim_mixed_batch.py) and this session's Taichi runs on one CPU thread, so the
states agree to float rounding; discovery and reward of equal states are then equal.  Rewards are compared
at 1e-6, actions, turns, piece counts and labels exactly.  The batch holds a stick episode (push, a turn after
its first cut) beside slices (no push, no turn), and 3 episodes at batch size 2 leave the second batch with a
frozen padding scene.
"""
import numpy as np
import pytest

from topocut.episode import Episode, make_scoring, run_episodes
from topocut.planning.heuristic import GoalPlanesPolicy
from topocut.reward.config import RewardConfig
from topocut.sim.config import SimConfig
from topocut.sim.objects import ObjectPose
from topocut.tasks import task_config
from topocut.topology.config import TopologyConfig

SIM = dict(n_grid=32, push_time=0.008, settle_time=0.0074)
EPISODES = [
    Episode("cube", ObjectPose(0.5, 0.5, 0.1, 1.0), 11, task_config("stick", max_cuts=3, push=True)),
    Episode("cake", ObjectPose(0.51, 0.49, -0.2, 0.9), 12, task_config("slice", max_cuts=3)),
    Episode("cube", ObjectPose(0.49, 0.5, 0.0, 1.1), 13, task_config("slice", max_cuts=3, thickness=0.05)),
]


class Stopping(GoalPlanesPolicy):
    """The goal's planes; stops (None) after ``limit`` cuts in episodes of seed 12, so its scene idles.  It is
    shown the observed points (``observation_fields``), which the fixture records."""

    observation_fields = ("points", "labels", "history", "goal", "goal_labels")

    def reset(self, goal, seed=None):
        super().reset(goal)
        self.limit = 1 if seed == 12 else None

    def act(self, obs):
        if self.limit is not None and self.t >= self.limit:
            return None
        return super().act(obs)


@pytest.fixture(scope="module")
def logs():
    from topocut.sim.env import CuttingEnv

    sc = make_scoring(RewardConfig(), TopologyConfig(resolution=48))
    out, seen = {}, {}
    for B in (2, 1):
        env = CuttingEnv(SimConfig(**SIM, batch_size=B))
        calls, seen[B] = [], {}

        def observe(x, labels, seed, seen=seen[B]):  # what a policy reading points sees (Stopping reads none)
            seen[seed] = (np.asarray(x)[::97].copy(), np.asarray(labels)[::97].copy())
            return seen[seed]

        if B > 1:
            orig = env.reset_scenes
            env.reset_scenes = lambda *a, orig=orig, calls=calls, **k: calls.append(a[0]) or orig(*a, **k)
            observe.batch = lambda xs, labels, seeds, calls=calls, f=observe: (
                calls.append(("batch", len(xs))) or [f(x, lab, s) for x, lab, s in zip(xs, labels, seeds)])
        out[B] = run_episodes(env, EPISODES, Stopping(), sc, max_cuts=3, observe_fn=observe), calls
    out["seen"] = seen
    return out


def test_batched_episodes_equal_episodes_run_alone(logs):
    (batched, calls), (alone, _) = logs[2], logs[1]
    resets = [c for c in calls if not isinstance(c, tuple)]
    assert resets == [["cube", "cake"], ["cube", "cube"]]  # two batches; the second padded with a copy
    # the live episodes observed in one call (observe_fn.batch) where two were live, one alone after that; each
    # episode's observation at each cut (keyed by its step seed) is the one it gets run alone
    assert ("batch", 2) in calls and not any(c == ("batch", 1) for c in calls)
    assert set(logs["seen"][2]) == set(logs["seen"][1])
    for seed, (x, lab) in logs["seen"][1].items():
        np.testing.assert_allclose(logs["seen"][2][seed][0], x, atol=1e-6, rtol=0)
        np.testing.assert_array_equal(logs["seen"][2][seed][1], lab)
    for a, b in zip(alone, batched):
        assert a.status == b.status == "ok", (a.error, b.error)
        assert a.actions == b.actions and a.turns == b.turns and a.num_pieces == b.num_pieces
        assert np.allclose(a.rewards, b.rewards, atol=1e-6, rtol=0) and abs(a.initial_reward - b.initial_reward) < 1e-6
        assert np.array_equal(a.labels, b.labels)


def test_an_episode_alone_moves_only_scene_0_and_equals_batch_size_1(logs):
    """One episode alone in a 2-scene batch (a planner's way: run_episodes(batch=False)) cuts, pushes and turns
    scene 0 only: scene 1, its planner's scratch (restored from scene 0 before each step's rollouts), idles
    through each of them, and the episode's log equals the same episode at batch size 1 (the stick: a push
    after each cut and a turn after the first)."""
    from topocut.sim.env import CuttingEnv

    env = CuttingEnv(SimConfig(**SIM, batch_size=2))
    calls = []
    def rows(x):  # scene 1's particles as a set: a turn re-sorts every scene's particles by cell
        return x[np.lexsort(x.T)]

    def spy(name, fn):  # what each primitive was asked to move, and what it did to scene 1
        def call(*a, **k):
            before = rows(np.asarray(env.state().x[1]).copy())
            out = fn(*a, **k)
            after = rows(np.asarray(env.state().x[1]))
            calls.append((name, a[0] if a else k.get("scenes"), np.array_equal(before, after)))
            return out
        return call

    for name in ("cut", "push", "turn"):
        setattr(env, name, spy(name, getattr(env, name)))
    sc = make_scoring(RewardConfig(), TopologyConfig(resolution=48))
    [log] = run_episodes(env, EPISODES[:1], Stopping(), sc, max_cuts=3, batch=False)
    [ref] = logs[1][0][:1]  # the same episode at batch size 1 (the fixture)
    assert log.status == ref.status == "ok", log.error
    assert log.actions == ref.actions and log.turns == ref.turns == [1] and log.num_pieces == ref.num_pieces
    assert np.allclose(log.rewards, ref.rewards, atol=1e-6, rtol=0) and np.array_equal(log.labels, ref.labels)
    assert [c[0] for c in calls] == ["cut", "push", "turn", "cut", "push", "cut", "push"]
    for what, arg, scene_1_kept in calls:
        moved = [a is not None for a in arg] if what in ("cut", "turn") else list(arg)
        assert moved == [True, False] and scene_1_kept, (what, arg)


def test_each_episode_follows_its_own_task(logs):
    stick, short, thick = logs[2][0]
    assert stick.turns == [1] and len(stick.actions) == 3  # the slab laid flat after the first cut
    assert short.turns == [] and len(short.actions) == 1  # its policy stopped: the scene idled after one cut
    assert thick.turns == [] and len(thick.actions) == 3
    assert stick.num_pieces[-1] >= 3 and thick.num_pieces[-1] >= 3  # the cuts made pieces
    assert len({len(e.labels) for e in (stick, short, thick)}) == 3  # three particle counts in the batches


# -- the policy call: act_batch once per step for all live episodes, act where it fails ---------------------
class _Planes:
    """The goal's planes, one per step; ``act_batch`` records its calls (and raises when told to)."""
    calls: list = []
    fail = False

    def reset(self, goal, seed=None):
        self.planes, self.t = list(goal.planes), 0

    def act(self, obs):
        if self.t >= len(self.planes):
            return None
        self.t += 1
        return self.planes[self.t - 1]

    @staticmethod
    def act_batch(policies, observations):
        _Planes.calls.append(len(policies))
        if _Planes.fail:
            raise RuntimeError("batched call failed")
        return [p.act(o) for p, o in zip(policies, observations)]


class _Boxes:
    """B scenes of 1-D 'particles' along x (as (n,3)); a cut at x0 moves those beyond it by 0.1."""
    batch_size = 3

    def __init__(self):
        from types import SimpleNamespace

        self.cfg = SimpleNamespace(board_z=0.0, spacing=0.01)

    def reset_scenes(self, objects, poses, seeds):
        self.x = [np.stack([np.linspace(0, 1, 20 + 5 * b), np.zeros(20 + 5 * b), np.zeros(20 + 5 * b)], -1)
                  for b in range(self.batch_size)]

    def cut(self, actions):
        for b, a in enumerate(actions):
            if a is not None:
                self.x[b][self.x[b][:, 0] > a.x, 0] += 0.1

    def state(self):
        from types import SimpleNamespace

        return SimpleNamespace(x=self.x, damage=[np.zeros(len(x), bool) for x in self.x], sweeps=[[]] * 3)


def _box_scoring():
    from types import SimpleNamespace

    from topocut.episode import Score, Scoring
    from topocut.sim.action import KnifeAction

    def goal_fn(task, obj, pose, spacing, seed=0):
        k = int(obj)
        return SimpleNamespace(planes=[KnifeAction(0.2 + 0.2 * i, 0.0) for i in range(k)], points=np.zeros((2, 3)),
                               labels=np.zeros(2, np.int32))

    def discover(x, damage, sweeps, previous):
        gaps = np.diff(np.sort(x[:, 0])) > 0.08
        return np.concatenate([[0], np.cumsum(gaps)])[np.argsort(np.argsort(x[:, 0]))].astype(np.int32)

    def score(xs, labels, goals, tasks):
        return [Score(float(len(np.unique(lab))), 0, False, len(np.unique(lab))) for lab in labels]

    return Scoring(goal_fn, discover, score)


@pytest.mark.parametrize("fail", [False, True])
def test_act_batch_is_one_call_per_step_and_falls_back_to_act(fail):
    from types import SimpleNamespace

    _Planes.calls, _Planes.fail = [], fail
    eps = [Episode(str(k), None, k, SimpleNamespace(push=False)) for k in (3, 1, 2)]  # 3, 1 and 2 planes
    logs = run_episodes(_Boxes(), eps, _Planes(), _box_scoring(), max_cuts=5)
    assert [len(lg.actions) for lg in logs] == [3, 1, 2]  # each stopped (None) after its own planes
    assert [lg.num_pieces[-1] for lg in logs] == [4, 2, 3] and all(lg.status == "ok" for lg in logs)
    # steps 1-4: 3, 3 (the 1-plane episode said None at step 2), 2, 1 live episodes; one live episode
    # calls act directly; a failing batched call was retried per episode with act
    assert _Planes.calls == [3, 3, 2]


def test_frames_carry_the_executed_cut_with_the_state_it_made():
    """Renders draw each cut's knife from the frame itself: the reset frame has none, each cut frame the action
    the engine executed (= EpisodeLog.actions), in order, with the labels scored after it."""
    from types import SimpleNamespace

    _Planes.calls, _Planes.fail = [], False
    eps = [Episode(str(k), None, k, SimpleNamespace(push=False)) for k in (3, 2)]
    logs = run_episodes(_Boxes(), eps, _Planes(), _box_scoring(), max_cuts=5, frames=True)
    for lg in logs:
        assert lg.frames[0][2] == "reset" and lg.frames[0][3] is None
        cuts = [f for f in lg.frames if f[3] is not None]
        assert [f[2].split(":")[0] for f in cuts] == [f"cut {k + 1}" for k in range(len(lg.actions))]
        np.testing.assert_allclose([f[3].to_vector() for f in cuts], lg.actions, atol=1e-6)
        assert [len(np.unique(f[1])) for f in cuts] == lg.num_pieces


def test_progress_names_the_episode_when_the_caller_reset_the_scene():
    """MPPI's episodes come without an object (the caller reset the scene): the progress line names the goal's
    object, never a literal None (issue: `mppi slice/cake 1/4 (20 s): None cut 1: reward 0.500`)."""
    from types import SimpleNamespace

    from topocut.sim.action import KnifeAction

    _Planes.calls, _Planes.fail = [], False
    goal = SimpleNamespace(planes=[KnifeAction(0.3, 0.0)], points=np.zeros((2, 3)), labels=np.zeros(2, np.int32),
                           object="cube")
    env = _Boxes()
    env.reset_scenes(None, None, None)  # the scene is loaded, as stage=mppi's run_episode finds it
    infos = []
    run_episodes(env, [Episode(None, None, 1, SimpleNamespace(push=False), goal=goal)], _Planes(), _box_scoring(),
                 max_cuts=2, progress=lambda n, info: infos.append(info))
    assert infos and infos[0].startswith("cube cut 1:") and not any("None" in i for i in infos)


class _PushedBoxes(_Boxes):
    """_Boxes whose cut leaves the two sides touching (it records a sweep) and whose push slides every particle
    beyond the last cut 0.1 along x, as the simulator's push slides one side away from the blade."""

    def cut(self, actions):
        self.at = [None if a is None else a.x for a in actions]
        self.sweeps = [[] if a is None else [f"sweep at {a.x}"] for a in actions]

    def push(self, scenes=None):
        for b, x0 in enumerate(self.at):
            if x0 is not None and (scenes is None or scenes[b]):
                self.x[b][self.x[b][:, 0] > x0, 0] += 0.1

    def state(self):
        from types import SimpleNamespace

        return SimpleNamespace(x=[x.copy() for x in self.x], damage=[np.zeros(len(x), bool) for x in self.x],
                               sweeps=getattr(self, "sweeps", [[]] * 3))


def test_discovery_runs_where_the_blade_left_the_pieces_then_after_the_push():
    """docs/topology.md#discovery-and-the-push: after each cut the engine discovers the pieces with the cut's
    sweep on the state the blade left (nothing moved yet), then pushes, then discovers again with no sweep and
    the first discovery's labels as the previous ones; the score sees the pushed positions."""
    from types import SimpleNamespace

    sc = _box_scoring()
    calls = []
    split_by_sweep = sc.discover_fn

    def discover(x, damage, sweeps, previous, start_positions=None):
        calls.append((float(np.diff(np.sort(x[:, 0])).max()), list(sweeps or []),
                      None if previous is None else np.asarray(previous).copy(), start_positions))
        if sweeps:  # where the blade left them only the sweep separates the two sides
            cut_at = float(sweeps[0].split()[-1])
            return (x[:, 0] > cut_at).astype(np.int32)
        return split_by_sweep(x, damage, sweeps, previous)

    sc.discover_fn = discover
    scored = []
    score = sc.score_fn
    sc.score_fn = lambda xs, labels, goals, tasks: scored.append([x.copy() for x in xs]) or score(xs, labels, goals,
                                                                                                  tasks)
    _Planes.calls, _Planes.fail = [], False
    env = _PushedBoxes()
    logs = run_episodes(env, [Episode("1", None, 1, SimpleNamespace(push=True))], _Planes(), sc, max_cuts=5)
    assert logs[0].status == "ok" and logs[0].num_pieces == [2]
    reset, before_push, after_push = calls  # the uncut scene, then the two discoveries of the one cut
    assert len(before_push[1]) == 1 and before_push[1][0].startswith("sweep at 0.2")
    assert before_push[0] < 0.08  # the sides still touch
    assert after_push[1] == [] and after_push[0] > 0.09  # pushed apart, no sweep
    # where the blade started (a kerf particle keeps its side there): given to the cut's discovery only
    np.testing.assert_array_equal(before_push[3], np.stack([np.linspace(0, 1, 20), np.zeros(20), np.zeros(20)], -1))
    assert after_push[3] is None
    x_cut = np.linspace(0, 1, 20)  # where the blade left them: the first discovery's labels are the previous ones
    np.testing.assert_array_equal(after_push[2], (x_cut > float(before_push[1][0].split()[-1])).astype(np.int32))
    assert np.diff(np.sort(scored[-1][0][:, 0])).max() > 0.09  # the score sees the pushed positions

"""Teleoperation state machine (scripted events, undo, save, replay) and the episode runner.

The unit tests use a small fake environment implementing the CuttingEnv contract:
a cut moves the particles on the +n side of the plane by 0.01 along n, a push
lowers everything by 0.005; the fake scorer splits clusters by cut planes.
"""
import json
import re
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import pytest

import topocut.planning.teleop as teleop
from topocut.planning import run_episode
from topocut.planning.teleop import Key, MouseMove, TeleopConfig, TeleopSession, Wheel, load_log, replay
from topocut.sim.action import KnifeAction, cut_mask

STEP_KEYS = ("x_t", "f_t", "x_t1", "f_t1", "action", "pose", "history", "reward", "success")


@dataclass
class FakeState:
    x: np.ndarray  # B,N,3
    damage: np.ndarray  # B,N
    sweeps: list


class FakeEnv:
    def __init__(self, batch_size=1, n=80):
        self.batch_size, self.n, self.cfg = batch_size, n, SimpleNamespace(board_z=0.05)
        self.raise_on_cut = None
        self.executed = []  # the actions of every cut, as the simulator received them

    def reset(self, object, pose=None, seed=0):
        rng = np.random.default_rng(seed)
        self.x = np.repeat(rng.uniform(0.4, 0.6, (1, self.n, 3)), self.batch_size, 0).astype(np.float32)
        self.damage = np.zeros((self.batch_size, self.n), bool)
        self.sweeps = [[] for _ in range(self.batch_size)]

    def cut(self, action):
        if self.raise_on_cut is not None:
            raise self.raise_on_cut
        acts = action if isinstance(action, list) else [action]
        self.executed.append(acts[0])
        for b, a in enumerate(acts):
            side = cut_mask(self.x[b], a).astype(np.float32)
            self.x[b] += (0.01 * side[:, None] * a.normal).astype(np.float32)
            self.sweeps[b] = [a]

    def push(self):
        self.x[..., 2] = np.maximum(self.x[..., 2] - 0.005, 0.05)

    def state(self):
        return FakeState(self.x.copy(), self.damage.copy(), [list(s) for s in self.sweeps])

    def get_state(self, b=0):
        return {"x": self.x[b].copy(), "damage": self.damage[b].copy(), "sweeps": list(self.sweeps[b])}

    def set_state(self, d, b=None):
        for i in range(self.batch_size) if b is None else [b]:
            self.x[i], self.damage[i], self.sweeps[i] = d["x"], d["damage"], list(d["sweeps"])


class FakeScorer:
    """Cluster id = compact code of the sides of every cut plane so far; reward penalises the wrong count."""

    def __init__(self, n_goal=3):
        self.n_goal = n_goal

    def labels(self, x, damage, sweeps, previous=None):
        prev = np.zeros(len(x), np.int64) if previous is None else np.asarray(previous, np.int64)
        if not sweeps:
            return prev.astype(np.int32)
        code = prev * 2 + cut_mask(x, sweeps[-1])
        return np.unique(code, return_inverse=True)[1].astype(np.int32)

    def reward(self, x, labels):
        k = len(np.unique(labels))
        return -abs(k - self.n_goal) - float(np.mean(x[:, 2])), k == self.n_goal


GOAL = SimpleNamespace(planes=[KnifeAction(0.45, 0.5), KnifeAction(0.55, 0.5)], points=np.zeros((5, 3)),
                       labels=np.zeros(5, np.int32))


def session(tmp_path, seed=0):
    return TeleopSession(FakeEnv(), GOAL, "cube", None, seed, "slice", scorer=FakeScorer(),
                         cfg=TeleopConfig(log_path=str(tmp_path / "log.json")))


def assert_same_records(a, b):
    assert len(a) == len(b)
    for sa, sb in zip(a, b):
        for k in STEP_KEYS:
            np.testing.assert_array_equal(sa[k], sb[k], err_msg=k)


def test_events_move_rotate_and_cut(tmp_path):
    s = session(tmp_path)
    s.handle(MouseMove(0.3, 0.62))
    s.handle(Wheel(2))  # +2 notches of 5 degrees of yaw
    s.handle(Key("left", shift=True))  # +1 notch of 2 degrees of tilt
    s.handle(Key("d"))  # -5 degrees of yaw
    np.testing.assert_allclose(s.knife, [0.3, 0.62, np.radians(5), np.radians(2)])
    s.handle(MouseMove(1.7, -0.2))
    np.testing.assert_allclose(s.knife[:2], [1.0, 0.0])  # clipped to the board square
    s.handle(MouseMove(0.5, 0.5))
    s.handle(Key("c"))
    assert len(s.steps) == 1 and s.log["actions"] == [{"type": "cut", "action": list(s.steps[0]["action"].astype(float))}]
    np.testing.assert_allclose(s.steps[0]["action"], [0.5, 0.5, np.radians(5), np.radians(2)], atol=1e-6)
    assert len(np.unique(s.steps[0]["f_t1"])) == 2 and (s.steps[0]["f_t"] == 0).all()
    with pytest.raises(TypeError, match="MouseMove, Key or Wheel"):
        s.handle("c")


def test_undo_restores_state_labels_and_history(tmp_path):
    s = session(tmp_path)
    for x in (0.45, 0.55):
        s.handle(MouseMove(x, 0.5))
        s.handle(Key("c"))
    after_first = s.steps[0]
    assert s.undo() and len(s.steps) == 1
    np.testing.assert_array_equal(s.env.get_state(0)["x"], after_first["x_t1"])
    np.testing.assert_array_equal(s.labels, after_first["f_t1"])
    np.testing.assert_array_equal(np.stack(list(s.history))[:2], np.zeros((2, 7)))
    np.testing.assert_allclose(np.stack(list(s.history))[2], KnifeAction(0.45, 0.5).pose_feature())
    s.handle(Key("u"))
    assert len(s.steps) == 0 and (s.labels == 0).all()
    n_log = len(s.log["actions"])
    assert not s.undo() and s.message == "nothing to undo" and len(s.log["actions"]) == n_log  # not logged


def test_scripted_session_saves_atomically_and_replays_identically(tmp_path):
    s = session(tmp_path, seed=4)
    script = [MouseMove(0.45, 0.5), Key("c"), Key("p"), MouseMove(0.52, 0.47), Wheel(3), Key("c"), Key("u"),
              MouseMove(0.56, 0.5), Key("c"), Key("p"), Key("p"), Key("s"), Key("escape")]
    for ev in script:
        s.handle(ev)
    assert s.done and [a["type"] for a in s.log["actions"]] == ["cut", "push", "cut", "undo", "cut", "push", "push"]
    path = tmp_path / "log.json"
    assert [p.name for p in tmp_path.iterdir()] == ["log.json"]  # no temp file left behind
    log = load_log(path)
    assert (log["object"], log["seed"], log["task"]) == ("cube", 4, "slice")
    steps, summary = replay(log, FakeEnv(), GOAL, scorer=FakeScorer())
    assert_same_records(steps, s.steps)
    assert summary["num_cuts"] == 2 and summary["final_reward"] == s.steps[-1]["reward"]
    # the two pushes after the last cut are part of its record: x_t1 is 2 x 0.005 lower where not on the board
    pre = s.steps[1]
    assert np.all(pre["x_t1"][:, 2] <= pre["x_t"][:, 2] + 1e-7) and pre["x_t1"][:, 2].min() >= 0.05
    with pytest.raises(ValueError, match="cut, push, undo"):
        replay({**log, "actions": [{"type": "slice"}]}, FakeEnv(), GOAL, scorer=FakeScorer())
    json.loads(path.read_text())


class Scripted:
    def __init__(self, actions):
        self.actions = actions

    def reset(self, goal):
        self.t = 0

    def act(self, obs):
        assert {"points", "labels", "history", "goal", "goal_labels", "sim_state", "particle_labels"} <= set(obs)
        self.t += 1
        return self.actions[self.t - 1]


def test_run_episode_matches_teleop_with_push_and_stops_at_success(tmp_path):
    actions = [KnifeAction(0.45, 0.5), KnifeAction(0.55, 0.5), KnifeAction(0.5, 0.45, yaw=1.5)]
    env = FakeEnv()
    env.reset("cube", None, seed=2)
    steps, summary = run_episode(env, GOAL, Scripted(actions), max_cuts=3, push=True, scorer=FakeScorer())
    assert summary["num_cuts"] == 2 and summary["success"] and summary["status"] == "ok"  # 3 clusters after 2 cuts
    for a, b in zip(steps[:-1], steps[1:]):
        np.testing.assert_array_equal(a["x_t1"], b["x_t"])
        np.testing.assert_array_equal(a["f_t1"], b["f_t"])
    np.testing.assert_array_equal(steps[0]["history"], np.zeros((3, 7)))
    np.testing.assert_allclose(steps[1]["history"][2], actions[0].pose_feature())
    np.testing.assert_allclose(steps[1]["pose"], actions[1].to_matrix(0.05), atol=1e-6)
    s = TeleopSession(FakeEnv(), GOAL, "cube", None, 2, "slice", scorer=FakeScorer())
    for a in actions[:2]:
        s.apply({"type": "cut", "action": a.to_vector().tolist()})
        s.apply({"type": "push"})
    assert_same_records(s.steps, steps)


def test_run_episode_marks_divergence_failed():
    try:
        from topocut.sim import SimulationDiverged
    except ImportError as e:
        pytest.skip(f"topocut.sim.SimulationDiverged not importable yet: {e}")
    env = FakeEnv()
    env.reset("cube", None, seed=0)
    pol = Scripted([KnifeAction(0.45, 0.5), KnifeAction(0.55, 0.5)])
    orig = env.cut

    def cut_then_diverge(action):
        if pol.t == 2:
            raise SimulationDiverged(17, 0)
        orig(action)

    env.cut = cut_then_diverge
    steps, summary = run_episode(env, GOAL, pol, max_cuts=2, scorer=FakeScorer(5))
    assert summary["status"] == "failed" and len(steps) == 1 and "step 17" in summary["error"]


def test_teleop_replay_in_simulator_matches_live(tmp_path):
    try:
        from topocut.reward import spectral_reward  # noqa: F401
        from topocut.sim.config import SimConfig
        from topocut.sim.env import CuttingEnv
        from topocut.sim.objects import ObjectPose
        from topocut.tasks import make_goal, task_config
        from topocut.topology import discover  # noqa: F401
    except ImportError as e:
        pytest.skip(f"simulator/topology/reward/goals not importable yet: {e}")
    cfg = SimConfig()
    for k, v in {"n_grid": 32, "batch_size": 1, "arch": "cpu"}.items():
        if hasattr(cfg, k):
            setattr(cfg, k, v)
    pose = ObjectPose()
    goal = make_goal(task_config("slice"), "cube", pose, getattr(cfg, "spacing", 0.01))
    env = CuttingEnv(cfg, batch_size=1)
    s = TeleopSession(env, goal, "cube", pose, 0, "slice", cfg=TeleopConfig(log_path=str(tmp_path / "log.json")))
    p0, p1 = goal.planes[0], goal.planes[min(1, len(goal.planes) - 1)]
    for ev in [MouseMove(p0.x, p0.y), Key("c"), MouseMove(0.5, 0.5), Key("c"), Key("u"), MouseMove(p1.x, p1.y),
               Key("c"), Key("s")]:
        s.handle(ev)
    live = [{k: st[k] for k in ("x_t", "f_t", "x_t1", "f_t1", "reward")} for st in s.steps]
    steps, _ = replay(load_log(tmp_path / "log.json"), env, goal)
    assert len(steps) == 2
    for a, b in zip(steps, live):
        np.testing.assert_allclose(a["x_t1"], b["x_t1"], atol=1e-6)
        np.testing.assert_array_equal(a["f_t1"], b["f_t1"])
        assert a["reward"] == pytest.approx(b["reward"], abs=1e-6)


def test_sim_rollout_chunks_restore_state_and_score_on_fake_env():
    from topocut.planning.rollout import make_sim_rollout

    A = [[0.45, 0.5, 0, 0], [0.55, 0.5, 0, 0]]  # two cuts through the cloud: 3 pieces, cost 0
    B = [[0.95, 0.5, 0, 0], [0.95, 0.5, 0, 0]]  # misses the cloud twice: 1 piece, cost |1 - 3| = 2
    C = [[0.45, 0.5, 0, 0], [0.45, 0.5, 0, 0]]  # the same plane twice: 2 pieces, cost 1
    seqs = np.array([A, B, C, A, C], np.float32)  # K=5, H=2
    results = []
    for batch in (1, 2, 5):
        env = FakeEnv(batch_size=batch)
        env.reset("cube", None, seed=3)
        state = env.get_state(0)
        z_mean = float(np.mean(state["x"][:, 2]))  # yaw = tilt = 0 cuts move along x only
        env.cut([KnifeAction(0.5, 0.5)] * batch)  # the rollout must restore the saved state first
        rollout = make_sim_rollout(env, state, GOAL, scorer=FakeScorer(3))
        costs = rollout(seqs)
        np.testing.assert_allclose(costs, np.array([0, 2, 1, 0, 1]) + z_mean, atol=1e-6)
        results.append(costs)
    np.testing.assert_array_equal(results[0], results[1])
    np.testing.assert_array_equal(results[0], results[2])


# ---- review fixes: failed cuts, window fallback, log safety, entry errors, float32 planes ------------------

def _diverged():
    from topocut.sim import SimulationDiverged

    return SimulationDiverged(812, 0)


def test_failed_cut_is_reported_and_changes_nothing(tmp_path):
    s = session(tmp_path)
    x0 = s.env.get_state(0)["x"].copy()
    s.handle(MouseMove(0.45, 0.5))
    s.handle(Key("c"))
    x1, labels1, log1 = s.env.get_state(0)["x"].copy(), s.labels.copy(), json.dumps(s.log)
    cut = s.env.cut

    def cut_then_diverge(action):  # the simulator moved particles before it noticed the NaN
        cut(action)
        raise _diverged()

    s.env.cut = cut_then_diverge
    s.handle(MouseMove(0.55, 0.5))
    msg = s.handle(Key("c"))  # reported to the operator, the session goes on
    assert msg.startswith("cut failed, scene restored") and "substep 812" in msg and not s.done
    with pytest.raises(type(_diverged()), match="substep 812"):  # called directly: raised as itself
        s.cut()
    assert len(s.steps) == 1 and len(s._snapshots) == 1 and json.dumps(s.log) == log1
    np.testing.assert_array_equal(s.env.get_state(0)["x"], x1)  # the scene before the failed cut
    np.testing.assert_array_equal(s.labels, labels1)
    s.env.cut = cut
    s.handle(Key("u"))  # undoes the one cut that happened, not the failed one
    assert len(s.steps) == 0
    np.testing.assert_array_equal(s.env.get_state(0)["x"], x0)
    s.env.raise_on_cut = ValueError("scorer bug")  # anything but a divergence propagates as itself
    with pytest.raises(ValueError, match="scorer bug"):
        s.handle(Key("c"))


def test_window_fallback_covers_only_opening_a_window(monkeypatch, tmp_path):
    opened, looped = [], []

    def open_window(kind, res):
        opened.append(kind)
        if kind in fail:
            raise RuntimeError(f"no {kind} here")
        return kind

    def loop(kind):
        def run(session, window):
            looped.append(kind)
            session.handle(MouseMove(0.45, 0.5))
            session.handle(Key("c"))
            if kind == "ggui":
                raise KeyError("bug in the loop")
        return run

    monkeypatch.setattr(teleop, "_ensure_taichi", lambda: None)
    monkeypatch.setattr(teleop, "_open_window", open_window)
    monkeypatch.setattr(teleop, "_loop_ggui", loop("ggui"))
    monkeypatch.setattr(teleop, "_loop_cpu_gui", loop("gui"))
    fail = set()
    s = session(tmp_path)
    with pytest.raises(KeyError, match="bug in the loop"):  # not "cannot open a teleop window", no second GUI
        teleop.run_window(s, backend="auto")
    assert opened == ["ggui"] and looped == ["ggui"] and len(s.steps) == 1
    opened.clear()
    looped.clear()
    fail = {"ggui"}
    assert teleop.run_window(session(tmp_path), backend="auto").steps  # no Vulkan: the CPU GUI runs the session
    assert opened == ["ggui", "gui"] and looped == ["gui"]
    with pytest.raises(RuntimeError, match="GGUI window unavailable.*no ggui here"):
        teleop.run_window(session(tmp_path), backend="ggui")
    fail = {"ggui", "gui"}
    with pytest.raises(RuntimeError, match="cannot open a teleop window.*no gui here.*stage.run.replay"):
        teleop.run_window(session(tmp_path), backend="auto")


def test_live_log_is_saved_when_the_session_fails(monkeypatch, tmp_path):
    from pipelines.teleop import record_session

    def window(session, backend):
        session.handle(MouseMove(0.45, 0.5))
        session.handle(Key("c"))
        raise KeyboardInterrupt  # Ctrl-C in the terminal, or any error in the window

    monkeypatch.setattr(teleop, "run_window", window)
    s, path = session(tmp_path), tmp_path / "run" / "teleop_log.json"
    with pytest.raises(KeyboardInterrupt):
        record_session(s, path)
    assert load_log(path)["actions"] == [{"type": "cut", "action": [0.44999998807907104, 0.5, 0.0, 0.0]}]
    assert [p.name for p in path.parent.iterdir()] == ["teleop_log.json"]  # written via a temp file + rename
    monkeypatch.setattr(teleop, "run_window", lambda session, backend: session.handle(Key("p")))
    assert record_session(s, path) == path and [a["type"] for a in load_log(path)["actions"]] == ["cut", "push"]


def test_bad_log_entries_name_the_file_and_the_index(tmp_path):
    path = tmp_path / "log.json"
    ok = {"type": "cut", "action": [0.45, 0.5, 0.0, 0.0]}
    for actions, needle in [([ok, {"type": "cut"}], "entry 1: a cut has no 'action'"),
                            ([ok, {"type": "push"}, {"type": "cut", "action": [0.5, 0.5]}], "entry 2: .*4 finite"),
                            ([{"type": "slice"}], "entry 0: entry type 'slice'; valid: cut, push, undo")]:
        path.write_text(json.dumps({"object": "cube", "seed": 0, "task": "slice", "actions": actions}))
        for call in (lambda: load_log(path), lambda: replay(path, FakeEnv(), GOAL, scorer=FakeScorer())):
            with pytest.raises(ValueError, match=f"teleop log {re.escape(str(path))}, {needle}"):
                call()
        with pytest.raises(ValueError, match=f"teleop log, {needle}"):  # a dict: checked before any cut runs
            replay(json.loads(path.read_text()), FakeEnv(), GOAL, scorer=FakeScorer())
    path.write_text('{"object": "cube", "seed": 0, "actions": [')  # torn file
    with pytest.raises(ValueError, match=f"teleop log {re.escape(str(path))} is not valid JSON.*line 1"):
        replay(path, FakeEnv(), GOAL, scorer=FakeScorer())


def test_stored_action_is_the_plane_that_was_executed():
    """yaw = pi/2 exactly: float32(pi/2) > pi/2 wraps to -pi/2 with the normal reversed, so a record that
    stored float32 of the executed float64 action would describe the opposite half-space."""
    a = KnifeAction(0.5, 0.5, yaw=np.pi / 2)
    env = FakeEnv()
    env.reset("cube", None, seed=0)
    steps, _ = run_episode(env, GOAL, Scripted([a]), max_cuts=1, scorer=FakeScorer(9))
    s = TeleopSession(FakeEnv(), GOAL, "cube", None, 0, "slice", scorer=FakeScorer(9))
    s.apply({"type": "cut", "action": [0.5, 0.5, np.pi / 2, 0.0]})
    for step, executed in ((steps[0], env.executed[0]), (s.steps[0], s.env.executed[0])):
        stored = KnifeAction.from_vector(step["action"])
        assert stored == executed
        np.testing.assert_array_equal(step["pose"], executed.to_matrix(0.05).astype(np.float32))
        moved = np.any(step["x_t1"] != step["x_t"], axis=1)  # the fake moves the +n side by 0.01 n
        assert 0 < moved.sum() < len(moved)
        np.testing.assert_array_equal(moved, cut_mask(step["x_t"], stored).astype(bool))
        shift = (step["x_t1"] - step["x_t"])[moved] / 0.01  # the pose's normal: where the particles moved
        np.testing.assert_allclose(shift, np.tile(step["pose"][:3, 2], (len(shift), 1)), atol=1e-4)

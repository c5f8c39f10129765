"""A scene kept on the device (CuttingEnv.save_scene / restore_scene, topocut.sim.slots): what MPPI's rollouts
start from instead of a numpy round trip of every scene (issue #49 item 2).  Checked against the numpy path:
the fields read back directly, and set_state of the same state."""
import numpy as np
import pytest

pytest.importorskip("taichi")

from topocut.sim import CuttingEnv, KnifeAction, SimConfig  # noqa: E402
from topocut.sim.objects import ObjectPose  # noqa: E402

# a short cut and push (as tests/test_stages.py's FAST): what is checked is what the state restores, not the physics
QUICK = dict(n_grid=32, arch="cpu", cut_substeps=40, dwell_time=0.0005, push_time=0.002, settle_time=0.002)


def _env(B):
    env = CuttingEnv(SimConfig(**QUICK), batch_size=B)
    env.reset("cube", ObjectPose(), seed=0)
    return env


def _fields(env, b):
    s = env.solver
    n = int(env.counts[b])
    return {k: getattr(s, k).to_numpy()[b, :n] for k in ("x", "v", "C", "F", "Jp", "sigma_y", "damage", "body",
                                                         "material")}


def test_get_state_copies_exactly_the_scene_asked_for():
    env = CuttingEnv(SimConfig(**QUICK), batch_size=2)
    env.reset_scenes(["cube", "potato"], [ObjectPose(), ObjectPose(yaw=0.3)], [0, 1])
    env.cut([KnifeAction.from_plane(np.array([1.0, 0, 0]), np.array([0.5, 0.5, 0.1])),
             KnifeAction.from_plane(np.array([0, 1.0, 0]), np.array([0.5, 0.48, 0.1]))])
    for b in (0, 1):
        st, direct = env.get_state(b), _fields(env, b)
        assert len(st["x"]) == env.counts[b]
        for k in ("x", "v", "C", "F", "sigma_y", "body", "material"):
            np.testing.assert_array_equal(st[k], direct[k], err_msg=k)
        np.testing.assert_array_equal(st["damage"], direct["damage"].astype(bool))
        np.testing.assert_array_equal(st["piece"], env.piece[b, :env.counts[b]])


def test_restore_puts_the_saved_scene_into_every_scene_as_it_was():
    env = _env(2)
    env.cut(KnifeAction.from_plane(np.array([1.0, 0, 0]), np.array([0.5, 0.5, 0.1])))
    before, piece, sweeps = _fields(env, 0), env.piece[0].copy(), list(env.sweeps[0])
    saved = env.save_scene(0, "t")
    env.cut(KnifeAction.from_plane(np.array([0, 1.0, 0]), np.array([0.5, 0.45, 0.1])))  # the scenes move on
    assert not np.array_equal(_fields(env, 1)["x"], before["x"])
    assert env.restore_scene(saved)
    for b in (0, 1):
        now = _fields(env, b)
        for k, v in before.items():
            np.testing.assert_array_equal(now[k], v, err_msg=f"scene {b} {k}")
        np.testing.assert_array_equal(env.piece[b], piece)
        assert env.sweeps[b] == sweeps
    assert env.push_side.tolist() == [0, 0] and not env.dead.any()


def test_a_later_save_under_the_same_name_invalidates_the_earlier():
    env = _env(1)
    first = env.save_scene(0, "t")
    second = env.save_scene(0, "t")
    assert not env.restore_scene(first)  # the slot holds the second now: the caller loads through set_state
    assert env.restore_scene(second)
    x = env.state().x[0]
    env.load_particles(np.concatenate([x + [dx, 0.0, 0.0] for dx in (-0.2, 0.0, 0.2)]),
                       np.zeros(3 * env.n, np.int32))  # thrice the particles: a new solver, its slots empty
    assert not env.restore_scene(second)


def test_rollouts_from_the_saved_start_equal_those_loaded_through_numpy(monkeypatch):
    """An MPPI iteration of three sequences in chunks of two: the first chunk loads the start through set_state
    and keeps it on the device, the second restores it; with restores refused (every chunk through set_state,
    the path before) the costs are the same bit for bit."""
    from topocut.planning.rollout import make_sim_rollout
    from topocut.tasks import make_goal, task_config

    goal = make_goal(task_config("slice"), "cube", ObjectPose(), SimConfig(n_grid=32).spacing)
    seqs = np.array([[goal.planes[0].to_vector()], [[0.45, 0.5, 0.0, 0.0]], [[0.55, 0.5, 0.1, 0.0]]], np.float32)
    out = []
    for refuse in (False, True):
        env = _env(2)
        state = env.get_state(0)
        if refuse:
            monkeypatch.setattr(env, "restore_scene", lambda saved: False)
        calls = []
        monkeypatch.setattr(env, "set_state", lambda *a, _c=calls, _f=env.set_state, **k: _c.append(1) or _f(*a, **k))
        rollout = make_sim_rollout(env, state, goal, board_z=env.cfg.board_z)
        out.append(rollout(seqs))
        assert len(calls) == (2 if refuse else 1)  # one per chunk, or only the first load
    np.testing.assert_array_equal(out[0], out[1])
    assert np.isfinite(out[0]).all()


def test_a_demonstration_plans_from_the_engines_saved_scene_without_loading_through_numpy(monkeypatch):
    """run_episode (MPPI, K = 2 scenes, 2 iterations): the engine keeps the scene on the device before planning
    (obs["sim_saved"]); the rollouts and the restore after planning use it, so nothing goes through set_state."""
    from topocut.planning import MPPIConfig, MPPIPolicy, run_episode, sim_rollout_factory
    from topocut.tasks import make_goal, task_config

    env = _env(2)
    goal = make_goal(task_config("slice"), "cube", ObjectPose(), env.cfg.spacing, board_z=env.cfg.board_z)
    calls = []
    monkeypatch.setattr(env, "set_state", lambda *a, _f=env.set_state, **k: calls.append(1) or _f(*a, **k))
    factory = sim_rollout_factory(env, board_z=env.cfg.board_z)
    steps, summary = run_episode(env, goal, MPPIPolicy(MPPIConfig(num_samples=2, iterations=2, horizon=1), factory,
                                                       seed=0), max_cuts=1, seed=0)
    assert summary["status"] != "failed" and len(steps) == 1
    assert calls == []

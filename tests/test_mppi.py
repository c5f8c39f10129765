"""MPPI core against synthetic costs with known minima; heuristic and MPPI policies; the sim rollout."""
from pathlib import Path

import numpy as np
import pytest

from topocut.planning import MPPI, GoalPlanesPolicy, MPPIConfig, MPPIPolicy, mppi_weights, shift
from topocut.sim.action import KnifeAction


class Goal:  # the parts of topocut.tasks.Goal the planners read
    def __init__(self, planes):
        self.planes = planes
        self.points = np.zeros((4, 3), np.float32)
        self.labels = np.zeros(4, np.int32)


def quadratic(target, scale):
    def rollout(seqs):  # K,H,4 -> K
        return np.sum(((seqs - target) / scale) ** 2, axis=(1, 2))
    return rollout


def test_weights_formula_and_limits():
    costs = np.array([3.0, 1.0, 2.0, np.inf])
    w = mppi_weights(costs, temperature=1.0)
    e = np.exp(-(np.array([3.0, 1.0, 2.0]) - 1.0))
    np.testing.assert_allclose(w[:3], e / e.sum())
    assert w[3] == 0 and np.isclose(w.sum(), 1.0)
    np.testing.assert_allclose(mppi_weights(costs, 1e-9), [0, 1, 0, 0])  # lambda -> 0: the best sample
    np.testing.assert_allclose(mppi_weights(costs[:3], 1e9), [1 / 3] * 3)  # lambda -> inf: uniform
    # normalised costs: (J - Jmin)/(Jmax - Jmin) = [1, 0, .5]
    e = np.exp(-np.array([1.0, 0.0, 0.5]) / 0.5)
    np.testing.assert_allclose(mppi_weights(costs, 0.5, normalize=True)[:3], e / e.sum())
    np.testing.assert_allclose(mppi_weights(np.full(3, np.nan), 1.0), [1 / 3] * 3)  # all diverged: keep mean


def test_converges_to_quadratic_minimum():
    target = np.array([[0.6, 0.42, 0.5, 0.0], [0.4, 0.55, -0.3, 0.0]])  # H=2
    cfg = MPPIConfig(num_samples=64, horizon=2, iterations=40, noise_sigma=[0.03, 0.03, 0.1, 0.1],
                     temperature=0.05, control_penalty=0.0)
    mppi = MPPI(cfg, quadratic(target, np.array([0.03, 0.03, 0.1, 1.0])), np.random.default_rng(0))
    start = np.array([[0.5, 0.5, 0.0, 0.0], [0.5, 0.5, 0.0, 0.0]])
    mean, info = mppi.plan(start)
    err0 = np.abs(start - target)[:, :3] / [0.03, 0.03, 0.1]
    err = np.abs(mean - target)[:, :3] / [0.03, 0.03, 0.1]
    assert err0.max() > 4 and err.max() < 0.5  # from > 4 sigma away to within half a sigma
    assert info["best_cost"] <= info["iterations"][0]["costs"][0]  # never worse than the start (sample 0)
    assert info["num_rollouts"] == 40 * 64


def test_planning_stops_after_the_first_iteration_in_which_a_rollout_succeeds():
    """stop_at_success: the iteration in which some finite-cost sequence succeeds is the last (its best sequence
    and mean update kept); a success only on a diverged (+inf) sequence, a rollout that reports no success, or
    stop_at_success=false run every iteration."""
    target = np.array([[0.6, 0.42, 0.5, 0.0]])
    scale = np.array([0.03, 0.03, 0.1, 1.0])
    cost = quadratic(target, scale)
    calls = []

    def succeeds_from(iteration, inf_only=False):
        def rollout(seqs):
            calls.append(len(seqs))
            c = cost(seqs)
            ok = np.zeros(len(seqs), bool)
            if len(calls) >= iteration:
                ok[0] = True  # sample 0 (the mean) succeeds from this iteration on
                if inf_only:
                    c[0] = np.inf
            return c, ok
        return rollout

    cfg = MPPIConfig(num_samples=6, horizon=1, iterations=4, control_penalty=0.0)
    start = np.array([[0.5, 0.5, 0.0, 0.0]])
    for iteration, expected in ((1, 1), (3, 3), (9, 4)):
        calls.clear()
        mean, info = MPPI(cfg, succeeds_from(iteration), np.random.default_rng(0)).plan(start)
        assert len(info["iterations"]) == len(calls) == expected, (iteration, info["stopped_at_success"])
        assert info["stopped_at_success"] == (iteration <= 4)
        assert info["num_rollouts"] == expected * 6
        best = min(it["costs"].min() for it in info["iterations"])
        assert info["best_cost"] == best  # the best of the iterations run
    # the same rollouts without the rule: every iteration
    calls.clear()
    off = MPPIConfig(num_samples=6, horizon=1, iterations=4, control_penalty=0.0, stop_at_success=False)
    _, info = MPPI(off, succeeds_from(1), np.random.default_rng(0)).plan(start)
    assert len(calls) == 4 and not info["stopped_at_success"]
    calls.clear()
    _, info = MPPI(cfg, succeeds_from(1, inf_only=True), np.random.default_rng(0)).plan(start)
    assert len(calls) == 4 and not info["stopped_at_success"]  # a diverged sequence's success does not count
    _, info = MPPI(cfg, cost, np.random.default_rng(0)).plan(start)  # costs only
    assert len(info["iterations"]) == 4 and not info["stopped_at_success"]


def test_mppi_policy_records_the_iterations_of_each_cut():
    """MPPIPolicy.iterations_done: per executed cut, the iterations planned (the demonstrations' episode log
    records them as mppi_iterations); reset starts a new list."""
    goal = Goal([KnifeAction(0.4, 0.5, 0.0), KnifeAction(0.6, 0.5, 0.0)])
    rounds = iter([False, True])

    def factory(obs, goal):
        done = next(rounds)  # the first cut's rollouts never succeed, the second's do
        return lambda seqs: (np.zeros(len(seqs)), np.full(len(seqs), done))

    policy = MPPIPolicy(MPPIConfig(num_samples=4, horizon=1, iterations=3), factory, seed=0, goal=goal)
    policy.act({})
    policy.act({})
    assert policy.iterations_done == [3, 1]
    policy.reset(goal)
    assert policy.iterations_done == []


def test_mean_update_is_weighted_average_and_lambda_zero_picks_best():
    seen = []

    def rollout(seqs):
        seen.append(seqs.astype(np.float64))
        return np.random.default_rng(len(seen)).uniform(0, 1, len(seqs))

    cfg = MPPIConfig(num_samples=8, horizon=3, iterations=1, temperature=0.3, normalize_costs=False,
                     control_penalty=0.0)
    mean0 = np.tile([0.5, 0.5, 0.1, 0.0], (3, 1))
    mean, info = MPPI(cfg, rollout, np.random.default_rng(1)).plan(mean0)
    samples, costs = seen[0], info["iterations"][0]["costs"]
    np.testing.assert_allclose(samples[0], mean0, atol=1e-6)  # include_mean: sample 0 is unperturbed
    w = np.exp(-(costs - costs.min()) / 0.3)
    np.testing.assert_allclose(mean, np.einsum("k,khd->hd", w / w.sum(), samples), atol=1e-6)
    seen.clear()
    cfg.temperature = 1e-8
    mean, info = MPPI(cfg, rollout, np.random.default_rng(1)).plan(mean0)
    k = int(np.argmin(info["iterations"][0]["costs"]))
    np.testing.assert_allclose(mean, seen[0][k], atol=1e-6)
    np.testing.assert_allclose(info["best_sequence"], seen[0][k], atol=1e-6)


def test_frozen_dims_bounds_and_control_cost():
    target = np.array([[0.5, 0.5, 0.0, 0.4]])  # prefers a tilt that is not sampled
    cfg = MPPIConfig(num_samples=16, horizon=1, iterations=3, sampled_dims=["x", "y"], xy_bounds=[0.45, 0.55])
    seen = []

    def rollout(seqs):
        seen.append(seqs)
        return quadratic(target, 0.1)(seqs)

    mppi = MPPI(cfg, rollout, np.random.default_rng(0))
    mean, _ = mppi.plan(np.array([[0.5, 0.5, 0.2, 0.0]]))
    allseq = np.concatenate(seen)
    assert np.all(allseq[..., 2] == np.float32(0.2)) and np.all(allseq[..., 3] == 0.0)  # yaw, tilt frozen
    assert allseq[..., :2].min() >= 0.45 and allseq[..., :2].max() <= 0.55
    eps = np.zeros((2, 1, 4))
    eps[1, 0] = [0.02, -0.01, 5.0, 5.0]  # yaw/tilt are not sampled: no penalty for them
    expected = cfg.control_penalty * ((0.02 / 0.01) ** 2 + (0.01 / 0.01) ** 2)
    np.testing.assert_allclose(mppi.control_cost(eps), [0.0, expected])


def test_shift_and_config_errors():
    m = np.arange(12, dtype=float).reshape(3, 4)
    np.testing.assert_array_equal(shift(m), np.stack([m[1], m[2], m[2]]))
    np.testing.assert_array_equal(shift(m, np.full(4, -1.0)), np.stack([m[1], m[2], np.full(4, -1.0)]))
    with pytest.raises(ValueError, match="planner.sampled_dims.*'roll'.*x, y, yaw, tilt"):
        MPPIConfig(sampled_dims=["x", "roll"]).validate()
    with pytest.raises(ValueError, match="planner.execute"):
        MPPIConfig(execute="worst").validate()
    with pytest.raises(ValueError, match=r"shape \(H, 4\)"):
        MPPI(MPPIConfig(), lambda s: np.zeros(len(s))).plan(np.zeros(4))


def test_heuristic_policy_returns_planes_in_order():
    planes = [KnifeAction(0.4, 0.5), KnifeAction(0.5, 0.5), KnifeAction(0.6, 0.5, yaw=0.3)]
    pol = GoalPlanesPolicy(Goal(planes))
    assert [pol.act({}) for _ in range(4)] == planes + [planes[-1]]
    np.testing.assert_allclose(pol.sequence(1, 3), [p.to_vector() for p in (planes[1], planes[2], planes[2])])
    pol.reset(Goal(planes[:1]))
    assert pol.act({}) == planes[0]
    with pytest.raises(ValueError, match="goal.planes"):
        GoalPlanesPolicy(Goal([]))


def test_mppi_policy_improves_on_heuristic_and_shifts():
    planes = [KnifeAction(0.40, 0.5), KnifeAction(0.50, 0.5), KnifeAction(0.60, 0.5)]
    optimum = np.array([0.43, 0.52])  # the true first cut is off the nominal plane (object moved)
    calls = []

    def factory(obs, goal):
        calls.append(obs["t"])
        return lambda seqs: np.sum((seqs[:, 0, :2] - optimum) ** 2, axis=1) / 1e-4

    cfg = MPPIConfig(num_samples=32, horizon=2, iterations=8, noise_sigma=[0.02, 0.02, 0.1, 0.1],
                     control_penalty=0.0, temperature=0.05)
    pol = MPPIPolicy(cfg, factory, seed=0, goal=Goal(planes))
    a0 = pol.act({"t": 0})
    assert np.hypot(a0.x - 0.43, a0.y - 0.52) < np.hypot(0.40 - 0.43, 0.5 - 0.52) / 3
    assert pol.last_info["best_cost"] < (0.03 ** 2 + 0.02 ** 2) / 1e-4  # better than the heuristic's cost
    # horizon shifted: the second slot is the heuristic's plane t + H - 1 = 2
    np.testing.assert_allclose(pol.mean[1], planes[2].to_vector(), atol=1e-6)
    # a rollout that punishes any deviation from the heuristic: execute="best" returns the heuristic's cut
    v0 = planes[0].to_vector()
    pol = MPPIPolicy(cfg, lambda obs, goal: lambda s: np.abs(s[:, 0] - v0).sum(axis=1), seed=1, goal=Goal(planes))
    np.testing.assert_allclose(pol.act({"t": 0}).to_vector(), v0, atol=1e-6)
    assert calls == [0]


def test_mppi_policy_reset_seed_makes_an_episode_independent_of_earlier_ones():
    planes = [KnifeAction(0.40, 0.5), KnifeAction(0.50, 0.5)]
    cfg = MPPIConfig(num_samples=8, horizon=2, iterations=2, noise_sigma=[0.02, 0.02, 0.1, 0.1],
                     control_penalty=0.0, temperature=0.05, execute="best")
    factory = lambda obs, goal: quadratic(np.array([0.43, 0.52, 1.0, 0.0]), 0.01)  # noqa: E731
    warm = MPPIPolicy(cfg, factory, seed=3)
    warm.reset(Goal(planes), seed=11)
    first = warm.act({}).to_vector()  # episode 11 consumes random numbers ...
    warm.reset(Goal(planes), seed=12)
    after = warm.act({}).to_vector()  # ... episode 12 must not see that
    fresh = MPPIPolicy(cfg, factory, seed=3)
    fresh.reset(Goal(planes), seed=12)
    np.testing.assert_array_equal(after, fresh.act({}).to_vector())
    assert not np.array_equal(first, after)  # other episode seed, other samples
    # without an episode seed the policy keeps one stream across episodes (the planner's own seed)
    cont = MPPIPolicy(cfg, factory, seed=3)
    cont.reset(Goal(planes))
    cont.act({})
    cont.reset(Goal(planes))
    assert not np.array_equal(cont.act({}).to_vector(), after)


def test_sim_rollout_factory_pushes_per_goal_task(monkeypatch):
    import topocut.planning.rollout as rollout

    seen, succ = [], []
    monkeypatch.setattr(rollout, "make_sim_rollout",
                        lambda *a, push, success_fn, **k: seen.append(push) or succ.append(success_fn) or push)
    obs = {"sim_state": None, "particle_labels": None}
    factory = rollout.sim_rollout_factory(None, push={"slice": False, "dice": True},
                                          success={"slice": "slice's", "dice": "dice's"})
    for task in ("slice", "dice", "slice"):
        factory(obs, type("G", (), {"task": task})())
    assert seen == [False, True, False]
    assert succ == ["slice's", "dice's", "slice's"]  # the goal's task's success, as its push
    with pytest.raises(KeyError, match="no push setting for task 'stick'; known: slice, dice"):
        factory(obs, type("G", (), {"task": "stick"})())
    rollout.sim_rollout_factory(None, push=True)(obs, type("G", (), {"task": "slice"})())
    assert seen[-1] is True and succ[-1] is None  # no success given: the rollouts report none


def test_planner_push_last_reaches_the_rollouts_of_demonstrations_and_evaluation(monkeypatch):
    """planner.push_last goes from the config to make_sim_rollout through both builders of MPPI's rollouts: the
    demonstrations' stage (pipelines/mppi.py) and the evaluation's MPPI policy (topocut.policies.scripted)."""
    import topocut.planning as planning
    import topocut.planning.rollout as rollout
    from topocut.planning import MPPIConfig
    from topocut.policies import scripted

    seen, succ = [], []
    monkeypatch.setattr(rollout, "make_sim_rollout",
                        lambda *a, push_last, success_fn, **k: seen.append(push_last) or succ.append(success_fn))
    obs = {"sim_state": None, "particle_labels": None}
    for value in (True, False):
        setup = scripted.ScriptedSetup(env=None, task_cfgs={"dice": type("T", (), {"push": True})()},
                                       planner=MPPIConfig(push_last=value))
        scripted.mppi(setup).rollout_factory(obs, type("G", (), {"task": "dice"})())
    no_planner = scripted.ScriptedSetup(task_cfgs={"dice": type("T", (), {"push": True})()})  # the planner's defaults
    scripted.mppi(no_planner).rollout_factory(obs, type("G", (), {"task": "dice"})())
    assert seen == [True, False, MPPIConfig().push_last]
    # the evaluation's rollouts report the task's own success (stop_at_success): dice's rule with its config
    from topocut.tasks import get_task

    assert all(f.func == get_task("dice").success and f.keywords["cfg"] is not None for f in succ)
    src = (Path(planning.__file__).parents[2] / "pipelines" / "mppi.py").read_text()
    assert "push_last=planner.push_last" in src  # the stage passes the planner's key (the stage itself: test_stages)
    assert "success=success" in src  # and the task's success (the stage's episode log: test_stages)


# ---- the simulator rollout: needs topocut.sim, topocut.topology, topocut.reward, topocut.tasks -----------

def _sim_modules():
    try:
        from topocut.reward import spectral_reward  # noqa: F401
        from topocut.sim.config import SimConfig
        from topocut.sim.env import CuttingEnv
        from topocut.sim.objects import ObjectPose
        from topocut.tasks import make_goal, task_config
        from topocut.topology import discover  # noqa: F401
    except ImportError as e:
        pytest.skip(f"simulator/topology/reward/goals not importable yet: {e}")
    return CuttingEnv, SimConfig, ObjectPose, make_goal, task_config


def _small_sim_cfg(SimConfig, batch_size):
    cfg = SimConfig()
    for k, v in {"n_grid": 32, "batch_size": batch_size, "arch": "cpu"}.items():
        if hasattr(cfg, k):
            setattr(cfg, k, v)
    return cfg


def _cube_slice(batch_size):
    """(env of batch_size scenes holding the cube at the nominal pose, its slice goal, scene 0's state)."""
    CuttingEnv, SimConfig, ObjectPose, make_goal, task_config = _sim_modules()
    pose = ObjectPose()
    sim = _small_sim_cfg(SimConfig, batch_size)
    goal = make_goal(task_config("slice"), "cube", pose, sim.spacing)
    env = CuttingEnv(sim, batch_size=batch_size)
    env.reset("cube", pose, seed=0)
    return env, goal, env.get_state(0)


def test_sim_rollout_batched_matches_sequential_and_restores_state():
    CuttingEnv, SimConfig, ObjectPose, make_goal, task_config = _sim_modules()
    from topocut.planning.rollout import make_sim_rollout

    pose = ObjectPose()
    sim1 = _small_sim_cfg(SimConfig, 1)
    goal = make_goal(task_config("slice"), "cube", pose, getattr(sim1, "spacing", 0.01))
    env1 = CuttingEnv(sim1, batch_size=1)
    env1.reset("cube", pose, seed=0)
    state = env1.get_state(0)
    seqs = np.array([[goal.planes[0].to_vector()], [[0.95, 0.5, 0.0, 0.0]], [[0.5, 0.5, 0.0, 0.0]]], np.float32)
    costs1 = make_sim_rollout(env1, state, goal, board_z=sim1.board_z)(seqs)  # K=3, H=1, sequential
    assert np.isfinite(costs1).all()
    assert costs1[0] < costs1[1]  # the goal's own plane beats a cut that misses the object (x = 0.95)
    env2 = CuttingEnv(_small_sim_cfg(SimConfig, 2), batch_size=2)
    env2.reset("cube", pose, seed=0)
    # batched, with a success rule: each sequence's success is reported beside the same costs
    bar = -0.5 * (costs1[0] + costs1[1])  # between the goal plane's reward and the miss's
    rollout2 = make_sim_rollout(env2, state, goal, board_z=sim1.board_z, success_fn=lambda r: r.total >= bar)
    costs2, ok = rollout2(seqs)  # chunks of 2 (+1 padded)
    # CPU atomics add in a thread-dependent order, so batched and sequential runs agree to float noise
    np.testing.assert_allclose(costs2, costs1, rtol=2e-3, atol=1e-4)
    np.testing.assert_allclose(rollout2(seqs)[0], costs2, rtol=2e-3, atol=1e-4)  # state restored before every chunk
    np.testing.assert_array_equal(ok, -costs2 >= bar)
    assert ok[0] and not ok[1]


def test_a_rollout_pushes_after_each_cut_but_the_horizons_last_unless_push_last(monkeypatch):
    """A pushing task's rollout of horizon 2 pushes once (between its cuts) by default, twice with push_last, never
    when the task does not push; the push after the last cut is the one planner.push_last names."""
    CuttingEnv, SimConfig, ObjectPose, make_goal, task_config = _sim_modules()
    from topocut.planning.rollout import make_sim_rollout

    quick = dict(n_grid=32, arch="cpu", cut_substeps=40, dwell_time=0.0005, push_time=0.002, settle_time=0.002)
    env = CuttingEnv(SimConfig(**quick), batch_size=2)
    env.reset("cube", ObjectPose(), seed=0)
    goal = make_goal(task_config("slice"), "cube", ObjectPose(), env.cfg.spacing)  # no turns between the cuts
    state, pushes = env.get_state(0), []
    push = env.push
    monkeypatch.setattr(env, "push", lambda *a, **k: pushes.append(1) or push(*a, **k))
    seqs = np.array([[[0.45, 0.5, 0.0, 0.0], [0.55, 0.5, 0.0, 0.0]]] * 2, np.float32)  # K=2 (one chunk), H=2
    for kw, expected in (({"push": True}, 1), ({"push": True, "push_last": True}, 2),
                         ({"push": False, "push_last": True}, 0)):
        pushes.clear()
        costs = make_sim_rollout(env, state, goal, board_z=env.cfg.board_z, **kw)(seqs)
        assert len(pushes) == expected, kw
        assert np.isfinite(costs).all()


def test_rollout_discovers_topology_where_the_simulator_runs():
    from types import SimpleNamespace

    from topocut.planning.rollout import topology_device

    assert topology_device(SimpleNamespace(cfg=SimpleNamespace(arch="cuda"))) == "cuda"
    assert topology_device(SimpleNamespace(cfg=SimpleNamespace(arch="cpu"))) == "cpu"
    assert topology_device(object()) == "cpu"  # a stand-in env without a config (tests' fakes)


def test_plane_scorer_matches_the_rollout_and_survives_divergence(monkeypatch):
    """The pyramid experiment's batched scorer: its rewards equal make_sim_rollout's (same cuts, one distance
    matrix scored under two R(d) tails), the softer tail never scores lower, and a diverging chunk costs
    +inf instead of ending the search."""
    import dataclasses

    from experiments.plane_scoring import PlaneScorer
    from topocut.planning.rollout import make_sim_rollout
    from topocut.reward import RewardConfig
    from topocut.sim import SimulationDiverged

    env, goal, state = _cube_slice(2)
    seqs = np.array([[goal.planes[0].to_vector()], [[0.95, 0.5, 0.0, 0.0]], [[0.5, 0.5, 0.0, 0.0]]], np.float32)
    cfg = RewardConfig()
    costs = make_sim_rollout(env, state, goal, reward_cfg=cfg, board_z=env.cfg.board_z)(seqs)
    scorer = PlaneScorer(env, state, goal, cfg, dataclasses.replace(cfg, delta=1.1), None)
    res = scorer.run(seqs[:, 0])
    np.testing.assert_allclose([r["reward"] for r in res], -costs, atol=1e-9)
    assert all(r["cost_reward"] >= r["reward"] for r in res) and res[0]["reward"] > res[1]["reward"]

    def diverge(*a, **k):
        raise SimulationDiverged(3, 1)

    monkeypatch.setattr(env, "cut", diverge)
    assert np.isinf(scorer.rollout(seqs)).all()


# ---- review fixes: executed = evaluated plane, the stage's tilt bound, goal board height, episode log, seeds ----

def test_mppi_policy_executes_exactly_the_float32_plane_its_rollouts_evaluated():
    from topocut.planning.rollout import _as_actions

    # plane 0 at yaw = pi/2 exactly: float32(pi/2) > pi/2, so the rollout ran the canonical yaw ~ -pi/2
    planes = [KnifeAction(0.43, 0.5, np.pi / 2), KnifeAction(0.47, 0.5, 1.2)]
    for best in (0, 1):  # 0: the unperturbed mean (include_mean); 1: a perturbed float64 sample
        seen = []

        def factory(obs, goal, seen=seen, best=best):
            def rollout(seqs):
                seen.append(seqs.copy())
                return np.where(np.arange(len(seqs)) == best, -1.0, 0.0)
            return rollout

        pol = MPPIPolicy(MPPIConfig(num_samples=4, iterations=1), factory, seed=0, goal=Goal(planes))
        a = pol.act({})
        evaluated = seen[0][best, 0]
        assert seen[0].dtype == np.float32
        ran = _as_actions(np.asarray(seen[0], np.float64)[:, 0])[best]  # as make_sim_rollout turns it into a cut
        assert a == ran  # every field bit-for-bit, not the float64 sample ~1e-8 away
        np.testing.assert_array_equal(a.to_vector(), ran.to_vector())
        if best == 1:
            np.testing.assert_array_equal(a.to_vector(), evaluated)
        else:  # the wrapped yaw: same plane as float32(pi/2), normal reversed to the canonical side
            assert float(evaluated[2]) > np.pi / 2 and -np.pi / 2 < a.yaw < -np.pi / 2 + 1e-6
            np.testing.assert_allclose(a.normal, [0, -1, 0], atol=1e-6)


def _compose(*overrides):
    from hydra import compose, initialize_config_dir

    from topocut.config import register_configs, to_dataclass

    register_configs()
    conf = str(__import__("pathlib").Path(__file__).resolve().parents[1] / "conf")
    with initialize_config_dir(config_dir=conf, version_base="1.3"):
        cfg = compose(config_name="config", overrides=["stage=mppi", "logger=none", *overrides])
    return {k: to_dataclass(cfg[k]) for k in ("sim", "object", "task", "planner")}


def test_mppi_stage_planner_covers_the_pyramid_goal_tilt():
    from pipelines.mppi import episode_scene, planner_for_task

    cfg = _compose("task=pyramid", "object=cube", "object.randomize_pose=false")
    task, planner = cfg["task"], cfg["planner"]
    stage_planner = planner_for_task(planner, task)
    _, goal = episode_scene(cfg["object"], task, cfg["sim"], 0, stage_planner)
    tilt = goal.planes[0].tilt
    assert tilt == pytest.approx(np.arcsin(1 / np.sqrt(3)), abs=2e-3)  # corner face normal (1,1,1)/sqrt(3): 35.26 deg
    assert planner.tilt_max < tilt <= stage_planner.tilt_max and "tilt" in stage_planner.sampled_dims
    start = GoalPlanesPolicy(goal).sequence(0, 1)
    assert MPPI(stage_planner, lambda s: np.zeros(len(s))).clip(start)[0, 3] == start[0, 3]  # not clipped
    with pytest.raises(ValueError, match=r"tilt up to 0\.61.*planner\.tilt_max=0\.6"):
        episode_scene(cfg["object"], task, cfg["sim"], 0, planner)  # the bound the stage used to plan with
    assert planner_for_task(planner, _compose("task=slice")["task"]) is planner


def test_mppi_stage_goal_sits_on_the_configured_board():
    from pipelines.mppi import episode_scene

    for board_z in (0.05, 0.12):
        cfg = _compose("task=slice", "object=cube", "object.randomize_pose=false", "sim.n_grid=32",
                       f"sim.board_z={board_z}")
        _, goal = episode_scene(cfg["object"], cfg["task"], cfg["sim"], 0)
        z0 = goal.points[:, 2].min()
        assert board_z <= z0 <= board_z + cfg["sim"].spacing  # the object rests on the board, as env.reset puts it


def test_mppi_episode_log_drops_a_torn_last_line_and_names_a_corrupt_one(tmp_path):
    import json

    from topocut.data.collection import read_records

    log = tmp_path / "episodes.jsonl"
    ep0, ep1, ep2 = ({"episode": e, "final_reward": r} for e, r in ((0, 0.9), (1, 0.8), (2, 0.7)))
    log.write_text(json.dumps(ep0) + "\n" + '{"episode": 1, "final_rew')  # killed while logging episode 1
    assert read_records(log) == [ep0]
    assert log.read_text().endswith("final_rew")  # reading alone leaves the file as it is
    assert read_records(log, repair=True) == [ep0]  # what the stage does before running episodes
    assert log.read_text() == json.dumps(ep0) + "\n"
    with open(log, "a") as f:  # the resumed run logs episodes 1 (again) and 2
        f.write(json.dumps(ep1) + "\n" + json.dumps(ep2) + "\n")
    assert read_records(log) == [ep0, ep1, ep2]
    log.write_text(json.dumps(ep0) + "\n" + '{"episode": 1, "final_rew' + "\n" + json.dumps(ep2) + "\n")
    with pytest.raises(ValueError, match=rf"{__import__('re').escape(str(log))}, line 2: not an episode record"):
        read_records(log, repair=True)
    assert "final_rew\n" in log.read_text()  # nothing dropped from a log that is corrupt in the middle


def test_mppi_episode_seeds_never_collide():
    from topocut.episode import demo_episode_seed as episode_seed

    assert episode_seed(0, 1000) != episode_seed(1, 0)
    seeds = [episode_seed(s, e) for s in range(5) for e in range(3000)]
    assert len(set(seeds)) == len(seeds) and 0 <= min(seeds) and max(seeds) < 2**31
    assert episode_seed(7, 2) == 7 * 1_000_003 + 2  # mix_seed, as the MPPI policy mixes its own seed

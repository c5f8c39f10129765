"""The one policy catalogue: every scripted policy is built through the registry from its spec's builder."""
from types import SimpleNamespace

import pytest

from topocut.policies import registry
from topocut.policies.scripted import ScriptedSetup


def test_every_scripted_spec_names_a_builder_that_exists():
    import importlib

    for name in registry.scripted():
        module, _, func = registry.get(name).builder.partition(":")
        assert callable(getattr(importlib.import_module(module), func)), name


def test_the_oracle_and_the_heuristic_are_built_from_the_setup():
    from topocut.planning.heuristic import HeuristicPolicy
    from topocut.planning.oracle import OraclePolicy
    from topocut.tasks import task_config

    setup = ScriptedSetup(sim=SimpleNamespace(board_z=0.07, spacing=0.01), task_cfgs={"slice": task_config("slice")})
    oracle = registry.build_scripted("oracle", setup)
    assert isinstance(oracle, OraclePolicy) and oracle.board_z == pytest.approx(0.07)
    heuristic = registry.build_scripted("heuristic", setup)
    assert isinstance(heuristic, HeuristicPolicy)
    assert (heuristic.spacing, heuristic.board_z, set(heuristic.task_cfgs)) == (0.01, 0.07, {"slice"})


def test_a_learned_policy_is_not_built_as_scripted():
    with pytest.raises(ValueError, match="learned"):
        registry.build_scripted("pddp", ScriptedSetup())


def test_the_heuristics_nominal_goal_is_made_once_for_every_copy_of_the_policy(monkeypatch):
    """The episode engine resets a copy of the policy per scene of a batch (``_slot_policy``): the goal at the nominal
    pose is made once per (task config, object) for all of them, and each copy cuts that goal's planes."""
    from topocut.episode.run import _slot_policy
    from topocut.planning import heuristic as h
    from topocut.sim.objects import ObjectPose
    from topocut.tasks import make_goal, task_config

    h._NOMINAL.clear()
    calls = []

    def counted(*a, **k):
        calls.append(a[1])
        return make_goal(*a, **k)

    monkeypatch.setattr("topocut.tasks.make_goal", counted)
    cfg = task_config("slice", max_cuts=3, thickness=0.05)
    policy = h.HeuristicPolicy({"slice": cfg}, spacing=0.0125)
    episode_goal = SimpleNamespace(task="slice", object="cube")
    copies = [_slot_policy(policy) for _ in range(3)]
    for c in copies:
        c.reset(episode_goal)
    _slot_policy(policy).reset(SimpleNamespace(task="slice", object="cake"))
    assert calls == ["cube", "cake"]
    nominal = make_goal(cfg, "cube", ObjectPose(), spacing=0.0125, board_z=0.05)
    want = [p.to_vector() for p in nominal.planes]
    for c in copies:
        assert [c.act().to_vector().tolist() for _ in want] == [w.tolist() for w in want]

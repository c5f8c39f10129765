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

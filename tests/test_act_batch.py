"""act_batch (one network batch for B episodes) equals act() per episode: actions, last_mask, generator states."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from topocut.policies import PDDPConfig, PolicyTrainConfig, make_obs
from topocut.policies.baselines.module import PoseDiffusionModule, PosePolicy
from topocut.policies.diffusion import rng
from topocut.policies.module import PDDPModule, PDDPPolicy

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py

TINY = dict(n_blocks=2, hidden=32, obs_dim=32, n_heads=2, cond_dim=32, time_freq_dim=32, goal_hidden=16, dropout=0.0)
NUM_POINTS = 64
COUNTS = (40, 64, 150)  # fewer points than the network sees (padding), exactly as many, more (FPS + spread back)
SEEDS = (5, 17, 123)


class Goal:
    def __init__(self, points, labels):
        self.points, self.labels = points, labels


def _box(rng_, n, c):
    lo, hi = np.array([c[0] - 0.1, c[1] - 0.1, 0.05]), np.array([c[0] + 0.1, c[1] + 0.1, 0.15])
    return rng_.uniform(lo, hi, (n, 3)).astype(np.float32)


def _episodes(step: int = 0):
    """One (goal, observation) per episode: different goals, centres and point counts."""
    out = []
    for b, n in enumerate(COUNTS):
        r = np.random.default_rng(100 * b + step)
        c = (0.45 + 0.05 * b, 0.5)
        g = _box(np.random.default_rng(b), 32, c)
        goal = Goal(g, (g[:, 0] > c[0]).astype(np.int32))
        hist = np.zeros((3, 7), np.float32)
        hist[-1, :4] = step * 0.1  # a cut before the second step
        obs = make_obs(_box(r, n, c), r.integers(0, 3, n), goal.points, goal.labels, history=hist)
        out.append((goal, obs))
    return out


def _states(policies):
    return [p.generator.get_state() for p in policies]


def test_per_row_draws_equal_batch_one_draws():
    gens = [torch.Generator().manual_seed(s) for s in SEEDS]
    ref = [torch.Generator().manual_seed(s) for s in SEEDS]
    x = rng.rand((3, 5, 2), gens)
    for b, g in enumerate(ref):
        torch.testing.assert_close(x[b:b + 1], torch.rand((1, 5, 2), generator=g), rtol=0, atol=0)
    assert all(torch.equal(a.get_state(), b.get_state()) for a, b in zip(gens, ref))
    with pytest.raises(ValueError, match="one per row"):
        rng.randn((2, 4), gens)


@pytest.mark.parametrize("graph,predictor", [("uniform", "analytic"), ("absorbing", "euler")])
def test_pddp_act_batch_equals_act(graph, predictor, monkeypatch):
    import topocut.policies.deploy as pm

    torch.manual_seed(0)
    module = PDDPModule(PDDPConfig(graph=graph, **TINY), "none",
                        train=PolicyTrainConfig(num_points=NUM_POINTS, num_goal_points=16))
    # reject two masks in three (by their size): each episode then retries a mask-dependent number of times and
    # may end with None, so the retries must follow each episode's own generator
    real, calls = pm.action_from_mask, []

    def mostly_rejected(points, mask, *a, **kw):
        calls.append(1)
        return None if int(mask.sum()) % 3 else real(points, mask, *a, **kw)

    monkeypatch.setattr(pm, "action_from_mask", mostly_rejected)

    def make():
        pols = [PDDPPolicy(module, sampler=predictor, steps=4, seed=1, retries=3) for _ in COUNTS]
        for p, (goal, _), s in zip(pols, _episodes(), SEEDS):
            p.reset(goal, seed=s)
        return pols

    one, many = make(), make()
    tries, nones = 0, 0
    for step in range(3):  # the later calls check that the generators advanced identically
        obs = [o for _, o in _episodes(step)]
        calls.clear()
        expect = [p.act(o) for p, o in zip(one, obs)]
        n_single = len(calls)
        calls.clear()
        got = PDDPPolicy.act_batch(many, obs)
        assert len(calls) == n_single  # the same tries
        tries += n_single
        nones += sum(e is None for e in expect)
        for e, g, p, q in zip(expect, got, one, many):
            assert (e is None) == (g is None)
            if e is not None:
                np.testing.assert_allclose(g.to_vector(), e.to_vector(), atol=1e-5)
            np.testing.assert_array_equal(q.last_mask, p.last_mask)
            assert q.last_mask.shape == (len(p.last_mask),)
        assert all(torch.equal(a, b) for a, b in zip(_states(one), _states(many)))
    assert tries > 3 * len(COUNTS) and 0 < nones < 3 * len(COUNTS)  # some episodes retried, some gave up
    assert [p.last_mask.shape[0] for p in many] == list(COUNTS)


def _pose_module(kind):
    torch.manual_seed(0)
    small = {"dp3": dict(enc_dim=32, down_dims=(32, 64, 128), horizon=4),
             "3dda": dict(dim=48, heads=2, layers=1, context_layers=1)}[kind]
    return PoseDiffusionModule(kind=kind, num_points=NUM_POINTS, num_goal_points=NUM_POINTS, num_train_steps=20,
                               **small)


@pytest.mark.parametrize("kind", ["dp3", "3dda"])
def test_pose_act_batch_equals_act(kind):
    module = _pose_module(kind)

    def make():
        pols = [PosePolicy(module, seed=2) for _ in COUNTS]
        for p, (goal, _), s in zip(pols, _episodes(), SEEDS):
            p.reset(goal, seed=s)
        return pols

    one, many = make(), make()
    for step in range(2):
        obs = [o for _, o in _episodes(step)]
        expect = [p.act(o) for p, o in zip(one, obs)]
        got = PosePolicy.act_batch(many, obs)
        for e, g in zip(expect, got):
            np.testing.assert_allclose(g.to_vector(), e.to_vector(), atol=1e-5)
        assert all(torch.equal(a, b) for a, b in zip(_states(one), _states(many)))
    assert len({tuple(np.round(a.to_vector(), 6)) for a in got}) == len(COUNTS)  # the episodes did not share noise


def test_act_batch_edge_cases():
    assert PDDPPolicy.act_batch([], []) == [] and PosePolicy.act_batch([], []) == []
    module = _pose_module("dp3")
    with pytest.raises(ValueError, match="observations"):
        PosePolicy.act_batch([PosePolicy(module)], [])
    with pytest.raises(RuntimeError, match="reset"):
        PosePolicy.act_batch([PosePolicy(module)], [_episodes()[0][1]])

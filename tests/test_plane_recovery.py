"""PDDP's plane from its mask in the demonstrations' action space (docs/policy.md, "The plane from the mask"):
vertical fits, and ``policy.sampler.tilt`` following the cuts a checkpoint trained on."""
import math

import numpy as np
import pytest
import torch

from experiments.plane_recovery import angle_deg, cut_states
from topocut.policies import PDDPConfig, PolicyTrainConfig, fit_plane, make_obs
from topocut.policies.base import history_from_actions
from topocut.policies.config import SamplerConfig
from topocut.policies.module import PDDPModule, PDDPPolicy
from topocut.sim.action import KnifeAction, cut_mask

TINY = dict(n_blocks=1, hidden=16, obs_dim=16, n_heads=2, cond_dim=16, time_freq_dim=16, goal_hidden=8, dropout=0.0)


@pytest.mark.parametrize("method", ["svm", "lsq"])
def test_a_vertical_fit_is_vertical_and_recovers_vertical_cuts(method):
    """Random vertical cuts of random boxes: the fitted normal has no z at all, lies within 2 degrees of the cut's
    and puts the points on the mask's sides."""
    rng = np.random.default_rng(4)
    for _ in range(8):
        a = KnifeAction(rng.uniform(0.45, 0.55), rng.uniform(0.45, 0.55), rng.uniform(-np.pi / 2, np.pi / 2), 0.0)
        pts = rng.uniform([0.35, 0.35, 0.05], [0.65, 0.65, 0.25], (1024, 3))
        mask = cut_mask(pts, a)
        n, p = fit_plane(pts, mask, method, vertical=True)
        assert n[2] == 0.0 and abs(np.linalg.norm(n) - 1.0) < 1e-9
        assert angle_deg(n, a) < 2.0
        assert (((pts - p) @ n > 0) == mask.astype(bool)).mean() > 0.98


def test_vertical_fits_recover_the_dice_plans_later_cuts_where_free_ones_turn():
    """The dice plans' own cuts and their exact masks (no learning): after the turn a cut's two sides touch along a
    short boundary, and the free max-margin plane turns several degrees from the cut that made the mask; the
    vertical fit, in the demonstrations' action space (every planned cut has tilt 0), stays within a few."""
    rng = np.random.default_rng(0)
    free, vertical = [], []
    for obj, seed in (("cake", 0), ("cube", 1)):
        for x, action, k in cut_states("dice", obj, float(rng.uniform(-0.5, 0.5)), seed):
            assert abs(action.tilt) < 1e-9  # the plan cuts vertically (to rounding)
            p = x[rng.choice(len(x), min(2048, len(x)), replace=False)]
            mask = cut_mask(p, action)
            if k == 0 or min(mask.sum(), len(mask) - mask.sum()) < 3:
                continue
            free.append(angle_deg(fit_plane(p, mask, "svm")[0], action))
            vertical.append(angle_deg(fit_plane(p, mask, "svm", vertical=True)[0], action))
    assert len(vertical) >= 6
    assert max(vertical) < 6.0, vertical
    assert np.mean(free) > 2.0 * np.mean(vertical), (free, vertical)


def _steps(tilt: float, n: int = 4):
    return [{"action": KnifeAction(0.5, 0.5, 0.3 * i, tilt).to_vector()} for i in range(n)]


def test_tilt_auto_follows_the_cuts_the_policy_trained_on(tmp_path):
    """set_demo_tilt records the largest |tilt| of the training cuts; "auto" fits vertical planes only when every one
    was vertical; "zero" / "free" say so whatever it trained on; the record travels in the checkpoint, and a
    checkpoint without it (trained before it) keeps free planes under "auto"."""
    import lightning

    module = PDDPModule(PDDPConfig(**TINY), "none", train=PolicyTrainConfig(num_points=16, num_goal_points=8))
    assert module.demo_max_tilt is None and not module.vertical_planes("auto")
    module.set_demo_tilt(_steps(0.0))
    assert module.demo_max_tilt == 0.0 and module.vertical_planes("auto") and not module.vertical_planes("free")
    module.set_demo_tilt(_steps(0.0) + _steps(-0.2, 1))
    assert math.isclose(module.demo_max_tilt, 0.2, abs_tol=1e-6) and not module.vertical_planes("auto")
    assert module.vertical_planes("zero")

    module.set_demo_tilt(_steps(0.0))
    ckpt = {"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams),
            "pytorch-lightning_version": lightning.__version__}
    module.on_save_checkpoint(ckpt)
    torch.save(ckpt, tmp_path / "new.ckpt")
    del ckpt["demo_max_tilt"]
    torch.save(ckpt, tmp_path / "old.ckpt")
    assert PDDPModule.load_from_checkpoint(str(tmp_path / "new.ckpt"), weights_only=True).vertical_planes("auto")
    assert not PDDPModule.load_from_checkpoint(str(tmp_path / "old.ckpt"), weights_only=True).vertical_planes("auto")


@pytest.mark.parametrize("demo_tilt,tilt,vertical", [(0.0, "auto", True), (0.3, "auto", False), (0.3, "zero", True),
                                                     (0.0, "free", False)])
def test_the_deployed_policy_fits_its_mask_as_sampler_tilt_says(demo_tilt, tilt, vertical):
    """PDDPPolicy.act with a sampler that returns the mask of a plane tilted 26.6 degrees: a vertical fit gives
    tilt 0 and the mask's yaw, a free fit the mask's tilt."""
    module = PDDPModule(PDDPConfig(**TINY), "none", train=PolicyTrainConfig(num_points=64, num_goal_points=8))
    module.set_demo_tilt(_steps(demo_tilt))
    n = np.array([1.0, 0.0, 0.5]) / math.sqrt(1.25)

    def tilted_mask(batch, **kw):  # B,N: the side of a tilted plane through each cloud's centre
        p = batch["points"].double()
        return (((p - p.mean(1, keepdim=True)) @ torch.as_tensor(n)) > 0).long()

    module.sample_masks = tilted_mask
    policy = PDDPPolicy(module, SamplerConfig(steps=2, tilt=tilt), seed=0)
    rng = np.random.default_rng(2)
    pts = rng.uniform([0.4, 0.4, 0.05], [0.6, 0.6, 0.2], (256, 3)).astype(np.float32)
    goal = pts[:8]
    policy.reset(type("Goal", (), {"points": goal, "labels": np.zeros(8, np.int32)})())
    a = policy.act(make_obs(pts, np.zeros(256, np.int32), policy.goal, policy.goal_labels,
                            history=history_from_actions([])))
    assert a is not None
    if vertical:
        assert abs(a.tilt) < 1e-12 and abs(abs(a.normal[0]) - 1.0) < 0.01
    else:
        assert abs(abs(math.degrees(a.tilt)) - math.degrees(math.atan(0.5))) < 4.0


def test_sampler_tilt_is_checked():
    with pytest.raises(ValueError, match="sampler.tilt"):
        SamplerConfig(tilt="sideways").validate()

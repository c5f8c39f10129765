"""Validation metrics of the Lightning modules: sample-weighted epoch means, DDP synchronisation, padded clouds."""
import numpy as np
import pytest
import torch

from topocut.models.config import DynamicsConfig
from topocut.models.datamodule import TransitionDataset
from topocut.models.losses import cluster_accuracy, dynamics_loss
from topocut.models.module import DynamicsModule
from topocut.utils.training import EpochMeans

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py

TINY = dict(num_points=16, hidden=16, k=4, cross_k=4, num_layers=1, num_heads=2, query_hidden=8, pointnet_dims=[16],
            pointnet_k=4, num_labels=8)
N = 8


def _capture(module) -> dict:
    logged = {}
    module.log = lambda name, value, **kw: logged.__setitem__(name, float(value))  # no Trainer needed
    return logged


def _batch(f_t1, seen) -> dict:
    """N points, one input cluster, the first half cut off (mask 1): the mask rule predicts ids 1 | 0."""
    B = len(f_t1)
    x = torch.arange(B * N * 3, dtype=torch.float32).reshape(B, N, 3) / 100
    mask = (torch.arange(N) < N // 2).long().expand(B, N)
    return {"x_t": x, "f_t": torch.zeros(B, N, dtype=torch.long), "mask": mask, "x_t1": x.clone(),
            "f_t1": torch.stack(f_t1), "seen": torch.tensor(seen)}


SPLIT = (torch.arange(N) < N // 2).long()  # the truth is the mask's split: rule accuracy 1
WHOLE = torch.zeros(N, dtype=torch.long)  # nothing separated: rule accuracy 1/2
NONE = torch.full((N,), -1)  # no labelled point: no accuracy (NaN), must not count


def _no_model(module):
    """forward -> (x_t1, uniform logits): the tests read the model-free mask rule and the loss bookkeeping."""
    module.forward = lambda b: (b["x_t1"].clone(), torch.zeros(*b["x_t"].shape[:2], module.cfg.num_labels))


def test_epoch_means_weight_samples_not_batches():
    m = EpochMeans(("a", "b", "never"))
    m.update("a", torch.tensor([1.0, 0.0, 1.0]))  # batch of 3 samples
    m.update("a", torch.tensor([0.0, float("nan")]))  # 2 samples, one without a value
    m.update("b", torch.tensor(0.3), weight=3)  # batch means with batch sizes
    m.update("b", torch.tensor(0.9), weight=1)
    m.update("never", torch.empty(0))
    out = m.compute()
    assert set(out) == {"a", "b"}  # no sample, no value (not a NaN)
    assert float(out["a"]) == pytest.approx(2 / 4)  # mean of batch means: (2/3 + 0) / 2 = 1/3
    assert float(out["b"]) == pytest.approx((3 * 0.3 + 0.9) / 4)  # 0.45; unweighted: 0.6
    m.update("a", torch.tensor([1.0]))
    m.update("b", torch.empty(0))
    assert {k: float(v) for k, v in m.compute().items()} == {"a": 1.0}  # reset: a new epoch starts from nothing


def test_validation_epoch_value_is_the_mean_over_samples_of_unequal_batches(tmp_path):
    import lightning as L
    from torch.utils.data import DataLoader

    module = DynamicsModule(DynamicsConfig(**TINY))
    _no_model(module)
    batches = [_batch([SPLIT, NONE], [True, False]), _batch([WHOLE], [False])]
    trainer = L.Trainer(accelerator="cpu", logger=False, enable_progress_bar=False, enable_model_summary=False,
                        default_root_dir=tmp_path)
    trainer.validate(module, DataLoader(batches, batch_size=None), verbose=False)
    m = {k: float(v) for k, v in trainer.callback_metrics.items()}
    # samples with a value: 1 and 1/2 -> 0.75 (a NaN-mean per batch weighted by its size would give (2*1 + 1/2)/3)
    assert m["val/mask_rule_acc"] == pytest.approx(0.75)
    assert m["val/mask_rule_acc_seen"] == pytest.approx(1.0) and m["val/mask_rule_acc_unseen"] == pytest.approx(0.5)
    assert m["val/chamfer"] == pytest.approx(0.0, abs=1e-9)


def test_validation_means_synchronise_across_ranks():
    """Two DDP ranks, simulated: rank 0's metrics gather rank 1's states as torch.distributed's all_gather would
    (torchmetrics' dist_sync_fn hook); the logged epoch value is the mean over both ranks' samples."""
    from torchmetrics import Metric

    ranks = [DynamicsModule(DynamicsConfig(**TINY)) for _ in range(2)]
    for module in ranks:
        _no_model(module)
    ranks[0].validation_step(_batch([SPLIT, SPLIT], [True, True]), 0)  # rank 0: seen only
    ranks[1].validation_step(_batch([WHOLE], [False]), 0)  # rank 1: one held-out sample
    for name, metric in ranks[0].val_means.means.items():
        assert isinstance(metric, Metric) and metric.sync_on_compute
        other = ranks[1].val_means.means[name]
        metric.distributed_available_fn = lambda: True
        metric.dist_sync_fn = lambda t, group=None, me=metric, o=other: [
            t, o.mean_value if t is me.mean_value else o.weight]
    logged = _capture(ranks[0])
    ranks[0].on_validation_epoch_end()
    assert logged["val/mask_rule_acc"] == pytest.approx((1 + 1 + 0.5) / 3)  # rank 0 alone: 1
    assert logged["val/mask_rule_acc_unseen"] == pytest.approx(0.5)  # only rank 1 saw an unseen sample
    assert logged["val/mask_rule_acc_seen"] == pytest.approx(1.0)


def test_policy_modules_use_synchronised_epoch_means():
    from topocut.policies import PDDPConfig, PolicyTrainConfig
    from topocut.policies.baselines.module import PoseDiffusionModule
    from topocut.policies.module import PDDPModule

    pddp = PDDPModule(PDDPConfig(n_blocks=1, hidden=16, obs_dim=16, n_heads=2, cond_dim=16, time_freq_dim=16,
                                 goal_hidden=8), "none", train=PolicyTrainConfig(num_points=4, num_goal_points=4))
    pddp.loss = lambda batch, model=None: torch.tensor(0.5)
    pddp.sample_masks = lambda batch, steps=0: torch.tensor([[1, 1, 1, 1]] * (len(batch["mask"]) - 1) + [[0, 0, 0, 0]])
    logged = _capture(pddp)
    for B in (3, 1):  # batches of 3 and 1 samples; the last sample of each gets every point wrong
        prev = torch.tensor([[1, 1, 0, 0]] * B) if B == 3 else torch.ones(B, 4, dtype=torch.long)
        pddp.validation_step({"mask": torch.ones(B, 4, dtype=torch.long), "prev_mask": prev}, 0)
    pddp.on_validation_epoch_end()
    assert logged == {"val/loss": pytest.approx(0.5), "val/mask_acc": pytest.approx(2 / 4),  # 2 of 4 samples right
                      "val/mask_acc_majority": pytest.approx(1.0),  # every target all ones: a constant 1 is right
                      "val/mask_acc_prev_plane": pytest.approx((3 * 0.5 + 1) / 4)}  # the floors beside it

    pose = PoseDiffusionModule(kind="dp3", enc_dim=8, down_dims=(8, 16), horizon=2)
    errs = iter([torch.tensor([[0.0] * 6, [0.0] * 6, [2.0, 0, 1, 0, 0, 0]]), torch.tensor([[0.0, 1, 1, 0, 0, 0]])])
    pose.compute_loss, pose.predict = (lambda batch: torch.tensor(1.0)), (lambda batch: next(errs))
    logged = _capture(pose)
    for B in (3, 1):
        pose.validation_step({"points": torch.zeros(B, 4, 3), "action": torch.tensor([[0.0, 0, 1, 0, 0, 0]] * B)}, 0)
    pose.on_validation_epoch_end()
    s = pose.hparams.pos_scale  # cut-point errors 0, 0, 2 s and 1 s over 4 samples
    assert logged["val/pose_err"] == pytest.approx(3 * s / 4) and logged["val/yaw_err"] == pytest.approx(0.0)
    assert logged["val/loss"] == pytest.approx(1.0)


# -- padded clouds --------------------------------------------------------------------------------------------

def _three_particles():
    x = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]], np.float32)
    return {"x_t": x, "f_t": np.zeros(3, int), "mask": np.zeros(3, int), "x_t1": x, "f_t1": np.array([0, 1, 1])}


def test_padding_rows_are_marked_and_left_out_of_losses_and_accuracy():
    """3 particles padded to 4 rows: particle 0 appears twice. Prediction: particle 0 off by 0.3 along x, its
    logits [1, 0] (class 0 = its true cluster after matching), particles 1, 2 with logits [0, 3].
    Over the 3 particles: CD = EMD = 0.3 / 3 = 0.1, HD = 0.3, CE = (log(1+e^-1) + 2 log(1+e^-3)) / 3;
    counting the copy would give CD = EMD = 0.6 / 4 = 0.15 and CE = (2 log(1+e^-1) + 2 log(1+e^-3)) / 4."""
    s = TransitionDataset([_three_particles()], num_points=4, sort=False, num_labels=2)[0]
    assert s["x_t"][:, 0].tolist() == [0.0, 1.0, 2.0, 0.0] and s["valid"].tolist() == [True, True, True, False]
    sorted_s = TransitionDataset([_three_particles()], num_points=4, sort=True)[0]
    assert sorted_s["x_t"][:, 0].tolist() == [0.0, 0.0, 1.0, 2.0] and int(sorted_s["valid"].sum()) == 3
    assert TransitionDataset([_three_particles()], num_points=3)[0]["valid"].all()

    b = {k: v[None] for k, v in s.items()}
    pred = b["x_t1"].clone()
    pred[..., 0] += torch.where(b["x_t1"][..., 0] == 0, 0.3, 0.0)
    logits = torch.where((b["x_t1"][..., 0] == 0)[..., None], torch.tensor([1.0, 0.0]), torch.tensor([0.0, 3.0]))
    cfg = DynamicsConfig(pos_scale=1.0, num_labels=2)
    got = dynamics_loss(pred, logits, b["x_t1"], b["f_t1"], cfg, b["valid"])
    ce = (np.log1p(np.exp(-1)) + 2 * np.log1p(np.exp(-3))) / 3
    assert float(got["chamfer"]) == pytest.approx(0.1, abs=1e-6) and float(got["emd"]) == pytest.approx(0.1, abs=1e-6)
    assert float(got["hausdorff"]) == pytest.approx(0.3, abs=1e-6) and float(got["loss_topo"]) == pytest.approx(ce)
    unique = dynamics_loss(pred[:, :3], logits[:, :3], b["x_t1"][:, :3], b["f_t1"][:, :3], cfg)
    for k in ("loss", "chamfer", "emd", "hausdorff", "loss_topo"):
        assert float(got[k]) == pytest.approx(float(unique[k]), abs=1e-6), k

    module = DynamicsModule(DynamicsConfig(**{**TINY, "num_points": 4, "num_labels": 2}))
    module.forward = lambda batch: (pred, torch.tensor([[[0.0, 1.0]] * 4]))  # every particle called cluster 1
    logged = _capture(module)
    module.validation_step(b, 0)
    module.on_validation_epoch_end()
    assert logged["val/cluster_acc"] == pytest.approx(2 / 3)  # particle 0 wrong once, not twice (2/4)
    assert logged["val/chamfer"] == pytest.approx(0.1, abs=1e-6)
    assert float(cluster_accuracy(torch.ones(1, 4, dtype=torch.long), b["f_t1"])[0]) == 0.5  # what the copy did


def test_cluster_accuracy_on_the_mask_rules_errors_and_the_error_reduction():
    """Two samples of N=8 points, one input cluster, the mask cuts off the first half (rule ids 1 | 0).
    Sample 1: truth = no separation (rule right on 4 of 8 after matching); the model says "one cluster": right on
    all 8, so on the rule's 4 wrong points it scores 4/4.  Sample 2: truth = the mask's split (rule right on 8 of
    8: no wrong point, no value); the model says "one cluster": 4 of 8.  Pooled over the rule's wrong points: 4/4.
    cluster_acc = (1 + 0.5) / 2 = 0.75, mask_rule_acc = (0.5 + 1) / 2 = 0.75: error reduction 1 - 0.25/0.25 = 0."""
    module = DynamicsModule(DynamicsConfig(**TINY))
    logits = torch.zeros(2, N, module.cfg.num_labels)
    logits[..., 0] = 1.0  # every point class 0
    module.forward = lambda b: (b["x_t1"].clone(), logits)
    logged = _capture(module)
    module.validation_step(_batch([WHOLE, SPLIT], [True, True]), 0)
    module.on_validation_epoch_end()
    assert logged["val/cluster_acc"] == pytest.approx(0.75) and logged["val/mask_rule_acc"] == pytest.approx(0.75)
    assert logged["val/cluster_acc_rule_wrong"] == pytest.approx(1.0)
    assert logged["val/cluster_acc_rule_wrong_seen"] == pytest.approx(1.0)
    assert "val/cluster_acc_rule_wrong_unseen" not in logged  # no unseen sample: no value, not a NaN
    assert logged["val/cluster_err_reduction"] == pytest.approx(0.0)
    from topocut.models.losses import error_reduction, matched_correct

    assert error_reduction(0.96, 0.92) == pytest.approx(0.5) and error_reduction(0.9, 1.0) is None
    ok = matched_correct(torch.tensor([[0, 0, 1, 1, 2]]), torch.tensor([[5, 5, 5, 7, -1]]))
    assert ok.tolist() == [[True, True, False, True, False]]  # ids matched 0->5, 1->7; the ignored point False

"""The training step's loss paths without per-sample host round trips: the batched Hungarian cluster loss
against the per-sample implementation it replaced, the device losses free of host syncs, the datamodule's
loader options and the throughput benchmark's batch sweep."""
from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from scipy.optimize import linear_sum_assignment

from topocut.models.losses import hungarian_cluster_loss, matched_targets

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


# -- reference: topocut/models/losses.py before the batched matching (per-sample unique + scipy) -------------

def _ref_match(cost: np.ndarray) -> np.ndarray:
    rows, cols = linear_sum_assignment(cost)
    out = np.empty(cost.shape[0], dtype=np.int64)
    out[rows] = cols
    return out


def ref_matched_targets(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    B, N, C = logits.shape
    out = torch.full_like(target, -1)
    with torch.no_grad():
        logp = F.log_softmax(logits.detach().float(), dim=-1)  # B,N,C
        for b in range(B):
            keep = target[b] >= 0
            if not keep.any():
                continue
            ids, inv = torch.unique(target[b][keep], return_inverse=True)  # K true clusters
            if len(ids) > C:
                raise ValueError(f"{len(ids)} true clusters exceed the {C} predicted classes (model.num_labels)")
            cost = torch.zeros(len(ids), C, device=logits.device).index_add_(0, inv, -logp[b][keep])  # K,C
            perm = torch.as_tensor(_ref_match(cost.cpu().numpy()), device=target.device)
            out[b][keep] = perm[inv]
    return out


def ref_hungarian_cluster_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    t = ref_matched_targets(logits, target)
    if (t < 0).all():
        return logits.sum() * 0.0
    return F.cross_entropy(logits.reshape(-1, logits.shape[-1]), t.reshape(-1), ignore_index=-1)


def random_case(seed: int, B: int = 6, N: int = 40, C: int = 8, dtype=torch.float32):
    """Logits and targets with arbitrary (sparse, large) ids, ignored points, an all-ignored sample and
    samples with 1..C clusters."""
    g = torch.Generator().manual_seed(seed)
    logits = (3 * torch.randn(B, N, C, generator=g)).to(dtype)
    target = torch.empty(B, N, dtype=torch.long)
    for b in range(B):
        K = 1 + b % C
        ids = torch.randperm(50, generator=g)[:K]  # ids need not be 0..K-1
        target[b] = ids[torch.randint(0, K, (N,), generator=g)]
        target[b, torch.rand(N, generator=g) < 0.2] = -1
    target[B - 1] = -1 if B > 2 else target[B - 1]  # a sample with no labelled point
    target[0, :3] = torch.tensor([-3, -1, -7])  # any negative id is ignored
    return logits, target


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("seed", range(4))
def test_batched_hungarian_equals_per_sample_reference(seed, device):
    for dtype in (torch.float32, torch.float64):
        logits, target = random_case(seed, dtype=dtype)
        logits, target = logits.to(device), target.to(device)
        assert torch.equal(matched_targets(logits, target), ref_matched_targets(logits, target))
        x = logits.clone().requires_grad_(True)
        y = logits.clone().requires_grad_(True)
        got, ref = hungarian_cluster_loss(x, target), ref_hungarian_cluster_loss(y, target)
        got.backward()
        ref.backward()
        assert torch.equal(got, ref) and torch.equal(x.grad, y.grad)


def test_batched_hungarian_ties_and_full_class_count():
    # K == C clusters in one sample, identical logits (every assignment ties) in another
    logits, target = random_case(7, B=3, N=30, C=4)
    target[1] = torch.arange(30) % 4 + 10
    logits[2] = 0.0
    target[2] = torch.arange(30) % 3
    assert torch.equal(matched_targets(logits, target), ref_matched_targets(logits, target))
    assert torch.equal(hungarian_cluster_loss(logits, target), ref_hungarian_cluster_loss(logits, target))


def test_batched_hungarian_all_ignored_and_too_many_clusters():
    logits = torch.randn(3, 10, 4, requires_grad=True)
    target = torch.full((3, 10), -1)
    loss = hungarian_cluster_loss(logits, target)
    assert loss.item() == 0.0 and loss.requires_grad
    target[1] = torch.arange(10)  # 10 clusters, 4 classes
    with pytest.raises(ValueError, match="10 true clusters exceed the 4 predicted classes"):
        hungarian_cluster_loss(logits, target)


def test_hungarian_syncs_once(monkeypatch):
    """One device -> host transfer per loss, whatever the batch size (here counted through Tensor.cpu)."""
    calls = []
    orig = torch.Tensor.cpu

    def counting(self, *a, **k):
        calls.append(tuple(self.shape))
        return orig(self, *a, **k)

    monkeypatch.setattr(torch.Tensor, "cpu", counting)
    logits, target = random_case(3, B=12)
    hungarian_cluster_loss(logits, target)
    assert len(calls) == 1


# -- device point losses: no host sync for the phase count, same values -----------------------------------

def test_auction_phase_count_without_sync_gives_the_same_assignment():
    from topocut.models.point_losses import (
        WARM_EPS0,
        _nn,
        auction_assignment,
        auction_phases,
        emd_auction,
        sinkhorn_potentials,
    )

    g = torch.Generator().manual_seed(11)
    a = torch.rand(3, 48, 3, generator=g, dtype=torch.float64)
    b = a + 0.05 * torch.rand(3, 48, 3, generator=g, dtype=torch.float64)
    valid = torch.ones(3, 48, dtype=torch.bool)
    valid[1, 40:] = False
    d, cols = emd_auction(a, b, valid, return_assignment=True)
    # the same steps with the phase count read back from the device, as before
    dist, ab, ba = _nn(a, b, valid)
    mean = lambda x: torch.where(valid, torch.where(torch.isfinite(x), x, 0), 0).sum(1) / valid.sum(1)  # noqa: E731
    lb = torch.maximum(mean(ab), mean(ba))
    dm = torch.where(valid[:, :, None] & valid[:, None, :], dist, torch.zeros_like(dist))
    eps = torch.maximum(0.01 * lb, 1e-9 * dm.amax((1, 2)))
    pg = sinkhorn_potentials(dist, 30 * eps, 150, valid)
    ref = auction_assignment(dist, eps, valid, price0=-pg, eps0=WARM_EPS0 * eps)
    assert auction_phases(float((torch.maximum(WARM_EPS0 * eps, eps) / eps).max())) == auction_phases(WARM_EPS0)
    assert torch.equal(cols, ref)


# -- data loading and the benchmark ------------------------------------------------------------------------

def test_datamodule_loaders_pin_and_keep_workers(tmp_path):
    from topocut.data.episodes import EpisodeWriter
    from topocut.models.datamodule import EpisodeDataModule, synthetic_steps

    w = EpisodeWriter(tmp_path / "d.zarr", points_per_step=60)
    for e, obj in enumerate(["cube", "cake"]):
        w.add_episode(synthetic_steps(3, 80, seed=e), {"task": "slice", "object": obj, "seed": e,
                                                      "goal": np.zeros((10, 3)), "goal_labels": np.zeros(10)})
    dm = EpisodeDataModule(str(tmp_path / "d.zarr"), num_points=16, batch_size=2, val_fraction=0.5)
    assert dm.pin_memory == torch.cuda.is_available()
    dm.setup("fit")
    train, val = dm.train_dataloader(), dm.val_dataloader()
    assert train.pin_memory == val.pin_memory == torch.cuda.is_available()
    assert not train.persistent_workers and not val.persistent_workers  # no workers: nothing to keep
    batch = next(iter(train))
    assert batch["x_t"].shape == (2, 16, 3) and batch["valid"].dtype == torch.bool
    pinned = EpisodeDataModule(str(tmp_path / "d.zarr"), num_points=16, batch_size=2, num_workers=1,
                               val_fraction=0.5, pin_memory=False)
    pinned.setup("fit")
    loader = pinned.train_dataloader()
    assert loader.persistent_workers and not loader.pin_memory


def test_benchmark_sweeps_batches(monkeypatch, capsys):
    import sys

    from benchmarks import train as bench

    monkeypatch.setattr(sys, "argv", ["train.py", "--models", "graph_transformer", "--points", "32", "--batch", "2",
                                      "--batches", "2", "3", "--cpu-steps", "1", "--steps", "1"])
    bench.main()
    out = capsys.readouterr().out
    assert "ratios to batch 2 fp32" in out
    rows = [line.split() for line in out.splitlines() if line.strip().startswith(("2 ", "3 "))]
    assert [r[:2] for r in rows] == [["2", "fp32"], ["3", "fp32"]] and rows[0][3] == "1.00x"
    monkeypatch.setattr(sys, "argv", ["train.py", "--amp"])
    with pytest.raises(SystemExit, match="--amp"):
        bench.main()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="counts CUDA synchronisations")
def test_hungarian_loss_synchronises_once_on_cuda():
    import warnings

    logits, target = random_case(5, B=32)
    logits, target = logits.cuda(), target.cuda()
    hungarian_cluster_loss(logits, target)  # warm-up (allocator, pinned-memory cache)
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("warn")
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            hungarian_cluster_loss(logits, target)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert sum("synchroniz" in str(w.message) for w in caught) == 1  # the cost matrices' copy to the host

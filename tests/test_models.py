"""Perception pretraining (topocut.models): losses, graphs, shapes, data, a short fit and checkpoints."""
import itertools

import numpy as np
import pytest
import torch

from topocut.models.config import DynamicsConfig
from topocut.models.datamodule import EpisodeDataModule, TransitionDataset, synthetic_steps
from topocut.models.dynamics import GraphTransformerDynamics
from topocut.models.encoder import TopoEncoder
from topocut.models.graphs import build_graph, group_knn, propagate
from topocut.models.losses import cluster_accuracy, hungarian_cluster_loss, position_losses
from topocut.models.module import DynamicsModule, load_encoder
from topocut.models.pointnet import FeaturePropagation, PointNetDynamics, PointNetEncoder, SetAbstraction

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


TINY = dict(num_points=64, hidden=32, k=6, cross_k=6, num_layers=1, num_heads=2, query_hidden=16,
            pointnet_dims=[32, 48], pointnet_k=8, warmup_steps=2)


def tiny_cfg(**kw) -> DynamicsConfig:
    return DynamicsConfig(**{**TINY, **kw})


# -- losses ------------------------------------------------------------------

def brute_force_topo_loss(logits: np.ndarray, target: np.ndarray) -> float:
    """min over injective renamings of the mean cross-entropy, by enumeration (one sample)."""
    logp = logits - np.log(np.exp(logits).sum(-1, keepdims=True))
    ids = np.unique(target)
    best = np.inf
    for cols in itertools.permutations(range(logits.shape[1]), len(ids)):
        ren = dict(zip(ids, cols))
        best = min(best, -np.mean([logp[i, ren[t]] for i, t in enumerate(target)]))
    return best


def test_hungarian_loss_equals_brute_force_and_ignores_relabelling():
    g = torch.Generator().manual_seed(0)
    logits = torch.randn(1, 30, 5, generator=g, dtype=torch.float64)
    target = torch.randint(0, 3, (1, 30), generator=g)
    loss = hungarian_cluster_loss(logits, target).item()
    assert loss == pytest.approx(brute_force_topo_loss(logits[0].numpy(), target[0].numpy()), rel=1e-9)
    relabelled = torch.tensor([17, 4, 9])[target]  # same partition, other (out-of-range) ids
    assert hungarian_cluster_loss(logits, relabelled).item() == pytest.approx(loss, rel=1e-12)


def test_hungarian_loss_minimum_and_ignored_points():
    target = torch.tensor([[0, 0, 1, 1, 2, -1]])
    logits = 40.0 * torch.nn.functional.one_hot(torch.tensor([[3, 3, 0, 0, 1, 2]]), 4).double()  # a renaming
    assert hungarian_cluster_loss(logits, target).item() < 1e-12
    assert cluster_accuracy(logits.argmax(-1), target).item() == 1.0


def test_cluster_accuracy_hand_count():
    target = torch.tensor([[0, 0, 0, 1, 1, 2]])
    pred = torch.tensor([[5, 5, 1, 1, 1, 7]])  # t0->5 (2 agree), t1->1 (2), t2->7 (1): 5 of 6
    assert cluster_accuracy(pred, target).item() == pytest.approx(5 / 6)


def test_position_losses_zero_for_identical_and_shift_for_translated():
    x = torch.rand(2, 40, 3)
    for v in position_losses(x, x.clone()).values():
        assert torch.allclose(v, torch.zeros(2), atol=1e-6)
    shift = torch.tensor([1e-3, 0.0, 0.0])  # far below the point spacing: every distance is |shift|
    grid = torch.stack(torch.meshgrid(*[torch.arange(4.0) * 0.05] * 3, indexing="ij"), -1).reshape(1, -1, 3)
    for v in position_losses(grid + shift, grid, scale=0.1).values():
        assert v.item() == pytest.approx(1e-3 / 0.1, rel=1e-4)


# -- graphs ------------------------------------------------------------------

def test_group_knn_never_crosses_groups_and_matches_brute_force():
    g = torch.Generator().manual_seed(1)
    pts = torch.rand(2, 50, 3, generator=g)
    groups = torch.randint(0, 4, (2, 50), generator=g)
    groups[0, :3] = 9  # a group of 3 points: only 2 valid neighbours each
    k = 5
    idx, valid = group_knn(pts, groups, k)
    assert (torch.gather(groups, 1, idx.view(2, -1)).view(2, 50, k) == groups[..., None])[valid].all()
    assert valid[0, :3].sum(-1).tolist() == [2, 2, 2]
    p, gr = pts.numpy(), groups.numpy()
    for b, i in [(0, 10), (1, 7), (0, 1)]:
        others = np.flatnonzero((gr[b] == gr[b, i]) & (np.arange(50) != i))
        d = np.linalg.norm(p[b, others] - p[b, i], axis=1)
        expect = others[np.argsort(d)][:k]
        assert idx[b, i][valid[b, i]].tolist() == expect.tolist()
    graph = build_graph(pts, groups, k)
    flat = groups.reshape(-1)
    assert (flat[graph.src] == flat[graph.dst]).all()


def test_propagate_matches_dense_normalised_adjacency():
    pts = torch.rand(1, 20, 3, generator=torch.Generator().manual_seed(2))
    groups = (pts[..., 0] > 0.5).long()
    graph = build_graph(pts, groups, 3)
    A = graph.dense()[0].numpy().astype(float) + np.eye(20)  # symmetrised kNN + self loops
    Dm = np.diag(A.sum(1) ** -0.5)
    x = torch.randn(1, 20, 4)
    np.testing.assert_allclose(propagate(x, graph)[0].numpy(), Dm @ A @ Dm @ x[0].numpy(), atol=1e-5)


# -- modules -----------------------------------------------------------------

def box_batch(B=3, N=64, seed=0):
    steps = synthetic_steps(B, N, seed=seed)
    items = [TransitionDataset(steps, num_points=N)[i] for i in range(B)]
    return {k: torch.stack([it[k] for it in items]) for k in items[0]}


def test_module_shapes():
    b = box_batch()
    x, f, m = b["x_t"], b["f_t"], b["mask"]
    enc = TopoEncoder(hidden=32, num_labels=32, k=6)
    assert enc(x, f).shape == (3, 64, 32) and enc.out_dim == 32
    cfg = tiny_cfg()
    for model in (GraphTransformerDynamics(cfg), PointNetDynamics(tiny_cfg(model="pointnet"))):
        px, logits = model(x, f, x, m)
        assert px.shape == (3, 64, 3) and logits.shape == (3, 64, 32)
        assert model.encoder(x, f).shape == (3, 64, 32)
    xyz, feat = SetAbstraction(8, 16, 0.25, 5, 2)(x, torch.randn(3, 64, 8))
    assert xyz.shape == (3, 16, 3) and feat.shape == (3, 16, 16)
    assert FeaturePropagation(16, 8, 12)(x, torch.randn(3, 64, 8), xyz, feat).shape == (3, 64, 12)
    assert len(PointNetEncoder([32, 48, 64], ratio=0.25).encode(x, f)) == 3


def test_encoder_translation_invariant_and_permutation_equivariant():
    b = box_batch(B=2)
    x, f = b["x_t"], b["f_t"]
    enc = TopoEncoder(hidden=32, k=6).eval()
    z = enc(x, f)
    assert torch.allclose(enc(x + torch.tensor([0.1, -0.2, 0.3]), f), z, atol=1e-4)
    perm = torch.randperm(64, generator=torch.Generator().manual_seed(3))
    assert torch.allclose(enc(x[:, perm], f[:, perm]), z[:, perm], atol=1e-4)


def test_initial_prediction_is_no_motion():
    b = box_batch(B=2)
    px, _ = GraphTransformerDynamics(tiny_cfg())(b["x_t"], b["f_t"], b["x_t"], b["mask"])
    assert torch.equal(px, b["x_t"])  # zero-initialised residual head


# -- data ----------------------------------------------------------------------

def test_transition_dataset_sampling_sort_relabel_noise():
    s = synthetic_steps(1, 300, seed=4)[0]
    s["f_t"] = s["f_t"] * 10 + 5  # ids 5 / 15, new pieces get larger ids
    s["f_t1"] = np.where(s["mask"] == 1, s["f_t"] + 100, s["f_t"])
    item = TransitionDataset([s], num_points=64, sort=True)[0]
    x = item["x_t"].numpy()
    assert x.shape == (64, 3) and np.all(np.diff(x[:, 0]) >= 0)
    rows = [np.flatnonzero(np.all(s["x_t"] == p, axis=1))[0] for p in x]  # each sampled point is an input row
    np.testing.assert_array_equal(item["x_t1"].numpy(), s["x_t1"][rows])
    np.testing.assert_array_equal(item["mask"].numpy(), s["mask"][rows])
    ids = np.unique(np.concatenate([s["f_t"][rows], s["f_t1"][rows]]))
    np.testing.assert_array_equal(item["f_t1"].numpy(), np.searchsorted(ids, s["f_t1"][rows]))
    noisy = TransitionDataset([s], num_points=64, noise_std=0.01, train=True)[0]["x_t"]
    assert 0.005 < (noisy - item["x_t"]).std().item() < 0.015  # jitter on inputs only
    assert torch.equal(TransitionDataset([s], num_points=64, noise_std=0.01, train=True)[0]["x_t1"], item["x_t1"])
    assert TransitionDataset([synthetic_steps(1, 20)[0]], num_points=64)[0]["x_t"].shape == (64, 3)  # padded
    with pytest.raises(KeyError, match="mask"):
        TransitionDataset([{k: v for k, v in s.items() if k != "mask"}])[0]


def test_split_by_episode_with_held_out_objects():
    dm = EpisodeDataModule("unused", val_fraction=0.25, held_out_objects=["donut"], seed=0)
    objects = ["cake", "cube", "donut", "ham", "cake", "donut", "potato", "cube"]
    split = dm.split_episodes(objects)
    assert split["unseen"] == [2, 5]
    assert len(split["val"]) == 2 and not set(split["val"]) & set(split["train"])
    assert sorted(split["train"] + split["val"]) == [0, 1, 3, 4, 6, 7]


def test_datamodule_reads_episode_dataset(tmp_path):
    from topocut.data.episodes import EpisodeWriter

    w = EpisodeWriter(tmp_path / "d.zarr", points_per_step=100)
    for e, obj in enumerate(["cube", "cake", "donut"]):
        w.add_episode(synthetic_steps(2, 120, seed=e), {"task": "slice", "object": obj, "seed": e,
                                                       "goal": np.zeros((10, 3)), "goal_labels": np.zeros(10)})
    dm = EpisodeDataModule.from_config(str(tmp_path / "d.zarr"), tiny_cfg(num_points=32, noise=False), batch_size=2,
                                       val_fraction=0.5, held_out_objects=["donut"])
    assert dm.noise_std == 0.0
    dm.setup("fit")
    assert len(dm.train_set) == 2 and len(dm.val_set) == 4  # 1 seen val episode + the donut, 2 steps each
    batch = next(iter(dm.val_dataloader()))
    assert batch["x_t"].shape == (2, 32, 3) and batch["seen"].tolist() == [True, True]


# -- training and checkpoints -------------------------------------------------------

@pytest.mark.parametrize("model", ["graph_transformer", "pointnet"])
def test_few_steps_reduce_loss(model):
    torch.manual_seed(0)
    cfg = tiny_cfg(model=model, lr=3e-3)
    module = DynamicsModule(cfg)
    batch = box_batch(B=8, N=64, seed=5)
    opt = torch.optim.AdamW(module.parameters(), lr=cfg.lr)
    first = module._step(batch)[2]
    for _ in range(25):
        opt.zero_grad()
        module._step(batch)[2]["loss"].backward()
        opt.step()
    last = module._step(batch)[2]
    assert last["loss"].item() < 0.6 * first["loss"].item(), (first["loss"].item(), last["loss"].item())
    assert last["loss_topo"].item() < first["loss_topo"].item()


def test_load_encoder_round_trip_and_bad_checkpoints(tmp_path):
    import lightning as L
    from torch.utils.data import DataLoader

    torch.manual_seed(0)
    ds = TransitionDataset(synthetic_steps(4, 64, seed=6), num_points=64)
    module = DynamicsModule(tiny_cfg())
    trainer = L.Trainer(max_steps=2, accelerator="cpu", logger=False, default_root_dir=tmp_path,
                        enable_progress_bar=False, enable_model_summary=False, limit_val_batches=1)
    trainer.fit(module, DataLoader(ds, batch_size=2), DataLoader(ds, batch_size=2))
    assert "val/cluster_acc" in trainer.callback_metrics and "train/loss_topo" in trainer.callback_metrics
    ckpt = trainer.checkpoint_callback.best_model_path
    enc = load_encoder(ckpt)
    assert isinstance(enc, TopoEncoder) and not enc.training
    assert not any(p.requires_grad for p in enc.parameters())
    b = box_batch(B=2)
    module.eval()
    assert torch.allclose(enc(b["x_t"], b["f_t"]), module.encoder(b["x_t"], b["f_t"]), atol=1e-6)

    bad = tmp_path / "corrupt.ckpt"
    bad.write_bytes(b"not a checkpoint" * 10)
    with pytest.raises(ValueError, match="corrupt.ckpt"):
        load_encoder(bad)
    torch.save({"state_dict": {}}, tmp_path / "other.ckpt")
    with pytest.raises(ValueError, match="other.ckpt.*hyper_parameters"):
        load_encoder(tmp_path / "other.ckpt")
    with pytest.raises(FileNotFoundError, match="missing.ckpt"):
        load_encoder(tmp_path / "missing.ckpt")


def test_config_errors_name_key_and_valid_values():
    with pytest.raises(ValueError, match="model.model='gnn'.*graph_transformer, pointnet"):
        DynamicsConfig(model="gnn").validate()
    with pytest.raises(ValueError, match="model.hidden=30.*num_heads=4"):
        DynamicsConfig(hidden=30).validate()
    with pytest.raises(KeyError, match="'hiden'.*hidden"):
        DynamicsModule({"hiden": 32})


@pytest.mark.parametrize("value", [0.0, -0.1, float("nan")])
def test_pos_scale_must_be_positive(value):
    """pos_scale divides every point-set distance: 0 gave inf/NaN losses (and an EMD ValueError), < 0 flipped
    the sign of the loss."""
    with pytest.raises(ValueError, match=r"model\.pos_scale=.* must be > 0"):
        DynamicsConfig(pos_scale=value).validate()
    with pytest.raises(ValueError, match=r"model\.coord_scale=0.0 must be > 0"):
        DynamicsConfig(coord_scale=0.0).validate()
    with pytest.raises(ValueError, match=r"model\.lr=-1.0 must be >= 0"):
        DynamicsConfig(lr=-1.0).validate()
    assert DynamicsConfig(pos_scale=1e-3, noise_std=0.0).validate().pos_scale == 1e-3


def test_validation_logs_the_mask_rule_floor():
    """val/mask_rule_acc: split each input cluster by the cut mask. Truth = that split -> 1; truth = no split
    of a half/half mask -> 1/2 (Hungarian keeps the better half); truth = a split at 3/4 of the points -> 3/4
    (the cut-off half matches the big piece: 32 points, the rest matches the small one: 16 of 32)."""
    module = DynamicsModule(tiny_cfg())
    logged = {}
    module.log = lambda name, value, **kw: logged.__setitem__(name, float(value))  # no Trainer needed
    N = 64
    x = torch.rand(2, N, 3)
    mask = (torch.arange(N) < N // 2).long().expand(2, N)  # first half cut off
    other = (torch.arange(N) < 3 * N // 4).long().expand(2, N)
    for f_t1, want in ((mask, 1.0), (torch.zeros(2, N, dtype=torch.long), 0.5), (other, 0.75)):
        batch = {"x_t": x, "f_t": torch.zeros(2, N, dtype=torch.long), "mask": mask, "x_t1": x, "f_t1": f_t1,
                 "seen": torch.tensor([True, False])}
        module.validation_step(batch, 0)
        module.on_validation_epoch_end()  # epoch means (EpochMeans), then reset
        assert logged["val/mask_rule_acc"] == pytest.approx(want)
        assert logged["val/mask_rule_acc_seen"] == logged["val/mask_rule_acc_unseen"] == pytest.approx(want)

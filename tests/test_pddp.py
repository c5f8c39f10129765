"""PDDP network, encoders, plane recovery, training and the deployed policy."""
import importlib.util

import numpy as np
import pytest
import torch

from topocut.policies import PDDPConfig, PolicyTrainConfig, action_from_mask, fit_plane, make_obs
from topocut.policies.base import Policy, history_from_actions
from topocut.policies.encoders import FrozenEncoder, build_encoder
from topocut.policies.module import PDDPModule, PDDPPolicy, PolicyDataset
from topocut.policies.pddp import PDDPNet
from topocut.sim.action import KnifeAction, cut_mask

TINY = dict(n_blocks=2, hidden=32, obs_dim=32, n_heads=2, cond_dim=32, time_freq_dim=32, goal_hidden=16, dropout=0.0)


def random_action(rng):
    return KnifeAction(rng.uniform(0.44, 0.56), rng.uniform(0.44, 0.56), rng.uniform(-np.pi / 2, np.pi / 2),
                       rng.uniform(-0.5, 0.5)).canonical()


def box_points(rng, n):
    return rng.uniform([0.35, 0.35, 0.05], [0.65, 0.65, 0.25], (n, 3)).astype(np.float32)


@pytest.mark.parametrize("method", ["svm", "lsq"])
def test_plane_round_trip(method):
    """Random action -> cut_mask on random points -> recovered plane within 3 degrees and 0.01 offset."""
    rng = np.random.default_rng(0)
    for _ in range(10):
        a = random_action(rng)
        pts = box_points(rng, 2048)
        mask = cut_mask(pts, a)
        r = action_from_mask(pts, mask, method)
        cos = float(r.normal @ a.normal)
        angle = np.degrees(np.arccos(min(1.0, abs(cos))))
        assert angle < 3.0
        c = pts.mean(0)  # the planes' separation measured at the cloud's centre
        offset = abs(a.normal @ (c - a.plane_point()) - np.sign(cos) * r.normal @ (c - r.plane_point()))
        assert offset < 0.01
        # the recovered plane cuts the points as the mask does (up to the canonical side convention)
        m2 = cut_mask(pts, r)
        assert max((m2 == mask).mean(), (m2 != mask).mean()) > 0.97
        n, p = fit_plane(pts, mask, method)
        assert ((pts - p) @ n > 0).astype(np.uint8)[mask == 1].mean() > 0.97  # normal points to class 1


@pytest.mark.parametrize("method", ["svm", "lsq"])
def test_plane_on_a_flat_sheet_and_a_line_of_points(method):
    """A sheet (all points at one height) and a line of points cut at x=0.5: the boundary of
    the mask is a segment or a single gap, whose smallest principal axis is not the cut's
    normal; the recovered plane must still be x=0.5 (vertical) and split the points as the mask does."""
    rng = np.random.default_rng(3)
    box = rng.uniform([0.4, 0.42, 0.05], [0.6, 0.58, 0.13], (256, 3))
    sheet = box.copy()
    sheet[:, 2] = 0.06
    line = np.stack([np.linspace(0.41, 0.59, 50), np.full(50, 0.5), np.full(50, 0.08)], 1)
    for pts in (box, sheet, line):
        mask = (pts[:, 0] > 0.5).astype(np.uint8)
        n, p = fit_plane(pts, mask, method)
        assert (((pts - p) @ n > 0) == mask.astype(bool)).mean() >= 0.98
        assert abs(n[0]) > 0.9  # the normal is (close to) the x axis
        a = action_from_mask(pts, mask, method)
        assert a is not None and abs(np.degrees(a.tilt)) < 30.0


def test_plane_degenerate_masks():
    pts = box_points(np.random.default_rng(1), 200)
    assert action_from_mask(pts, np.zeros(200, np.uint8)) is None
    assert action_from_mask(pts, np.ones(200, np.uint8), "lsq") is None
    horizontal = (pts[:, 2] > 0.15).astype(np.uint8)  # a horizontal plane: no downward knife makes it
    assert action_from_mask(pts, horizontal) is None
    with pytest.raises(ValueError, match="svm"):
        fit_plane(pts, horizontal, "ransac")


@pytest.mark.parametrize("graph,goal_mode,score_param", [("uniform", "pool", "denoiser"), ("absorbing", "cross", "denoiser"),
                                                          ("uniform", "cross", "direct"), ("absorbing", "pool", "direct")])
def test_network_shapes_and_set_equivariance(graph, goal_mode, score_param):
    torch.manual_seed(0)
    net = PDDPNet(PDDPConfig(graph=graph, goal_mode=goal_mode, score_param=score_param, **TINY)).eval()
    for p in net.parameters():  # zero-initialised adaLN/output layers would make the test trivial
        torch.nn.init.normal_(p, std=0.2)
    B, N, G = 2, 24, 10
    d = 2 if graph == "uniform" else 3
    z, goal, hist = torch.randn(B, N, 32), torch.randn(B, G, 32), torch.randn(B, 3, 7)  # goal: z_g = Φ(X_g, F_g)
    x = torch.randint(0, d, (B, N))
    sigma = torch.tensor([0.1, 2.0])
    ctx = net.context(z, goal, hist)
    out = net(x, sigma, ctx)
    assert out.shape == (B, N, d)
    assert torch.all(out.gather(-1, x[..., None]) == 0)  # ratio 1 at the current state
    perm = torch.randperm(N)
    out_p = net(x[:, perm], sigma, net.context(z[:, perm], goal[:, torch.randperm(G)], hist))
    torch.testing.assert_close(out_p, out[:, perm], atol=1e-4, rtol=1e-4)  # a set, not a sequence
    assert not torch.allclose(out, net(x, sigma, net.context(z, goal, hist.flip(1))))  # history matters
    assert not torch.allclose(out, net(x, sigma, net.context(z, goal.flip(-1), hist)))  # the goal matters
    # padding copies of a goal point (goal_valid False) change nothing: pooled and attended to once
    padded = torch.cat([goal, goal[:, :3]], 1)
    valid = torch.cat([torch.ones(B, G, dtype=torch.bool), torch.zeros(B, 3, dtype=torch.bool)], 1)
    torch.testing.assert_close(net(x, sigma, net.context(z, padded, hist, valid)), out, atol=1e-5, rtol=1e-5)


def test_paper_sizes():
    net = PDDPNet(PDDPConfig())
    assert net.goal_enc[0].weight.shape == (64, 96)  # goal encoder 96 -> 64 -> 96 over z_g = Φ(X_g, F_g)
    assert PDDPNet(PDDPConfig(goal_input="xyz")).goal_enc[0].weight.shape == (64, 3)  # the task-blind legacy
    assert len(net.blocks) == 12
    assert net.blocks[0].attn.kv.weight.shape == (288, 96)  # 96 -> 288 fused qkv
    assert net.blocks[0].mlp[0].weight.shape == (384, 96)
    assert net.blocks[0].ada.weight.shape == (576, 128)
    assert net.hist.weight.shape == (128, 21)
    assert net.sigma_map.mlp[0].weight.shape == (128, 256)
    assert net.out.linear.weight.shape == (2, 96)  # binary logits per point


@pytest.mark.parametrize("kind", ["none", "graphconv", "pretrained"])
def test_encoders(kind):
    B, N = 2, 40
    pts, labels = torch.rand(B, N, 3), torch.randint(-1, 4, (B, N))
    if kind == "pretrained":
        if importlib.util.find_spec("topocut.models.encoder") is None:
            pytest.skip("topocut.models.encoder (TopoEncoder) is not written yet")
        from topocut.models.encoder import TopoEncoder

        enc = FrozenEncoder(TopoEncoder(hidden=96, num_labels=32))
        enc.train()
        assert not enc.encoder.training and not any(p.requires_grad for p in enc.parameters())
    else:
        enc = build_encoder(kind)
    out = enc(pts, labels)
    assert out.shape == (B, N, enc.out_dim) and enc.out_dim == 96
    assert torch.isfinite(out).all()
    with pytest.raises(ValueError, match="graphconv"):
        build_encoder("pointnet")
    with pytest.raises(ValueError, match="ckpt"):
        build_encoder("pretrained")


def synthetic_steps(n_steps, n_points=64, seed=0):
    """Steps whose mask is the cut of a fixed plane: learnable from the point positions alone."""
    rng = np.random.default_rng(seed)
    action = KnifeAction(0.5, 0.5, 0.4, 0.0)
    steps = []
    for _ in range(n_steps):
        x = box_points(rng, n_points)
        goal = box_points(rng, 16)
        steps.append({"x_t": x, "f_t": np.zeros(n_points, np.int32), "mask": cut_mask(x, action),
                      "action": action.to_vector(), "history": np.zeros((3, 7), np.float32), "goal": goal,
                      "goal_labels": (goal[:, 0] > 0.55).astype(np.int32)})
    return steps, action


def test_training_reduces_loss_and_policy_acts(one_thread):
    torch.manual_seed(0)
    steps, action = synthetic_steps(64)
    ds = PolicyDataset(steps, num_points=64, num_goal_points=16)
    module = PDDPModule(PDDPConfig(**TINY), "none", train=PolicyTrainConfig(lr=1e-3, warmup_steps=1, ema_decay=0.8,
                                                                          num_points=64, num_goal_points=16))
    batch = torch.utils.data.default_collate([ds[i] for i in range(32)])
    t = torch.linspace(0.05, 0.95, 32)

    def fixed_loss():  # same noise levels and perturbations every time
        with torch.no_grad():
            return module.loss(batch, t=t, generator=torch.Generator().manual_seed(0)).item()

    before = fixed_loss()
    opt = module.configure_optimizers()["optimizer"]
    loader = torch.utils.data.DataLoader(ds, batch_size=16, shuffle=True)
    for _ in range(24):  # 96 steps
        for b in loader:
            loss = module.loss(b)
            opt.zero_grad()
            loss.backward()
            opt.step()
            module.on_train_batch_end(None, b, 0)
    after = fixed_loss()
    assert after < 0.4 * before, (before, after)

    masks = module.sample_masks(batch, steps=16, generator=torch.Generator().manual_seed(1))
    assert (masks == batch["mask"]).float().mean() > 0.8

    policy = PDDPPolicy(module, steps=16, seed=0)
    assert isinstance(policy, Policy)
    rng = np.random.default_rng(5)
    pts = box_points(rng, 200)  # more points than the network sees: the mask is spread back to all of them
    goal = box_points(rng, 16)
    policy.reset(type("Goal", (), {"points": goal, "labels": (goal[:, 0] > 0.55).astype(np.int32)})())
    obs = make_obs(pts, np.zeros(200, np.int32), policy.goal, policy.goal_labels, history=history_from_actions([]))
    a = policy.act(obs)
    assert a is not None and policy.last_mask.shape == (200,)
    assert np.degrees(np.arccos(min(1.0, abs(a.normal @ action.normal)))) < 20.0


def test_trainer_logs_metrics(tmp_path, one_thread):
    import lightning as L

    steps, _ = synthetic_steps(16, n_points=32)
    tr = PolicyTrainConfig(num_points=32, num_goal_points=16, warmup_steps=1, val_sample_steps=4)
    module = PDDPModule(PDDPConfig(graph="absorbing", goal_mode="cross", **TINY), "graphconv", train=tr)
    # sample="batch": the FPS in the module's on_after_batch_transfer, for training and validation batches alike
    dl = torch.utils.data.DataLoader(PolicyDataset(steps, 32, 16, sample="batch"), batch_size=8)
    assert "cloud" in next(iter(dl))
    trainer = L.Trainer(max_steps=4, limit_val_batches=1, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, accelerator="cpu",
                        default_root_dir=tmp_path)
    trainer.fit(module, dl, dl)
    m = trainer.callback_metrics
    assert {"train/loss", "val/loss", "val/mask_acc", "val/mask_acc_majority", "val/mask_acc_prev_plane"} <= set(m)
    assert 0.0 <= float(m["val/mask_acc"]) <= 1.0
    assert 0.5 <= float(m["val/mask_acc_majority"]) <= 1.0  # the best constant mask is right on >= half the points
    ckpt = tmp_path / "p.ckpt"
    trainer.save_checkpoint(ckpt)
    policy = PDDPPolicy(str(ckpt), sampler="euler", steps=4, plane="lsq")
    assert policy.module.cfg.graph == "absorbing" and policy.module.cfg.goal_mode == "cross"


def test_val_mask_accuracy_is_sampled_every_kth_epoch_and_the_last(tmp_path, one_thread):
    import lightning as L

    steps, _ = synthetic_steps(8, n_points=32)
    tr = PolicyTrainConfig(num_points=32, num_goal_points=16, warmup_steps=1, val_sample_steps=2, val_sample_every=3)
    module = PDDPModule(PDDPConfig(**TINY), "none", train=tr)
    sampled, real = [], module.sample_masks
    module.sample_masks = lambda batch, **kw: sampled.append(module.current_epoch) or real(batch, **kw)
    dl = torch.utils.data.DataLoader(PolicyDataset(steps, 32, 16), batch_size=8)
    trainer = L.Trainer(max_epochs=7, limit_train_batches=1, limit_val_batches=1, num_sanity_val_steps=0,
                        logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, accelerator="cpu", default_root_dir=tmp_path)
    trainer.fit(module, dl, dl)
    assert sampled == [2, 5, 6]  # epochs 3 and 6 (every 3rd) and 7 (the last), 1-based
    assert "val/mask_acc" in trainer.callback_metrics and "val/loss" in trainer.callback_metrics
    assert PDDPModule(PDDPConfig(**TINY), "none", train=tr).sample_due()  # a module outside a fit: always


def test_config_errors():
    with pytest.raises(ValueError, match="absorbing"):
        PDDPConfig(graph="masked").validate()
    with pytest.raises(ValueError, match="encoder_ckpt"):
        PolicyTrainConfig(encoder="pretrained").validate()
    with pytest.raises(KeyError, match="goal"):
        make_obs(np.zeros((3, 3)), np.zeros(3), None)


def test_ema_warms_up_then_reaches_its_decay():
    import torch

    from topocut.policies.module import ema_decay_at, ema_with_warmup

    assert ema_decay_at(0.999, 0) == 0.1 and ema_decay_at(0.999, 10) == 11 / 20
    assert ema_decay_at(0.999, 10**6) == 0.999
    ema, cur = [torch.zeros(3)], [torch.ones(3)]
    ema_with_warmup(0.999)(ema, cur, torch.tensor(0))  # first update: 0.1 * 0 + 0.9 * 1
    assert torch.allclose(ema[0], torch.full((3,), 0.9))


def test_policy_reseeds_per_episode_and_forwards_the_whole_sampler_config(one_thread):
    from topocut.policies.config import SamplerConfig

    torch.manual_seed(0)
    tr = PolicyTrainConfig(num_points=64, num_goal_points=16)
    module = PDDPModule(PDDPConfig(**TINY), "none", train=tr)  # untrained: masks are noise, which is the point
    rng = np.random.default_rng(3)
    pts, goal = box_points(rng, 64), type("Goal", (), {"points": box_points(rng, 16)})()
    labels = np.zeros(64, np.int32)

    warm = PDDPPolicy(module, steps=4, seed=1)
    warm.reset(goal, seed=10)
    first = warm.sample((pts, labels))[0]  # episode 10 draws from the generator ...
    warm.reset(goal, seed=11)
    after = warm.sample((pts, labels))[0]
    fresh = PDDPPolicy(module, steps=4, seed=1)
    fresh.reset(goal, seed=11)
    np.testing.assert_array_equal(after, fresh.sample((pts, labels))[0])  # ... episode 11 does not see it
    assert not np.array_equal(first, after)

    calls = []
    real = module.sample_masks
    module.sample_masks = lambda batch, **kw: calls.append(kw) or real(batch, **kw)
    cfg = SamplerConfig(predictor="euler", steps=3, denoise=False, eps=1e-3, plane="lsq", retries=0)
    policy = PDDPPolicy(module, sampler=cfg, steps=99, plane="svm", retries=7)  # the config wins
    policy.reset(goal, seed=0)
    policy.sample((pts, labels))
    assert len(calls) == 1  # retries=0: one draw
    assert {k: calls[0][k] for k in ("steps", "predictor", "denoise", "eps")} == \
        {"steps": 3, "predictor": "euler", "denoise": False, "eps": 1e-3}
    assert policy.scfg.plane == "lsq"


def _perception_ckpt(path, seed=1):
    """A tiny pretrain checkpoint as stage=pretrain writes it (state_dict + hyper_parameters.cfg)."""
    import dataclasses

    from topocut.models.config import DynamicsConfig
    from topocut.models.module import DynamicsModule

    cfg = DynamicsConfig(num_points=16, hidden=16, k=4, cross_k=4, num_layers=1, num_heads=2, query_hidden=8)
    torch.manual_seed(seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"state_dict": DynamicsModule(cfg).state_dict(), "hyper_parameters": {"cfg": dataclasses.asdict(cfg)}},
               path)
    return str(path)


def _save_like_lightning(module, path, drop=()):
    import lightning

    path.parent.mkdir(parents=True, exist_ok=True)
    hp = {k: v for k, v in dict(module.hparams).items() if k not in drop}
    torch.save({"state_dict": module.state_dict(), "hyper_parameters": hp,
                "pytorch-lightning_version": lightning.__version__}, path)


def test_pddp_checkpoint_with_pretrained_encoder_travels_without_its_perception_file(tmp_path):
    """Φ's weights are in the policy's own state dict and its architecture in encoder_arch: a checkpoint moved to a
    machine that never had checkpoint/perception loads, with Φ's weights as trained. A checkpoint from before
    encoder_arch finds the perception version in its own store; found nowhere, one error names both paths."""
    first = tmp_path / "gpu" / "checkpoint" / "perception" / "v001" / "model.ckpt"
    enc_ckpt = _perception_ckpt(first)
    train = PolicyTrainConfig(encoder="pretrained", encoder_ckpt=enc_ckpt, num_points=16, num_goal_points=16)
    torch.manual_seed(0)
    module = PDDPModule(PDDPConfig(**TINY), "pretrained", enc_ckpt, train)
    assert module.hparams["encoder_arch"]["hidden"] == 16
    trained = {k: v.clone() for k, v in module.state_dict().items() if ".encoder." in k}
    assert trained
    ckpt = tmp_path / "store" / "checkpoint" / "pddp" / "v001" / "model.ckpt"
    _save_like_lightning(module, ckpt)
    old = tmp_path / "store" / "checkpoint" / "pddp" / "v002" / "model.ckpt"
    _save_like_lightning(module, old, drop=("encoder_arch",))
    first.unlink()  # the machine it trained on is gone

    policy = PDDPPolicy(str(ckpt), steps=2)
    loaded = policy.module.state_dict()
    for k, v in trained.items():
        torch.testing.assert_close(loaded[k], v, msg=k)
    with pytest.raises(FileNotFoundError, match=r"perception/v001/model\.ckpt.*store/checkpoint/perception/v001"):
        PDDPPolicy(str(old), steps=2)
    _perception_ckpt(tmp_path / "store" / "checkpoint" / "perception" / "v001" / "model.ckpt", seed=2)  # carried
    relocated = PDDPPolicy(str(old), steps=2).module
    assert relocated.hparams["encoder_ckpt"] == str(tmp_path / "store" / "checkpoint" / "perception" / "v001"
                                                    / "model.ckpt")
    for k, v in trained.items():  # the state dict, not the relocated file's (other) weights, wins
        torch.testing.assert_close(relocated.state_dict()[k], v, msg=k)


def test_loader_workers_draw_their_own_fps_starts(one_thread):
    """Each DataLoader worker counts its own accesses: without its id in the seed, worker 1's first access of a
    step would repeat worker 0's FPS start.  The main process (num_workers=0) keeps the seeds it always had, and
    stage=bc's persistent workers (pipelines/bc.py) keep counting from one epoch to the next."""
    from pipelines.bc import _loaders

    steps, _ = synthetic_steps(2, n_points=200)  # 200 points, 16 taken: the start decides the sample

    def points(loader):
        return [b["points"][0].numpy() for b in loader]

    one_step = [0, 0, 0, 0]  # step 0 four times: workers 0, 1, 0, 1 (batches handed out in turn)
    ds = PolicyDataset(steps, 16, 8)
    w0a, w1a, w0b, w1b = points(torch.utils.data.DataLoader(ds, batch_size=1, num_workers=2, sampler=one_step))
    main = PolicyDataset(steps, 16, 8)
    m1, m2 = main[0]["points"].numpy(), main[0]["points"].numpy()
    assert not np.array_equal(w0a, w1a)  # the two workers' first accesses: different starts
    np.testing.assert_array_equal(w0a, m1)  # worker 0 seeds as the main process does
    np.testing.assert_array_equal(w0b, m2)
    assert not np.array_equal(w1b, m2)

    train, val = _loaders(lambda idx: PolicyDataset(steps, 16, 8, indices=idx),
                          {"train": [0, 1], "val": [], "unseen": [1]}, batch_size=1, num_workers=2)
    assert train.persistent_workers and val.persistent_workers and val.num_workers == 2
    first, second = points(train), points(train)
    assert not any(np.array_equal(a, b) for a in first for b in second)  # counters carried over the epoch


def test_batch_sampling_gives_the_loader_batches(one_thread):
    """policy.train.sample=batch: the whole cloud goes to the batch, whose FPS (sample_batch, float64 from each
    item's drawn start) picks what the loader's per-item numpy FPS picks, so every field of every batch is the
    same; a cloud of few distinct points repeats picks, flagged in ``valid`` as valid_rows flags them; after a
    first cut ``prev_mask`` is that cut's mask on the picked rows, before it the sampled mask's majority."""
    from topocut.policies.dataset import sample_batch

    steps, action = synthetic_steps(12, n_points=200)
    for k, s in enumerate(steps):
        if k % 2:  # a previous cut: the plane-from-previous-cut floor
            s["history"] = history_from_actions([KnifeAction(0.45 + 0.01 * k, 0.5, 0.3, 0.0)])
    steps[3]["x_t"] = np.repeat(steps[3]["x_t"][:10], 20, axis=0)  # 10 distinct points for 16 picks
    loader = PolicyDataset(steps, num_points=16, num_goal_points=8, seed=3)
    batch = PolicyDataset(steps, num_points=16, num_goal_points=8, seed=3, sample="batch")
    item = PolicyDataset(steps, num_points=16, num_goal_points=8, seed=3, sample="batch")[0]  # its own counter
    assert set(item) >= {"cloud", "cloud_mask", "start"} and "points" not in item
    fields = ("points", "labels", "valid", "history", "goal", "goal_labels", "goal_valid", "mask", "prev_mask",
              "has_prev")
    for epoch in range(2):  # the second epoch draws other starts in both
        for a, b in zip(torch.utils.data.DataLoader(loader, batch_size=4),
                        torch.utils.data.DataLoader(batch, batch_size=4)):
            b = sample_batch(b, 16)
            assert set(b) == set(a)
            for k in fields:
                assert b[k].dtype == a[k].dtype and torch.equal(b[k], a[k]), (epoch, k)
    assert not loader[3]["valid"].all() and loader[1]["has_prev"] and not loader[0]["has_prev"]
    done = sample_batch(b, 16)
    assert done is b  # a batch without clouds passes through
    assert PolicyDataset(steps, num_points=256, sample="batch").sample == "loader"  # 200 points: padded copies
    for k in ("x_t", "f_t", "mask"):
        steps[5][k] = steps[5][k][:100]
    mixed = PolicyDataset(steps, num_points=16, sample="batch")  # a batch stacks one size: the loader's FPS
    assert mixed.sample == "loader" and "points" in mixed[5]

"""DP3 / 3D Diffuser Actor baselines: diffusion maths, action representation, training, acting."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from topocut.policies.baselines.diffuser_actor import RelativeAttention
from topocut.policies.baselines.module import (
    GaussianDiffusion,
    PoseDiffusionModule,
    PosePolicy,
    PoseStepDataset,
    action_stats,
    decode_action,
    encode_action,
    load_pose_policy,
)
from topocut.sim.action import KnifeAction

N = 64  # points per cloud: equal to num_points, so no FPS is needed
SMALL = {"dp3": dict(enc_dim=32, down_dims=(32, 64, 128), horizon=4),
         "3dda": dict(dim=48, heads=2, layers=1, context_layers=1)}


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


# -- diffusion maths -------------------------------------------------------------------------------------
def test_cosine_schedule_matches_formula():
    T, s = 100, 0.008
    d = GaussianDiffusion(T)
    f = lambda t: math.cos((t / T + s) / (1 + s) * math.pi / 2) ** 2  # noqa: E731
    expect = np.array([f(t + 1) / f(0) for t in range(T - 1)])  # abar_t = f(t+1)/f(0) before the beta clip
    np.testing.assert_allclose(d.abar[:-1].numpy(), expect, rtol=1e-4, atol=1e-7)
    assert float(d.betas.max()) <= 0.999 + 1e-6 and torch.all(d.betas > 0)


def test_forward_noising_marginal_matches_closed_form():
    """Running the one-step chain x_t = sqrt(1-b_t) x_{t-1} + sqrt(b_t) z gives N(sqrt(abar) x0, 1-abar)."""
    torch.manual_seed(0)
    d, x0, M = GaussianDiffusion(50), 0.7, 200_000
    x = torch.full((M,), x0, dtype=torch.float64)
    for t in range(30):
        b = float(d.betas[t])
        x = math.sqrt(1 - b) * x + math.sqrt(b) * torch.randn(M, dtype=torch.float64)
        if t in (0, 9, 29):
            ab = float(np.prod(1 - d.betas[: t + 1].double().numpy()))
            assert abs(x.mean().item() - math.sqrt(ab) * x0) < 5e-3
            assert abs(x.var().item() - (1 - ab)) < 5e-3
            q = d.q_sample(torch.full((M,), x0), torch.full((M,), t), torch.randn(M))  # the closed form
            assert abs(q.mean().item() - x.mean().item()) < 7e-3 and abs(q.var().item() - x.var().item()) < 7e-3


@pytest.mark.parametrize("steps,eta", [(100, 0.0), (100, 1.0), (10, 0.0)])
def test_ddim_recovers_point_mass_with_perfect_noise_predictor(steps, eta):
    d = GaussianDiffusion(100)
    star = torch.tensor([0.3, -0.7, 0.9])

    def eps_fn(x, t):  # exact for data = delta(star): x_t = sqrt(abar) star + sqrt(1-abar) eps
        a = d.abar[t].view(-1, 1, 1)
        return (x - a.sqrt() * star) / (1 - a).sqrt()

    out = d.sample(eps_fn, (5, 2, 3), steps=steps, eta=eta, generator=torch.Generator().manual_seed(0), clip=None)
    torch.testing.assert_close(out, star.expand(5, 2, 3), atol=1e-4, rtol=0)


# -- action representation ---------------------------------------------------------------------------------
def test_action_representation_round_trip_and_plane_uniqueness():
    rng = np.random.default_rng(0)
    c = np.array([0.5, 0.45, 0.1])
    for _ in range(50):
        a = KnifeAction(*rng.uniform([0.3, 0.3, -1.57, -0.5], [0.7, 0.7, 1.57, 0.5])).canonical()
        b = decode_action(encode_action(a.to_vector(), c, 0.15), c, 0.15)
        np.testing.assert_allclose(b.normal, a.normal, atol=1e-5)
        assert abs(b.x - a.x) < 1e-5 and abs(b.y - a.y) < 1e-5
        # the same plane written with yaw + pi and -tilt has the same representation
        flipped = [a.x, a.y, a.yaw + math.pi, -a.tilt]
        np.testing.assert_allclose(encode_action(flipped, c, 0.15), encode_action(a.to_vector(), c, 0.15), atol=1e-6)


def test_rotary_attention_is_relative():
    torch.manual_seed(0)
    att = RelativeAttention(24, 2)
    q, k = torch.randn(2, 3, 24), torch.randn(2, 7, 24)
    pq, pk, shift = torch.randn(2, 3, 3), torch.randn(2, 7, 3), torch.tensor([0.4, -1.3, 2.0])
    out = att(q, pq, k, pk)
    torch.testing.assert_close(att(q, pq + shift, k, pk + shift), out, atol=1e-5, rtol=1e-5)
    assert (att(q, pq, k, pk + shift) - out).abs().max() > 1e-2  # moving only the keys changes it


# -- training and acting -----------------------------------------------------------------------------------
def _steps(n, seed=0):
    """Boxes around random centres; the demonstrated cut is 2 cm right of the centre at yaw 0.3."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        c = rng.uniform(0.45, 0.55, 2)
        pts = np.concatenate([rng.uniform(-0.1, 0.1, (N, 2)) + c, rng.uniform(0.05, 0.15, (N, 1))], 1)
        out.append(dict(x_t=pts.astype(np.float32), f_t=np.zeros(N, np.int32), goal=pts.astype(np.float32),
                        goal_labels=np.zeros(N, np.int32), history=np.zeros((3, 7), np.float32),
                        action=np.array([c[0] + 0.02, c[1], 0.3, 0.0], np.float32)))
    return out


def _module(kind, steps):
    torch.manual_seed(0)
    m = PoseDiffusionModule(kind=kind, num_points=N, num_goal_points=N, num_train_steps=50, lr=1e-3, **SMALL[kind])
    m.set_action_stats(action_stats(steps))
    return m


@pytest.mark.parametrize("kind", ["dp3", "3dda"])
def test_training_reduces_loss_and_act_returns_valid_action(kind, tmp_path):
    import lightning as L

    steps = _steps(32)
    m = _module(kind, steps)
    ds = PoseStepDataset(steps, N, N)
    batch = torch.utils.data.default_collate([ds[i] for i in range(len(ds))])
    fixed = lambda: m.compute_loss(batch, torch.Generator().manual_seed(1)).item()  # noqa: E731 same t and noise
    before = fixed()
    opt = m.configure_optimizers()
    for _ in range(40):
        loss = m.compute_loss(batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert fixed() < 0.7 * before

    s = steps[0]
    obs = dict(points=s["x_t"], labels=s["f_t"], history=s["history"], goal=s["goal"], goal_labels=s["goal_labels"])
    pol = PosePolicy(m, seed=3)
    with pytest.raises(RuntimeError, match="reset"):
        pol.act(obs)
    pol.reset(None)
    a = pol.act(obs)
    assert isinstance(a, KnifeAction) and np.all(np.isfinite(a.to_vector()))
    assert -math.pi / 2 < a.yaw <= math.pi / 2 and abs(a.tilt) < math.pi / 2
    lo, hi = s["x_t"].min(0), s["x_t"].max(0)  # the cut point lies over the object
    assert lo[0] - 0.05 < a.x < hi[0] + 0.05 and lo[1] - 0.05 < a.y < hi[1] + 0.05
    pol.reset(None)
    assert pol.act(obs) == a  # re-seeded at reset: reproducible episodes

    # Lightning loop (train/loss, val/pose_err) and checkpoint round trip
    dl = torch.utils.data.DataLoader(ds, batch_size=16)
    trainer = L.Trainer(max_steps=2, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, limit_val_batches=1, accelerator="cpu")
    trainer.fit(m, dl, dl)
    assert "val/pose_err" in trainer.callback_metrics and "train/loss" in trainer.callback_metrics
    trainer.save_checkpoint(tmp_path / "last.ckpt")
    pol2, pol = load_pose_policy(tmp_path / "last.ckpt", seed=3), PosePolicy(m, seed=3)
    pol.reset(None)
    pol2.reset(None)
    assert pol2.act(obs) == pol.act(obs)


def test_unknown_kind_names_valid_ones():
    with pytest.raises(ValueError, match="dp3, 3dda"):
        PoseDiffusionModule(kind="act")


def test_dataset_fps_downsamples():
    pytest.importorskip("topocut.metrics")
    steps = _steps(2)
    big = dict(steps[0], x_t=np.repeat(steps[0]["x_t"], 4, 0) + 1e-3 * np.arange(4 * N)[:, None],
               f_t=np.zeros(4 * N, np.int32))
    item = PoseStepDataset([big], N, N)[0]
    assert item["points"].shape == (N, 3) and item["labels"].shape == (N,)
    center = big["x_t"].mean(0)
    np.testing.assert_allclose(item["center"], center, atol=1e-6)
    np.testing.assert_allclose(item["action"][:2], (big["action"][:2] - center[:2]) / 0.15, atol=1e-5)


def test_3dda_attends_to_a_padded_point_once():
    """A 5-point cloud padded to 8 rows by copies: with prepare_inputs' valid masks the network's output equals
    its output on the 5 unique points (copies are identical keys; masking all but one is exact); unmasked, the
    copied points weigh twice and the output moves."""
    from topocut.policies.baselines.diffuser_actor import DiffuserActorNet
    from topocut.policies.baselines.module import prepare_inputs

    rng = np.random.default_rng(0)
    pts, goal = rng.normal(0.5, 0.05, (5, 3)), rng.normal(0.5, 0.05, (4, 3))
    labels, glabels, hist = np.array([0, 0, 1, 1, 2]), np.array([0, 1, 1, 2]), np.zeros((3, 7), np.float32)
    torch.manual_seed(0)
    net = DiffuserActorNet(dim=48, heads=2, layers=2, context_layers=2).eval()

    def out(n, g, masked=True):
        inp = prepare_inputs(pts, labels, goal, glabels, hist, num_points=n, num_goal_points=g)
        if not masked:
            inp.pop("valid"), inp.pop("goal_valid")
        batch = {k: torch.as_tensor(np.asarray(v))[None] for k, v in inp.items()}
        x = torch.full((1, 1, 6), 0.1)
        with torch.no_grad():
            return net.denoise(x, torch.tensor([3]), net.encode(batch), x)

    padded = prepare_inputs(pts, labels, goal, glabels, hist, num_points=8, num_goal_points=6)
    assert padded["valid"].sum() == 5 and padded["goal_valid"].sum() == 4
    exact = out(5, 4)
    torch.testing.assert_close(out(8, 6), exact, atol=1e-5, rtol=1e-5)
    assert (out(8, 6, masked=False) - exact).abs().max() > 1e-4

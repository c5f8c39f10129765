"""Score-entropy discrete diffusion maths, checked against independent evaluations (scipy expm, explicit loops)."""
import itertools
import math

import numpy as np
import pytest
import scipy.linalg
import torch

from topocut.policies.diffusion import (
    Absorbing,
    GeometricNoise,
    LogLinearNoise,
    Uniform,
    dse_loss,
    get_loss,
    sample,
    sq_score_loss,
)


def dense_Q(graph):
    """Rate matrices written out by hand, Q[y, x] = rate x -> y."""
    d = graph.dim
    if isinstance(graph, Uniform):
        return np.full((d, d), 1.0 / d) - np.eye(d)
    Q = np.zeros((d, d))
    for x in range(d - 1):
        Q[d - 1, x], Q[x, x] = 1.0, -1.0
    return Q


GRAPHS = [Uniform(2), Uniform(3), Absorbing(2)]


@pytest.mark.parametrize("graph", GRAPHS, ids=lambda g: f"{type(g).__name__}{g.dim}")
def test_rates_and_transitions_match_expm(graph):
    Q = dense_Q(graph)
    np.testing.assert_allclose(graph.rate_matrix().numpy(), Q)
    d = graph.dim
    states = torch.arange(d)  # every state, the absorbing graph's mask included (its column: stay w.p. 1)
    for sigma in (0.05, 0.7, 3.0):
        P = scipy.linalg.expm(sigma * Q)  # P[y, x] = p(x_t = y | x_0 = x)
        s = torch.full((len(states),), sigma, dtype=torch.float64)
        np.testing.assert_allclose(graph.transition(states, s).numpy(), P[:, states.numpy()].T, atol=1e-12)
        rows = torch.arange(d)
        np.testing.assert_allclose(graph.transp_transition(rows, torch.full((d,), sigma, dtype=torch.float64)).numpy(),
                                   P, atol=1e-12)


@pytest.mark.parametrize("graph", GRAPHS, ids=lambda g: f"{type(g).__name__}{g.dim}")
def test_forward_marginals_monte_carlo(graph):
    """Sampled transitions x_0 -> x_t have the frequencies of exp(sigma Q)."""
    gen = torch.Generator().manual_seed(0)
    n = 40000
    for x0 in range(graph.dim - 1 if graph.absorb else graph.dim):
        for sigma in (0.2, 1.5):
            xt = graph.sample_transition(torch.full((n,), x0), torch.tensor(sigma), gen)
            freq = np.bincount(xt.numpy(), minlength=graph.dim) / n
            P = scipy.linalg.expm(sigma * dense_Q(graph))[:, x0]
            assert np.abs(freq - P).max() < 4 * math.sqrt(0.25 / n), (freq, P)


def reference_dse(score, sigma, x, x0, Q):
    """SEDD's denoising score entropy written out with loops:
    sum_{y != x} Q[x, y] (e^{s_y} - r_y s_y + r_y (log r_y - 1)),  r_y = P[y, x0] / P[x, x0]."""
    out = np.zeros(x.shape)
    for b, i in itertools.product(range(x.shape[0]), range(x.shape[1])):
        P = scipy.linalg.expm(sigma[b] * Q)
        xi, x0i = x[b, i], x0[b, i]
        for y in range(Q.shape[0]):
            if y == xi or Q[xi, y] == 0:
                continue
            r = P[y, x0i] / P[xi, x0i]
            K = r * (math.log(r) - 1) if r > 0 else 0.0
            out[b, i] += Q[xi, y] * (math.exp(score[b, i, y]) - r * score[b, i, y] + K)
    return out


@pytest.mark.parametrize("graph", GRAPHS, ids=lambda g: f"{type(g).__name__}{g.dim}")
def test_score_entropy_matches_reference(graph):
    rng = np.random.default_rng(1)
    B, N, d = 3, 7, graph.dim
    x0 = rng.integers(0, d - 1 if graph.absorb else d, (B, N))
    x = np.where(rng.random((B, N)) < 0.5, x0, rng.integers(0, d, (B, N)))
    score = rng.normal(size=(B, N, d))
    sigma = np.array([0.01, 0.6, 4.0])
    got = graph.score_entropy(torch.tensor(score), torch.tensor(sigma)[:, None], torch.tensor(x), torch.tensor(x0))
    ref = reference_dse(score, sigma, x, x0, dense_Q(graph))
    np.testing.assert_allclose(got.numpy(), ref, rtol=1e-9, atol=1e-9)
    assert (got >= -1e-9).all()
    # at the conditional ratio the integrand vanishes (the score entropy's minimum)
    r = graph.cond_ratio(torch.tensor(x), torch.tensor(x0), torch.tensor(sigma)[:, None])
    zero = graph.score_entropy(torch.log(r.clamp_min(1e-300)), torch.tensor(sigma)[:, None], torch.tensor(x),
                               torch.tensor(x0))
    np.testing.assert_allclose(zero.numpy(), 0.0, atol=1e-9)


@pytest.mark.parametrize("graph", [Uniform(2), Absorbing(2)], ids=["uniform", "absorbing"])
@pytest.mark.parametrize("noise", [LogLinearNoise(1e-3), GeometricNoise(1e-3, 5.0)], ids=["loglinear", "geometric"])
def test_dse_loss_is_dsigma_weighted_sum(graph, noise):
    """dse_loss = sum_i sigma'(t) * integrand at the perturbed state it fed the model; sq loss likewise."""
    gen = torch.Generator().manual_seed(3)
    B, N = 4, 6
    x0 = torch.randint(0, 2, (B, N), generator=gen)
    W = torch.randn(graph.dim, graph.dim, dtype=torch.float64, generator=gen)
    seen = {}

    def model_fn(xt, sigma, cond):
        seen["xt"], seen["sigma"] = xt.clone(), sigma.clone()
        return torch.nn.functional.one_hot(xt, graph.dim).double() @ W + cond * sigma[:, None, None]

    t = torch.tensor([0.1, 0.4, 0.7, 0.95], dtype=torch.float64)
    loss = dse_loss(model_fn, x0, 0.3, graph, noise, t=t, generator=gen)
    score = model_fn(seen["xt"], seen["sigma"], 0.3).numpy()
    sig, dsig = noise.total_noise(t).numpy(), noise.rate_noise(t).numpy()
    ref = reference_dse(score, sig, seen["xt"].numpy(), x0.numpy(), dense_Q(graph))
    np.testing.assert_allclose(loss.numpy(), (dsig[:, None] * ref).sum(1), rtol=1e-9)
    # schedules: rate is the derivative of total noise
    h = 1e-6
    np.testing.assert_allclose(dsig, (noise.total_noise(t + h) - noise.total_noise(t - h)).numpy() / (2 * h), rtol=1e-5)

    sq = sq_score_loss(model_fn, x0, 0.3, graph, noise, t=t, generator=gen)
    xt, Q = seen["xt"].numpy(), dense_Q(graph)
    score = model_fn(seen["xt"], seen["sigma"], 0.3).numpy()
    ref = np.zeros(B)
    for b, i in itertools.product(range(B), range(N)):
        P = scipy.linalg.expm(sig[b] * Q)
        for y in range(graph.dim):
            if y != xt[b, i]:
                r = P[y, x0[b, i]] / P[xt[b, i], x0[b, i]]
                ref[b] += dsig[b] * Q[xt[b, i], y] * (math.exp(score[b, i, y]) - r) ** 2
    np.testing.assert_allclose(sq.numpy(), ref, rtol=1e-9)
    assert get_loss("dse") is dse_loss
    with pytest.raises(ValueError, match="dse"):
        get_loss("mse")


def exact_joint_model(graph, p0_joint):
    """Perfect log-score of a 2-position data distribution p0_joint (K,K) over data states K."""
    Q = torch.tensor(dense_Q(graph))
    d = graph.dim
    p0 = torch.zeros(d, d, dtype=torch.float64)
    K = p0_joint.shape[0]
    p0[:K, :K] = torch.tensor(p0_joint)

    def model_fn(x, sigma, cond):  # x B,2
        P = torch.matrix_exp(sigma[0].double() * Q)  # P[y, x0]; the sampler uses one sigma per call
        pt = P @ p0 @ P.T  # pt[a, b] = p_t(x_1 = a, x_2 = b)
        a, c = x[:, 0], x[:, 1]
        cur = pt[a, c][:, None]  # B,1
        return torch.stack([pt[:, c].T / cur, pt[a, :] / cur], 1).log().float()  # B,2,d

    return model_fn


@pytest.mark.parametrize("predictor,steps", [("analytic", 32), ("euler", 128)])
@pytest.mark.parametrize("graph,noise", [(Uniform(2), LogLinearNoise(1e-3)), (Uniform(2), GeometricNoise(1e-4, 12.0)),
                                         (Absorbing(2), LogLinearNoise(1e-3))],
                         ids=["uniform-loglinear", "uniform-geometric", "absorbing-loglinear"])
def test_sampler_recovers_joint_distribution(graph, noise, predictor, steps):
    """With the exact score of a correlated 2-position distribution the sampler reproduces it (chi^2 test)."""
    p0 = np.array([[0.45, 0.05], [0.15, 0.35]])
    n = 3000
    gen = torch.Generator().manual_seed(7)
    x = sample(exact_joint_model(graph, p0), graph, noise, (n, 2), steps=steps, predictor=predictor,
               generator=gen)
    assert x.max() < 2  # no mask state left
    counts = np.bincount((x[:, 0] * 2 + x[:, 1]).numpy(), minlength=4)
    expected = n * p0.reshape(-1)
    chi2 = ((counts - expected) ** 2 / expected).sum()
    assert chi2 < 16.3, (counts / n, p0.reshape(-1))  # 3 dof, p = 0.001


def test_sampler_independent_bernoulli():
    """N independent positions with known P(1) = p_i."""
    graph, noise = Uniform(2), LogLinearNoise(1e-3)
    p = torch.linspace(0.05, 0.95, 8, dtype=torch.float64)
    Q = torch.tensor(dense_Q(graph))

    def model_fn(x, sigma, cond):
        P = torch.matrix_exp(sigma[0].double() * Q)
        pt = torch.stack([1 - p, p], -1) @ P.T  # N,2 marginals at sigma
        pt = pt[None].expand(x.shape[0], -1, -1)
        ratio = pt / pt.gather(-1, x[..., None])  # B,N,2
        return ratio.log().float()

    n = 4000
    x = sample(model_fn, graph, noise, (n, 8), steps=16, generator=torch.Generator().manual_seed(2))
    freq = x.double().mean(0)
    assert (freq - p).abs().max() < 4 * math.sqrt(0.25 / n), (freq, p)


@pytest.mark.parametrize("graph", [Uniform(2), Absorbing(2)], ids=["uniform", "absorbing"])
def test_denoiser_parametrisation_gives_exact_scores(graph):
    """With pi = p(x0_1 | x_2,t) (the clean posterior of one position given the other) the log-scores
    from score_from_denoiser equal the exact ratios of the joint 2-position marginal."""
    p0 = np.array([[0.45, 0.05], [0.15, 0.35]])
    d = graph.dim
    for sigma in (0.05, 0.8, 3.0):
        P = scipy.linalg.expm(sigma * dense_Q(graph))  # P[y, c]
        pt = P[:, :2] @ p0 @ P[:, :2].T  # p_t(x1, x2)
        for a, b in itertools.product(range(d), range(d)):
            if pt[a, b] <= 0 or (graph.absorb and a != graph.mask):
                continue  # an unmasked absorbing state has no reverse jumps: its scores are unused
            post = p0 @ P[b, :2]  # p(x0_1 = c, x_2,t = b) up to normalisation
            log_pi = torch.tensor(np.log(post / post.sum()))[None]
            got = graph.score_from_denoiser(log_pi, torch.tensor([a]), torch.tensor([sigma], dtype=torch.float64))
            exact = np.log(pt[:, b] / pt[a, b])
            keep = pt[:, b] > 0
            np.testing.assert_allclose(got[0].numpy()[keep], exact[keep], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("loss_fn", [dse_loss, sq_score_loss], ids=["dse", "sq"])
def test_padding_positions_carry_no_loss(loss_fn):
    """valid=False positions (copies FPS padding adds to a small cloud) drop out of the per-sample sum: the
    masked loss equals the unmasked one minus exactly the padded positions' terms (same seed, same x_t)."""
    graph, noise = Uniform(2), LogLinearNoise(1e-3)
    B, N = 3, 5
    x0 = torch.randint(0, 2, (B, N), generator=torch.Generator().manual_seed(0))
    W = torch.randn(2, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    model_fn = lambda xt, sigma, cond: torch.nn.functional.one_hot(xt, 2).double() @ W  # noqa: E731
    t = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    valid = torch.ones(B, N, dtype=torch.bool)
    valid[0, 3:] = False  # sample 0: 3 points padded to 5
    valid[2, 4] = False
    run = lambda v: loss_fn(model_fn, x0, None, graph, noise, t=t, generator=torch.Generator().manual_seed(7),  # noqa: E731
                            valid=v)
    full, masked, pad_only = run(None), run(valid), run(~valid)
    np.testing.assert_allclose((masked + pad_only).numpy(), full.numpy(), rtol=1e-12)
    assert pad_only[1] == 0 and pad_only[0] > 0 and pad_only[2] > 0  # sample 1 has no padding


def test_policy_dataset_marks_padding_copies():
    """A 3-point cloud asked for 8 points: each real point is valid once, the 5 copies are not."""
    from topocut.policies.module import PolicyDataset

    x = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    step = {"x_t": x, "f_t": np.zeros(3, np.int32), "mask": np.array([1, 0, 1]), "history": np.zeros((3, 7)),
            "goal": np.eye(3, dtype=np.float32)}
    item = PolicyDataset([step], num_points=8, num_goal_points=3)[0]
    valid = item["valid"].numpy()
    assert valid.sum() == 3 and len(valid) == 8
    assert sorted(map(tuple, item["points"].numpy()[valid])) == sorted(map(tuple, x))
    assert item["mask"].numpy()[valid].sum() == 2

"""Reverse-time samplers for score-entropy discrete diffusion.

Time runs from t = 1 (limit distribution) to t = eps in ``steps`` equal steps,
then an optional final denoising step removes the remaining noise sigma(eps).

* Euler:    x_{t-dt} ~ onehot(x) + dt sigma'(t) R(x),  R the reverse rate Q[x, y] s_y.
* Analytic: Tweedie tau-leaping, exact for one position given the others:
            p(x_{t-dt} = y | x_t = x) ∝ [exp(-ds Q) s(x)]_y · exp(ds Q)[x, y],  ds = sigma(t) - sigma(t-dt).

``model_fn(x (B,N) long, sigma (B,), cond) -> log-scores (B,N,d)``; the log-score at
the current state must be 0 (ratio 1), as the network enforces.

``generator``: one torch.Generator, or a list of B, one per row (``topocut.policies.diffusion.rng``): row b then
draws exactly the noise a batch-1 call with generator b draws, so B independent chains can share one network
batch (``PDDPPolicy.act_batch``) and still equal their one-at-a-time runs.
"""
from __future__ import annotations

import torch

from topocut.policies.diffusion.graph import Graph, sample_categorical
from topocut.policies.diffusion.noise import Noise
from topocut.policies.diffusion.rng import Generators

PREDICTORS = ("analytic", "euler")


def euler_update(model_fn, graph: Graph, noise: Noise, x, t: float, dt: float, cond, generator=None):
    B = x.shape[0]
    tt = torch.full((B,), t, device=x.device)
    sigma, dsigma = noise(tt)  # B, B
    score = model_fn(x, sigma, cond).exp()  # B,N,d
    rate = (dt * dsigma)[:, None, None] * graph.reverse_rate(x, score)
    return graph.sample_rate(x, rate, generator)


def analytic_update(model_fn, graph: Graph, noise: Noise, x, t: float, dt: float, cond, generator=None):
    B = x.shape[0]
    tt = torch.full((B,), t, device=x.device)
    sigma = noise.total_noise(tt)  # B
    dsig = (sigma - noise.total_noise(tt - dt))[:, None]  # B,1
    score = model_fn(x, sigma, cond).exp()  # B,N,d
    probs = graph.staggered_score(score, dsig) * graph.transp_transition(x, dsig)
    return sample_categorical(probs, generator)


def denoise_update(model_fn, graph: Graph, noise: Noise, x, t: float, cond, generator=None):
    """Tweedie step from sigma(t) straight to 0; an absorbing graph may not stay masked."""
    B = x.shape[0]
    sigma = noise.total_noise(torch.full((B,), t, device=x.device))  # B
    score = model_fn(x, sigma, cond).exp()
    probs = graph.staggered_score(score, sigma[:, None]) * graph.transp_transition(x, sigma[:, None])
    if graph.absorb:
        probs = probs[..., :-1]
    return sample_categorical(probs, generator)


@torch.no_grad()
def sample(model_fn, graph: Graph, noise: Noise, shape: tuple[int, int], cond=None, steps: int = 32,
           predictor: str = "analytic", denoise: bool = True, eps: float = 1e-5, device=None,
           generator: Generators = None) -> torch.Tensor:
    """Draw states (B,N) long from the reverse chain."""
    if predictor not in PREDICTORS:
        raise ValueError(f"predictor={predictor!r} is not valid; choose one of {', '.join(PREDICTORS)}")
    if steps < 1:
        raise ValueError(f"steps={steps} must be >= 1")
    update = analytic_update if predictor == "analytic" else euler_update
    x = graph.sample_limit(*shape, device=device, generator=generator)
    dt = (1.0 - eps) / steps
    for k in range(steps):
        x = update(model_fn, graph, noise, x, 1.0 - k * dt, dt, cond, generator)
    if denoise:
        x = denoise_update(model_fn, graph, noise, x, eps, cond, generator)
    return x

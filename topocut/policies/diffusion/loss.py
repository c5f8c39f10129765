"""Training objectives for score-entropy discrete diffusion.

``model_fn(x_t (B,N) long, sigma (B,), cond) -> log-scores (B,N,d)``.

Default: denoising score entropy (Lou et al. 2024, eq. DSE), integrated over
t ~ U(eps, 1) with the weight sigma'(t), summed over positions:

    L = E_t E_{x_t ~ p(.|x_0)} sigma'(t) sum_i sum_{y != x_i} Q[x_i, y]
          ( s_y - r_y log s_y + K(r_y) ),    r_y = p(y | x0_i) / p(x_i | x0_i),  K(a) = a (log a - 1).

Ablation "sq": the squared-error objective printed in the paper, taken in ratio
space so that its minimiser is still the true concrete score:
sigma'(t) sum_{y != x} Q[x, y] (s_y - r_y)^2.  (Its targets blow up like 1/sigma near t = 0,
which is why score entropy is the default.)
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from topocut.policies.diffusion import rng
from topocut.policies.diffusion.graph import Graph
from topocut.policies.diffusion.noise import Noise


def _perturb(x0, graph: Graph, noise: Noise, t, sampling_eps, generator):
    B = x0.shape[0]
    if t is None:
        t = (1.0 - sampling_eps) * rng.rand((B,), generator, device=x0.device) + sampling_eps
    sigma, dsigma = noise(t)  # B, B
    xt = graph.sample_transition(x0, sigma[:, None], generator)  # B,N
    return xt, sigma, dsigma


def _weights(valid, like: torch.Tensor) -> torch.Tensor | float:
    """Per-position weights (B,N): 0 on padding copies of a point (``valid`` False), so none counts twice."""
    return 1.0 if valid is None else valid.to(like.dtype)


def dse_loss(model_fn, x0: torch.Tensor, cond, graph: Graph, noise: Noise, t: torch.Tensor | None = None,
             sampling_eps: float = 1e-3, generator: torch.Generator | None = None,
             valid: torch.Tensor | None = None) -> torch.Tensor:
    """Denoising score-entropy loss per sample (B,) for clean states x0 (B,N), summed over valid positions."""
    xt, sigma, dsigma = _perturb(x0, graph, noise, t, sampling_eps, generator)
    log_score = model_fn(xt, sigma, cond)  # B,N,d
    ent = graph.score_entropy(log_score, sigma[:, None], xt, x0)  # B,N
    return (dsigma[:, None] * ent * _weights(valid, ent)).sum(-1)


def sq_score_loss(model_fn, x0: torch.Tensor, cond, graph: Graph, noise: Noise, t: torch.Tensor | None = None,
                  sampling_eps: float = 1e-3, generator: torch.Generator | None = None,
                  valid: torch.Tensor | None = None) -> torch.Tensor:
    """Squared error between predicted and conditional ratios (ablation), per sample (B,)."""
    xt, sigma, dsigma = _perturb(x0, graph, noise, t, sampling_eps, generator)
    log_score = model_fn(xt, sigma, cond)  # B,N,d
    r = graph.cond_ratio(xt, x0, sigma[:, None])  # B,N,d
    w = graph.transp_rate(xt).to(r) * (1.0 - F.one_hot(xt, graph.dim).to(r))  # Q[x, y], y != x
    err = (w * (log_score.exp() - r) ** 2).sum(-1)  # B,N
    return (dsigma[:, None] * err * _weights(valid, err)).sum(-1)


LOSSES = {"dse": dse_loss, "sq": sq_score_loss}


def get_loss(name: str):
    if name not in LOSSES:
        raise ValueError(f"loss={name!r} is not valid; choose one of {', '.join(LOSSES)}")
    return LOSSES[name]

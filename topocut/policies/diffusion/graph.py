"""Transition graphs of a continuous-time Markov chain over the states {0..d-1} of each position.

Score Entropy Discrete Diffusion (Lou et al. 2024): every position x_i of a
sequence diffuses independently under  dp_t/dt = sigma'(t) Q p_t, so that

    p(x_t = y | x_0 = i) = [exp(sigma(t) Q)]_{y,i}            (columns = source state)

Q is the rate matrix: Q[y, x] >= 0 is the rate x -> y and each column sums to 0.
The network predicts, per position, the *concrete score* s(x)_y = p_t(y) / p_t(x)
(x with position i changed to y) as a log-score; the reverse chain jumps
x -> y at rate  sigma'(t) Q[x, y] s(x)_y.

Two graphs:
  * Uniform(d): Q = 11^T/d - I.  For d = 2 a jump is a bit flip: the paper's bit-flip noise.
  * Absorbing(d): d data states plus a mask state m = d; Q[m, x] = 1, Q[x, x] = -1.

Tensor conventions: states ``i`` are long tensors of any shape (B,N); ``sigma``
broadcasts against them (e.g. (B,1)); vector-valued outputs add a trailing
axis of size ``dim``.  Every ``generator`` is one torch.Generator or one per row of
the leading axis (``topocut.policies.diffusion.rng``).
"""
from __future__ import annotations

import abc
import math

import torch
import torch.nn.functional as F

from topocut.policies.diffusion import rng
from topocut.policies.diffusion.rng import Generators


def sample_categorical(probs: torch.Tensor, generator: Generators = None) -> torch.Tensor:
    """Sample indices from unnormalised non-negative weights along the last axis (negatives clamp to 0).

    ``generator``: one, or one per row of the leading (batch) axis (``topocut.policies.diffusion.rng``)."""
    p = probs.clamp_min(0.0)
    c = p.cumsum(-1)  # ...,d
    u = rng.rand(c.shape[:-1], generator, device=p.device, dtype=c.dtype) * c[..., -1]
    idx = (c <= u[..., None]).sum(-1)  # first index whose cumulative weight exceeds u
    return idx.clamp_max(p.shape[-1] - 1)


def _expm1(sigma: torch.Tensor) -> torch.Tensor:
    return torch.expm1(sigma)


def _xlogx_minus_x(r: torch.Tensor) -> torch.Tensor:
    """K(r) = r (log r - 1), with K(0) = 0: the constant that makes score entropy >= 0."""
    return torch.xlogy(r, r) - r


class Graph(abc.ABC):
    dim: int  # number of states seen by the network (including a mask state)
    num_data: int  # number of data states (the mask labels' classes)
    absorb: bool  # whether a mask state follows the data states
    min_data: int  # the fewest data states the graph is defined on

    def __init__(self, dim: int):
        """``dim`` data states, and after them the mask state of an absorbing graph."""
        if dim < self.min_data:
            raise ValueError(f"{type(self).__name__} graph needs dim >= {self.min_data}, got {dim}")
        self.num_data = int(dim)
        self.dim = self.num_data + int(self.absorb)

    # -- rate matrix --------------------------------------------------------
    @abc.abstractmethod
    def rate_matrix(self) -> torch.Tensor:  # d,d  Q[y, x] = rate x -> y
        """The dense rate matrix."""

    def rate(self, i: torch.Tensor) -> torch.Tensor:  # ...,d  column i of Q (rates out of i)
        return self.rate_matrix().to(i.device)[:, i].movedim(0, -1)

    def transp_rate(self, i: torch.Tensor) -> torch.Tensor:  # ...,d  row i of Q: Q[i, y], rates into i
        return self.rate_matrix().to(i.device)[i]

    # -- reverse process ----------------------------------------------------
    def reverse_rate(self, i: torch.Tensor, score: torch.Tensor) -> torch.Tensor:
        """Reverse-chain rates out of i, R[y] = Q[i, y] s_y for y != i, R[i] = -sum (score = ratios, ...,d)."""
        r = self.transp_rate(i).to(score.dtype) * score
        r = r.scatter(-1, i[..., None], torch.zeros_like(r[..., :1]))
        return r.scatter(-1, i[..., None], -r.sum(-1, keepdim=True))

    def sample_rate(self, i: torch.Tensor, rate: torch.Tensor, generator=None) -> torch.Tensor:
        """One Euler step of a chain at i with jump probabilities ``rate`` (diagonal = -total)."""
        return sample_categorical(F.one_hot(i, self.dim).to(rate) + rate, generator)

    def cond_ratio(self, x: torch.Tensor, x0: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
        """p(y | x0) / p(x | x0) for every y (...,d): the denoising target of the score at x."""
        p = self.transition(x0, sigma)  # ...,d
        return p / p.gather(-1, x[..., None])

    # graph-specific pieces
    @abc.abstractmethod
    def transition(self, i, sigma):
        """Column i of exp(sigma Q): p(x_t = . | x_0 = i), (...,d)."""

    @abc.abstractmethod
    def transp_transition(self, i, sigma):
        """Row i of exp(sigma Q): p(x_t = i | x_0 = .), (...,d)."""

    @abc.abstractmethod
    def sample_transition(self, i, sigma, generator=None):
        """Draw x_t ~ p(. | x_0 = i)."""

    @abc.abstractmethod
    def staggered_score(self, score, dsigma):
        """exp(-dsigma Q) applied to the ratio vector (Tweedie step)."""

    @abc.abstractmethod
    def sample_limit(self, *shape, device=None, generator=None):
        """Draw from the limiting distribution sigma -> infinity."""

    @abc.abstractmethod
    def score_entropy(self, score, sigma, x, x0):
        """Denoising score-entropy integrand per position for log-scores (...,d)."""

    @abc.abstractmethod
    def forward_log_marginal(self, log_pi, sigma):
        """log p_sigma(y) = log sum_c pi_c p(y | c) for a clean distribution log pi (...,K) -> (...,d)."""

    def score_from_denoiser(self, log_pi, x, sigma):
        """Log-scores (...,d) of the per-position model "x_0 ~ pi, then noise":  s_y = log p_sigma(y) - log p_sigma(x).

        Equivalently sum_c p(c | x_t) p(y | c)/p(x | c) with the posterior p(c | x_t) ∝ pi_c p(x | c), so the
        likelihood of the observed noisy state is built in exactly and the network only predicts pi
        (exact when the positions are independent given the condition).
        """
        lm = self.forward_log_marginal(log_pi, sigma.expand(x.shape)[..., None])  # ...,d
        return lm - lm.gather(-1, x[..., None])

    @abc.abstractmethod
    def log_score_offset(self, sigma):
        """sigma-dependent baseline added to the network's log-scores (scale_by_sigma)."""


class Uniform(Graph):
    """Every state jumps to every other at rate 1/d.  exp(sigma Q) = e^-s I + (1 - e^-s) 11^T/d."""

    absorb = False
    min_data = 2  # a lone state has nowhere to jump

    def rate_matrix(self) -> torch.Tensor:
        d = self.dim
        return torch.full((d, d), 1.0 / d) - torch.eye(d)

    def transition(self, i, sigma):
        d = self.dim
        move = (-torch.expm1(-sigma)).expand(i.shape)[..., None]  # 1 - e^-sigma
        p = (move / d).expand(*i.shape, d).clone()
        return p.scatter(-1, i[..., None], 1.0 - move * (d - 1) / d)

    def transp_transition(self, i, sigma):
        return self.transition(i, sigma)  # Q is symmetric

    def sample_transition(self, i, sigma, generator=None):
        # with prob 1 - e^-sigma resample uniformly (which may land on i again)
        move = rng.rand(i.shape, generator, device=i.device) < -torch.expm1(-sigma)
        fresh = rng.randint(0, self.dim, i.shape, generator, device=i.device)
        return torch.where(move, fresh, i)

    def staggered_score(self, score, dsigma):
        """[exp(-dsigma Q) s]_y = e^ds s_y + (1 - e^ds)/d sum_z s_z  (score ...,d of ratios, s_x = 1)."""
        e = torch.exp(dsigma)[..., None]
        return e * score + (1.0 - e) / self.dim * score.sum(-1, keepdim=True)

    def sample_limit(self, *shape, device=None, generator=None):
        return rng.randint(0, self.dim, shape, generator, device=device)

    def score_entropy(self, score, sigma, x, x0):
        """Denoising score entropy per position (...), for log-scores ``score`` (...,d).

        sum_{y != x} Q[x, y] (e^{s_y} - r_y s_y + K(r_y)),  r_y = p(y|x0)/p(x|x0), Q[x, y] = 1/d.
        x == x0: r_y = (e^s - 1)/(e^s - 1 + d) for all y != x.
        x != x0: r_{x0} = 1 + d/(e^s - 1), r_y = 1 otherwise.
        """
        d = self.dim
        em1 = _expm1(sigma).expand(x.shape)
        not_x = 1.0 - F.one_hot(x, d).to(score)  # ...,d
        pos = (score.exp() * not_x).sum(-1) / d
        sum_s = (score * not_x).sum(-1)
        s_x0 = score.gather(-1, x0[..., None]).squeeze(-1)
        r_same = em1 / (em1 + d)
        r_back = 1.0 + d / em1
        same = x == x0
        neg = torch.where(same, r_same * sum_s, sum_s + (r_back - 1.0) * s_x0) / d
        const = torch.where(same, (d - 1) * _xlogx_minus_x(r_same), _xlogx_minus_x(r_back) - (d - 2)) / d
        return pos - neg + const

    def forward_log_marginal(self, log_pi, sigma):
        d = self.dim
        stay = torch.log(torch.exp(-sigma) - torch.expm1(-sigma) / d)  # log p(y = c | c)
        move = torch.log(-torch.expm1(-sigma)) - math.log(d)  # log p(y | c), y != c
        eye = torch.eye(d, device=log_pi.device, dtype=torch.bool)
        logP = torch.where(eye, stay[..., None], move[..., None])  # ...,d(y),d(c)
        return torch.logsumexp(log_pi[..., None, :] + logP, -1)

    def log_score_offset(self, sigma):
        """log of the ratio p(y|x0)/p(x|x0) when x == x0 (the typical case): the network predicts a residual."""
        em1 = _expm1(sigma)
        return torch.log(em1) - torch.log(em1 + self.dim)


class Absorbing(Graph):
    """``dim`` data states plus a mask state (index dim): each data state is masked at rate 1."""

    absorb = True
    min_data = 1

    @property
    def mask(self) -> int:
        """The mask state's index: the one after the data states."""
        return self.num_data

    def rate_matrix(self) -> torch.Tensor:
        Q = -torch.eye(self.dim)
        Q[self.mask, :] += 1.0
        return Q  # Q[m, m] = 0: the mask is absorbing

    def transition(self, i, sigma):
        keep = torch.exp(-sigma).expand(i.shape)[..., None]
        p = F.one_hot(i, self.dim).to(keep) * keep
        p[..., self.mask] += 1.0 - keep[..., 0]  # data states: masked w.p. 1 - e^-s; the mask: keep + 1 - keep = 1
        return p

    def transp_transition(self, i, sigma):
        """Row i of exp(sigma Q): e^-s at y = i; a mask is reached from every y with 1 - e^-s (and from m with 1)."""
        keep = torch.exp(-sigma).expand(i.shape)[..., None]
        p = F.one_hot(i, self.dim).to(keep) * keep
        return p + (i == self.mask)[..., None] * (1.0 - keep)

    def sample_transition(self, i, sigma, generator=None):
        move = rng.rand(i.shape, generator, device=i.device) < -torch.expm1(-sigma)
        return torch.where(move, torch.full_like(i, self.mask), i)

    def staggered_score(self, score, dsigma):
        """exp(-ds Q) s: data entries scale by e^ds; the mask entry gets s_m + (1 - e^ds) sum_{z != m} s_z."""
        e = torch.exp(dsigma)[..., None]
        out = e * score
        extra = (1.0 - e[..., 0]) * score.sum(-1)
        out[..., self.mask] += extra  # e s_m + (1-e)(sum_data + s_m) = s_m + (1-e) sum_data
        return out

    def sample_limit(self, *shape, device=None, generator=None):
        return torch.full(shape, self.mask, dtype=torch.long, device=device)

    def score_entropy(self, score, sigma, x, x0):
        """Only masked positions carry loss: sum_{y != m} e^{s_y} - s_{x0}/(e^s - 1) + K(1/(e^s - 1))."""
        em1 = _expm1(sigma).expand(x.shape)
        r = 1.0 / em1
        pos = score[..., : self.mask].exp().sum(-1)
        neg = r * score.gather(-1, x0[..., None]).squeeze(-1)
        ent = pos - neg + _xlogx_minus_x(r)
        return torch.where(x == self.mask, ent, torch.zeros_like(ent))

    def forward_log_marginal(self, log_pi, sigma):
        """Data y: log pi_y - sigma; mask: log(1 - e^-sigma).  (For a masked x this gives SEDD's
        s_y = log pi_y - log(e^sigma - 1).)"""
        mask = torch.log(-torch.expm1(-sigma)).expand(*log_pi.shape[:-1], 1)  # sigma ...,1
        return torch.cat([log_pi - sigma, mask], -1)

    def log_score_offset(self, sigma):
        """SEDD's scale_by_sigma: a masked position unmasks to each of the d data states with ratio ~ 1/(d (e^s - 1))."""
        return -torch.log(_expm1(sigma)) - math.log(self.num_data)


GRAPHS = {"uniform": Uniform, "absorbing": Absorbing}


def build_graph(name: str, num_classes: int = 2) -> Graph:
    if name not in GRAPHS:
        raise ValueError(f"graph={name!r} is not valid; choose one of {', '.join(GRAPHS)}")
    return GRAPHS[name](num_classes)

"""Random draws from one generator, or from one generator per batch row.

A sampler that serves B independent episodes in one network batch (``PDDPPolicy.act_batch``,
``PosePolicy.act_batch``) must draw each episode's noise from that episode's own generator, in the order and
shapes its one-episode call draws it, so that the batched result equals B calls with batch 1 and leaves every
generator in the same state.  Each function here therefore takes ``generator`` as None, one torch.Generator
(drawn as torch.rand & co. would), or a sequence of B generators: row b of the (B, ...) result is then drawn
by generator b with shape (1, ...) -- exactly the draw of a batch-1 call -- and the rows are concatenated.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import torch

Generators = torch.Generator | Sequence[torch.Generator] | None


def per_row(draw: Callable[[tuple, torch.Generator | None], torch.Tensor], shape, generator: Generators):
    """``draw(shape, generator)`` over the whole batch, or row by row with one generator per row."""
    shape = tuple(shape)
    if generator is None or isinstance(generator, torch.Generator):
        return draw(shape, generator)
    gens = list(generator)
    if not shape or len(gens) != shape[0]:
        raise ValueError(f"{len(gens)} generators for a draw of shape {shape}: need one per row (shape[0])")
    row = (1, *shape[1:])
    return torch.cat([draw(row, g) for g in gens])


def rand(shape, generator: Generators = None, device=None, dtype=None) -> torch.Tensor:
    return per_row(lambda s, g: torch.rand(s, device=device, dtype=dtype, generator=g), shape, generator)


def randn(shape, generator: Generators = None, device=None, dtype=None) -> torch.Tensor:
    return per_row(lambda s, g: torch.randn(s, device=device, dtype=dtype, generator=g), shape, generator)


def randint(low: int, high: int, shape, generator: Generators = None, device=None) -> torch.Tensor:
    return per_row(lambda s, g: torch.randint(low, high, s, device=device, generator=g), shape, generator)

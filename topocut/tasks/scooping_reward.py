"""Ice-cream scooping's score (docs/tasks.md#ice-cream-scooping): the chunks in the cup against the target chunks.

The knife tasks account for every fragment (goal piece, the uncut stock, or waste: topocut.reward.matching).  That
makes no sense here: the block that stays on the board is neither stock to keep nor waste, and a chunk's material
in the cup is where it should be.  So scooping scores

* each target chunk g (one per scoop): R(d) of the cup piece matched to it (today's distance d = d_spec + d_size and
  the paper's piecewise map R, topocut.reward), the pieces and targets paired one-to-one for the largest summed R
  (``topocut.reward.match``); a target without a piece in the cup earns 0.  The size terms take the block's particle
  spacing (the scene's, which the pieces and the targets share: every particle stands for spacing^3 of material)
  rather than estimating it from each cloud's neighbour distances: the spoon's sided transfers put the particles
  its rim reaches back on the shell's surface, where they crowd (the chunk's median neighbour distance shrinks ~4%)
  while the material keeps its volume (J = det F 0.998-1.000), and the estimate read that as an 11% smaller chunk;
* what stays on the block: nothing (not waste);
* spilled material (neither in the cup nor on the block: dropped on the board, on the cup's rim, beside it): charged
  as the knife tasks charge waste, ``waste_cost * r_max`` per target chunk's worth of particles, w = N_spilled /
  mean target count (same lattice, so counts are volumes);

total = (sum_g R_g - waste_cost r_max w) / G (kappa = 1 / G, or reward.kappa), clipped to [0, r_max].  A cup piece
that matches no target (a chunk broken in two) earns nothing and costs nothing itself: the matched part is smaller
than its target, and its R shows that.  The knife tasks' mismatch cost (a wrong-shaped goal piece's material
counted as partly wasted) is not applied: the material is in the cup.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from topocut.reward import RewardConfig, distance_matrix, match, piecewise_reward


@dataclass
class ScoopReward:
    total: float  # clipped to [0, r_max]
    per_chunk: np.ndarray  # G, R(d) of the cup piece matched to each target (0: none)
    matching: list = field(default_factory=list)  # [(cup piece index, target index)]
    distances: np.ndarray | None = None  # F,G
    spilled: int = 0  # particles neither in the cup nor on the block
    spill_weight: float = 0.0  # spilled / mean target count
    unclipped: float = 0.0


def scoop_total(per_chunk, spill_weight: float, cfg: RewardConfig) -> tuple[float, float]:
    """(total, unclipped) from each target's R (G,) and the spilled material in target chunks (the module's rule)."""
    per = np.asarray(per_chunk, np.float64)
    kappa = 1.0 / len(per) if cfg.kappa is None else cfg.kappa
    unclipped = float(kappa * (per.sum() - cfg.waste_cost * cfg.r_max * spill_weight))
    return (float(np.clip(unclipped, 0.0, cfg.r_max)) if cfg.clip_total else unclipped), unclipped


def scooping_reward(cup_pieces, targets, spilled: int = 0, cfg: RewardConfig | None = None, *,
                    spacing: float) -> ScoopReward:
    """Score of the pieces in the cup (list of (n,3)) against the target chunks (list of (m,3), one per scoop) with
    ``spilled`` particles outside both cup and block; ``spacing``: the block's particle spacing (the module's
    docstring)."""
    cfg = (cfg or RewardConfig()).validate()
    if not len(targets):
        raise ValueError("scooping_reward needs at least one target chunk")
    if spilled < 0:
        raise ValueError(f"scooping_reward: spilled={spilled} must be >= 0 (a particle count)")
    G = len(targets)
    D = distance_matrix(list(cup_pieces), list(targets), cfg, spacing=spacing) if len(cup_pieces) else np.zeros((0, G))
    pairs = match(D, cfg)
    per = np.zeros(G)
    for f, g in pairs:
        per[g] = piecewise_reward(D[f, g], cfg)
    w = spilled / float(np.mean([len(t) for t in targets]))
    total, unclipped = scoop_total(per, w, cfg)
    return ScoopReward(total, per, pairs, D, int(spilled), w, unclipped)

"""Training objectives of F: L = λ_pos (CD + EMD + HD) + λ_topo L_topo (paper §3.3.1, appendix "Training Loss").

Cluster ids are arbitrary: a cut may give the new piece any id, so L_topo compares *partitions*.
For each sample the true clusters are matched to predicted classes by the Hungarian algorithm on
the cost  C[t, c] = - Σ_{i in cluster t} log softmax(logits_i)[c]  (the cross-entropy the sample would
have if cluster t were called class c), the targets are renamed by the matching and the ordinary
cross-entropy follows.  The matching is found without gradient; the loss is then exactly
min over injective renamings of the cross-entropy, hence invariant to any relabelling of the truth.
(The paper writes ℓ as a binary cross-entropy over one-hot ids; the softmax form is the same
objective for mutually exclusive clusters.)  Negative target labels (unassigned points) are ignored.
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from scipy.optimize import linear_sum_assignment

from topocut.models.config import DynamicsConfig


def _match(cost: np.ndarray) -> np.ndarray:
    """Row -> column assignment of a (K,C) cost matrix, K <= C."""
    rows, cols = linear_sum_assignment(cost)
    out = np.empty(cost.shape[0], dtype=np.int64)
    out[rows] = cols
    return out


def _cluster_ranks(target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per sample, the rank of each point's cluster id among the sample's distinct non-negative ids (ascending,
    as ``torch.unique``), -1 on ignored points, and the number K of distinct ids: (B,N) long, (B,) long.
    Sort-based, so the whole batch takes fixed-shape kernels and no host round trip."""
    keep = target >= 0
    s, order = torch.sort(target, dim=1, stable=True)  # ignored (negative) ids first
    new = s >= 0
    new[:, 1:] &= s[:, 1:] != s[:, :-1]  # first occurrence of each non-negative id
    rank_sorted = new.long().cumsum(1) - 1
    rank = torch.empty_like(rank_sorted).scatter_(1, order, rank_sorted)
    return torch.where(keep, rank, torch.full_like(rank, -1)), new.sum(1)


def _match_all(packed: np.ndarray, C: int) -> tuple[np.ndarray, bool]:
    """Hungarian matching of every sample on the host: packed (B, C*C + 1) = flattened (C,C) cost rows and the
    cluster count K in the last column -> (B,C) mapping rank -> class (unused ranks 0) and whether any K > 0."""
    B = packed.shape[0]
    perm = np.zeros((B, C), dtype=np.int64)
    counts = packed[:, -1].astype(np.int64)
    cost = packed[:, :-1].reshape(B, C, C)
    for b in range(B):
        K = int(counts[b])
        if K == 0:
            continue
        if K > C:
            raise ValueError(f"{K} true clusters exceed the {C} predicted classes (model.num_labels)")
        perm[b, :K] = _match(cost[b, :K])
    return perm, bool((counts > 0).any())


def _matched(logits: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, bool]:
    """``matched_targets`` and whether any point is labelled, with one device -> host transfer (the (B,C,C) costs
    and cluster counts) and one host -> device transfer (the (B,C) mappings) for the whole batch."""
    B, N, C = logits.shape
    if B == 0 or N == 0:
        return torch.full_like(target, -1), False
    dev = logits.device
    with torch.no_grad():
        logp = F.log_softmax(logits.detach().float(), dim=-1)  # B,N,C
        rank, counts = _cluster_ranks(target.to(dev))
        # row b*C + rank of the flat cost; ignored points and ranks >= C (an error below) go to a spare row
        ok = (rank >= 0) & (rank < C)
        row = torch.where(ok, torch.arange(B, device=dev)[:, None] * C + rank, torch.full_like(rank, B * C))
        cost = torch.zeros(B * C + 1, C, dtype=logp.dtype, device=dev).index_add_(0, row.reshape(-1),
                                                                                 -logp.reshape(B * N, C))
        packed = torch.cat([cost[:-1].reshape(B, C * C), counts[:, None].to(cost.dtype)], 1)
        perm, any_kept = _match_all(packed.cpu().numpy(), C)  # the one host round trip of the loss
        perm_t = torch.from_numpy(perm)
        if dev.type == "cuda":
            perm_t = perm_t.pin_memory().to(dev, non_blocking=True)
        else:
            perm_t = perm_t.to(dev)
        out = torch.where(rank >= 0, perm_t.gather(1, rank.clamp(min=0, max=C - 1)), torch.full_like(rank, -1))
    return out.to(target.device), any_kept


def matched_targets(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Rename each sample's target cluster ids to the predicted classes they are best matched to.

    logits (B,N,C), target (B,N) long (negative = ignore) -> (B,N) long in [0, C) or -1.
    All samples at once: the (B,C,C) cluster-to-class costs are summed on the device in one ``index_add_``
    (clusters ranked per sample by a sort; rows past a sample's K clusters stay unused), copied to the host in
    one transfer, matched there per sample by scipy (tiny problems) and the (B,C) mappings sent back in one.
    """
    return _matched(logits, target)[0]


def hungarian_cluster_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Cross-entropy after Hungarian renaming of the true clusters; logits (B,N,C), target (B,N) -> scalar."""
    t, any_kept = _matched(logits, target)
    if not any_kept:  # known on the host from the matching's transfer: no extra sync
        return logits.sum() * 0.0
    return F.cross_entropy(logits.reshape(-1, logits.shape[-1]), t.reshape(-1), ignore_index=-1)


def matched_correct(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per point, whether the predicted cluster agrees with the truth after the Hungarian matching of
    ``cluster_accuracy``: pred (B,N) long, target (B,N) long (negative = ignored) -> (B,N) bool, False on ignored
    points.  Predicted and true ids are matched one-to-one per sample to maximise the agreeing points."""
    B = pred.shape[0]
    out = torch.zeros(pred.shape, dtype=torch.bool)
    for b in range(B):
        keep = (target[b] >= 0).cpu()
        if not keep.any():
            continue
        t_ids, t_inv = np.unique(target[b][keep].cpu().numpy(), return_inverse=True)
        p_ids, p_inv = np.unique(pred[b][keep].cpu().numpy(), return_inverse=True)
        conf = np.zeros((len(t_ids), len(p_ids)))
        np.add.at(conf, (t_inv, p_inv), 1.0)
        rows, cols = linear_sum_assignment(-conf)
        match = np.full(len(p_ids), -1)  # predicted id -> its true id (-1: unmatched, always wrong)
        match[cols] = rows
        out[b, keep] = torch.from_numpy(match[p_inv] == t_inv)
    return out.to(pred.device)


def cluster_accuracy(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Fraction of points whose predicted cluster matches the truth after Hungarian matching of hard labels.

    pred (B,N) long predicted classes, target (B,N) long (negative = ignored) -> (B,) accuracy per sample (NaN for
    a sample without a labelled point).  Predicted and true ids are matched one-to-one to maximise the number of
    agreeing points, so any renaming of either side leaves the accuracy unchanged.
    """
    keep = (target >= 0).to(pred.device)
    n = keep.sum(1).to(torch.float64)
    hits = matched_correct(pred, target).sum(1).to(torch.float64)
    return torch.where(n > 0, hits / n.clamp(min=1), torch.full_like(n, float("nan")))


def error_reduction(acc, rule) -> float | None:
    """1 - (1 - acc) / (1 - rule): the fraction of the mask rule's errors a model removes (1: all, 0: none, < 0:
    more errors than the rule); None when the rule made none (or a value is missing)."""
    if acc is None or rule is None or not float(rule) < 1.0:
        return None
    return 1.0 - (1.0 - float(acc)) / (1.0 - float(rule))


def masked_targets(target: torch.Tensor, valid: torch.Tensor | None) -> torch.Tensor:
    """Cluster ids with the rows outside ``valid`` (B,N bool; padding copies) set to -1, which losses ignore."""
    return target if valid is None else torch.where(valid.bool(), target, torch.full_like(target, -1))


def per_sample(fn, a: torch.Tensor, b: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
    """``fn(a, b)`` -> (B,) of batched point sets (B,N,3), each sample restricted to its ``valid`` rows (B,N)."""
    if valid is None or bool(valid.all()):
        return fn(a, b)
    valid = valid.bool()
    return torch.cat([fn(a[i][valid[i]][None], b[i][valid[i]][None]) for i in range(a.shape[0])])


def position_losses(pred: torch.Tensor, target: torch.Tensor, scale: float = 1.0,
                    valid: torch.Tensor | None = None, emd_method: str = "auto",
                    emd_tol: float = 0.01, emd_rounds: int = 0) -> dict[str, torch.Tensor]:
    """Chamfer, EMD and Hausdorff of pred vs target (B,N,3), in units of ``scale``; each (B,).

    ``valid`` (B,N bool): the rows that are distinct particles; padding copies (TransitionDataset) are left
    out so that a particle counts once.  Computed in float64 around the target centroid: cdist's matmul
    formulation loses sqrt(float32 rounding) ~ 3e-4 of the coordinate magnitude, which would floor the loss
    and add gradient noise.  All three are batched on the inputs' device (point_losses.py); the EMD is exact
    (scipy, host) or the device auction within (1 + emd_tol) of it, per ``emd_method`` (auto: auction on CUDA);
    ``emd_rounds`` > 0 caps the auction's rounds, the items left solved exactly on the host.
    """
    from topocut.models.point_losses import chamfer, emd, hausdorff

    c = target.mean(dim=1, keepdim=True).detach()
    p, t = ((pred - c) / scale).double(), ((target - c) / scale).double()
    out = {"chamfer": chamfer(p, t, valid), "emd": emd(p, t, valid, emd_method, emd_tol, emd_rounds),
           "hausdorff": hausdorff(p, t, valid)}
    return {k: v.to(pred.dtype) for k, v in out.items()}


def dynamics_loss(pred_x: torch.Tensor, logits: torch.Tensor, x_t1: torch.Tensor, f_t1: torch.Tensor,
                  cfg: DynamicsConfig | None = None, valid: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Total loss and its parts: loss, loss_pos, loss_topo, chamfer/emd/hausdorff (batch means).

    ``valid`` (B,N bool, default all): rows counted by every term; padding copies of a particle are not.
    """
    cfg = cfg or DynamicsConfig()
    parts = {k: v.mean() for k, v in position_losses(pred_x, x_t1, cfg.pos_scale, valid,
                                                                 cfg.emd_method, cfg.emd_tol, cfg.emd_rounds).items()}
    loss_pos = cfg.w_chamfer * parts["chamfer"] + cfg.w_emd * parts["emd"] + cfg.w_hausdorff * parts["hausdorff"]
    loss_topo = hungarian_cluster_loss(logits, masked_targets(f_t1, valid))
    return {"loss": cfg.lambda_pos * loss_pos + cfg.lambda_topo * loss_topo, "loss_pos": loss_pos,
            "loss_topo": loss_topo, **parts}

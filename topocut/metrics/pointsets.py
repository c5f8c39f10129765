"""Point-set distances: Chamfer, Hausdorff and Earth Mover's distance.

All three are in scene units (unsquared Euclidean distances), so they can be
compared with each other and with particle spacings:

    nn(a -> b)  = mean_i min_j |a_i - b_j|
    chamfer     = (nn(a -> b) + nn(b -> a)) / 2
    hausdorff   = max(max_i min_j |a_i - b_j|, max_j min_i |b_j - a_i|)
    emd         = min over bijections s of mean_i |a_i - b_s(i)|

For two copies of a cloud shifted by a vector t (|t| below half the nearest
neighbour spacing) all three equal |t|.  chamfer <= hausdorff always; for
equal sizes nn(a -> b) <= emd.

Inputs are numpy (N,3)/(M,3) -> float, or torch (B,N,3)/(B,M,3) -> (B,)
tensor, differentiable with respect to both inputs.  EMD is exact (Hungarian
assignment, scipy.optimize.linear_sum_assignment) when N == M <= max_exact;
otherwise both clouds are first reduced by farthest point sampling to
m = min(N, M, max_exact) points and the exact EMD of the reduced clouds is
returned: an approximation that treats the FPS subset as an even sample of
each shape.  In torch the assignment is computed without gradient and the
mean matched distance is then differentiated (the assignment is piecewise
constant in the inputs, so this is the exact gradient almost everywhere).
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from topocut.metrics.sampling import fps, fps_torch

MAX_EXACT_EMD = 2048


def _is_torch(x) -> bool:
    return type(x).__module__.split(".")[0] == "torch"


def _np(a, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[0] == 0:
        raise ValueError(f"{name} must be a non-empty (N,D) point array, got shape {a.shape}")
    return a


def _torch_pair(a, b):
    if a.dim() != 3 or b.dim() != 3 or a.shape[0] != b.shape[0]:
        raise ValueError(f"torch inputs must be (B,N,D) and (B,M,D) with equal B, got {tuple(a.shape)}, {tuple(b.shape)}")


def _nn_np(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance (N,) from each point of a to its nearest point in b."""
    return cKDTree(b).query(a, k=1)[0]


def chamfer(a, b):
    """Symmetric mean nearest-neighbour distance (see module docstring)."""
    if _is_torch(a):
        import torch

        _torch_pair(a, b)
        d = torch.cdist(a, b)  # B,N,M
        return 0.5 * (d.min(2).values.mean(1) + d.min(1).values.mean(1))
    a, b = _np(a, "a"), _np(b, "b")
    return float(0.5 * (_nn_np(a, b).mean() + _nn_np(b, a).mean()))


def hausdorff(a, b):
    """Symmetric Hausdorff distance."""
    if _is_torch(a):
        import torch

        _torch_pair(a, b)
        d = torch.cdist(a, b)  # B,N,M
        return torch.maximum(d.min(2).values.amax(1), d.min(1).values.amax(1))
    a, b = _np(a, "a"), _np(b, "b")
    return float(max(_nn_np(a, b).max(), _nn_np(b, a).max()))


def _assignment(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Column index (N,) matched to each row of a (N == M), minimising the summed distance."""
    cost = np.sqrt(((a[:, None, :] - b[None, :, :]) ** 2).sum(-1))  # N,M
    return linear_sum_assignment(cost)[1]


def emd(a, b, max_exact: int = MAX_EXACT_EMD):
    """Earth Mover's distance with uniform weights: mean matched distance (see module docstring)."""
    if _is_torch(a):
        return _emd_torch(a, b, max_exact)
    a, b = _np(a, "a"), _np(b, "b")
    m = min(len(a), len(b), max_exact)
    if len(a) != m:
        a = a[fps(a, m)]
    if len(b) != m:
        b = b[fps(b, m)]
    cols = _assignment(a, b)
    return float(np.linalg.norm(a - b[cols], axis=1).mean())


def _emd_torch(a, b, max_exact: int):
    import torch

    _torch_pair(a, b)
    m = min(a.shape[1], b.shape[1], max_exact)
    B = a.shape[0]
    ar = torch.arange(B, device=a.device)[:, None]
    if a.shape[1] != m:
        a = a[ar, fps_torch(a, m)]  # B,m,3
    if b.shape[1] != m:
        b = b[ar, fps_torch(b, m)]
    with torch.no_grad():
        an, bn = a.detach().double().cpu().numpy(), b.detach().double().cpu().numpy()
        cols = np.stack([_assignment(an[i], bn[i]) for i in range(B)])  # B,m
    cols = torch.as_tensor(cols, device=a.device)
    return (a - b[ar, cols]).norm(dim=-1).mean(1)

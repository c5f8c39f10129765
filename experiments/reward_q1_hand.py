"""The reward on hand-cut pieces (issue #29; docs/reward.md): paper Q1 on a cube cut by exact planes, and the
thickness sweep, both on jittered lattices at the 64^3 spacing.  ``python experiments/reward_figures.py q1_hand``
draws them."""
from __future__ import annotations

import numpy as np

from topocut.reward.config import RewardConfig
from topocut.reward.matching import spectral_reward

H64 = 1 / 128
_YAW = 0.3  # slab normal oblique to the world-aligned lattice


def _axes():
    return np.array([np.cos(_YAW), np.sin(_YAW), 0.0]), np.array([-np.sin(_YAW), np.cos(_YAW), 0.0])


def hand_object(name: str, seed: int = 0, h: float = H64) -> np.ndarray:
    """A jittered (+-h/4) lattice of the 0.16 cube (yawed by 0.3 rad) or the cake (cylinder r 0.1, height 0.1)."""
    a1, a2 = _axes()
    half = {"cube": (0.12, 0.12, 0.08), "cake": (0.1, 0.1, 0.05)}[name]
    ax = [np.arange(-half[0] + h / 2, half[0], h), np.arange(-half[1] + h / 2, half[1], h),
          np.arange(h / 2, 2 * half[2], h)]
    g = np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)
    g = g + np.random.default_rng(seed).uniform(-h / 4, h / 4, g.shape)
    if name == "cube":
        inside = (np.abs(g @ a1) < 0.08) & (np.abs(g @ a2) < 0.08) & (g[:, 2] < 0.16)
    else:
        inside = (np.hypot(g[:, 0], g[:, 1]) < 0.1) & (g[:, 2] < 0.1)
    return g[inside]


def thickness_sweep(cfg: RewardConfig | None = None, ratios=(0.4, 0.5, 0.6, 0.7, 0.8, 0.85, 0.9, 0.95, 1.0, 1.05, 1.1,
                                                             1.15, 1.2, 1.3, 1.4, 1.5, 1.7), t: float = 0.03) -> dict:
    """R and N_C of an edge slab r t thick against the goal slab t (cube and cake; other jitter seed)."""
    cfg = cfg or RewardConfig()
    a1, _ = _axes()
    face = {"cube": 0.08, "cake": 0.1}
    out = {"ratios": list(ratios), "t": t}
    for name in ("cube", "cake"):
        g, f = hand_object(name, 0), hand_object(name, 1)
        goal = g[g @ a1 > face[name] - t]
        rs = [spectral_reward([f[f @ a1 > face[name] - r * t]], [goal], cfg) for r in ratios]
        out[name] = {"R": [float(r.per_goal[0]) for r in rs], "N_C": [int(r.cut_count) for r in rs],
                     "d": [float(r.distances[0, 0]) for r in rs]}
    return out


def _split(p, planes, h=H64):
    """Pieces of p after full-length planes (normal, offset): connected components of each cell."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    key = np.zeros(len(p), np.int64)
    for i, (n, o) in enumerate(planes):
        key |= (p @ n > o).astype(np.int64) << i
    out = []
    for k in np.unique(key):
        q = p[key == k]
        pairs = cKDTree(q).query_pairs(1.5 * h, output_type="ndarray")
        m = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(q), len(q)))
        n, lab = connected_components(m, directed=False)
        out += [q[lab == i] for i in range(n)]
    return out


def q1_hand(cfg: RewardConfig | None = None, t: float = 0.03) -> dict:
    """Paper Q1 on a hand-cut cube (slice, 5 goal slabs): three good cuts, then each of 10 wrong 4th cuts
    and the right one.  Returns totals, N_C and the fragments' values per state."""
    cfg = cfg or RewardConfig()
    a1, a2 = _axes()
    p, face = hand_object("cube"), 0.08
    goal = sorted(_split(p, [(a1, face - i * t) for i in range(1, 6)]), key=lambda g: -(g @ a1).mean())[:5]
    good = [(a1, face - i * t) for i in (1, 2, 3)]

    def turned(deg, axis):
        n = np.cos(np.deg2rad(deg)) * a1 + np.sin(np.deg2rad(deg)) * axis
        return (n, (face - 4 * t) * (n @ a1) + (0.08 * n[2] if axis[2] else 0.0))

    states = {f"{k} cuts": _split(p, good[:k]) for k in range(4)}
    states["right 4th"] = _split(p, good + [(a1, face - 4 * t)])
    for d in (10, 20, 30, 45):
        states[f"yaw {d}"] = _split(p, good + [turned(d, a2)])
    states["tilt 20"] = _split(p, good + [turned(20, np.array([0, 0, 1.0]))])
    states["0.5t"] = _split(p, good + [(a1, face - 3.5 * t)])
    states["1.5t"] = _split(p, good + [(a1, face - 4.5 * t)])
    states["through slab 2"] = _split(p, good + [(a1, face - 1.5 * t)])
    three = states["3 cuts"]
    big = max(three, key=len)
    states["chop the rest"] = [q for q in three if q is not big] + _split(big, [(a2, 0.0)])
    states["halve everything"] = _split(p, good + [(a2, 0.003)])
    out = {"steps": list(states)}
    for k, frags in states.items():
        r = spectral_reward(frags, goal, cfg)
        out[k] = {"total": r.total, "unclipped": r.unclipped, "N_C": r.cut_count, "pieces": [len(f) for f in frags],
                  "values": np.round(r.values, 3).tolist(), "per_goal": np.round(r.per_goal, 3).tolist()}
    return out


def draw_q1_hand(res: dict, sweep: dict, out: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(12, 4.2), gridspec_kw={"width_ratios": [1.4, 1]})
    seq = [res[f"{k} cuts"]["total"] for k in range(4)]
    ax.plot(range(4), seq, "o-", color="C3", lw=2.5, label="good cuts")
    ax.plot([3, 4], [seq[3], res["right 4th"]["total"]], "s--", color="C2", lw=2, label="right 4th cut")
    wrong = [k for k in res["steps"] if not k.endswith("cuts") and k != "right 4th"]
    for i, k in enumerate(wrong):
        y = res[k]["total"]
        ax.plot([3, 4 + 0.06 * (i - len(wrong) / 2)], [seq[3], y], ":", color="C0", lw=0.8)
        ax.text(4.35, y, f"{k} (N_C {res[k]['N_C']})", fontsize=7, va="center")
    ax.set_xlim(-0.2, 5.6)
    ax.set_xticks(range(5), ["uncut", "1", "2", "3", "4"])
    ax.set_ylabel("total reward")
    ax.set_title("Q1, hand-cut cube (goal: 5 slabs of 3 cm)")
    ax.legend(fontsize=8, loc="upper left")
    for name, c in (("cube", "C3"), ("cake", "C0")):
        ax2.plot(sweep["ratios"], sweep[name]["R"], "o-", color=c, label=f"{name} edge slab: R")
        ok = [r for r, n in zip(sweep["ratios"], sweep[name]["N_C"]) if n]
        ax2.axvspan(min(ok), max(ok), color=c, alpha=0.08)
    ax2.set_xlabel("slab thickness / goal thickness (shaded: N_C success window)")
    ax2.set_ylabel("R(d)")
    ax2.set_title("thickness sweep (planes oblique to the lattice)")
    ax2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=120)


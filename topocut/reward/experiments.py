"""Reward experiments (paper appendix): pose invariance and the spectral-loss matrix; metric table.

python experiments/reward_figures.py pose_invariance --out docs/img/reward_pose_invariance.png
python experiments/reward_figures.py loss_matrix --out docs/img/reward_loss_matrix.png
python experiments/reward_figures.py q1_hand --out docs/img/reward_q1.png  (hand-cut pieces: Q1 + thickness sweep)
python experiments/reward_figures.py q1 --out docs/img/reward_q1_sim.png   (simulator; paper Q1, ~2 min on CPU)
``metric_table(states, goal)`` scores each step of the simulated sequence.
"""
from __future__ import annotations

import numpy as np

from topocut.metrics import chamfer, emd, hausdorff
from topocut.reward.config import RewardConfig
from topocut.reward.matching import spectral_reward

H = 0.008  # lattice spacing in scene units (the simulator's default particle spacing)


def lattice_box(nx: int, ny: int, nz: int, h: float = H, surface: bool = False, jitter: float = 0.0,
                seed: int = 0) -> np.ndarray:
    """Particles of an nx x ny x nz lattice block (N,3); surface=True keeps only the boundary layer.

    jitter moves each particle by U(-jitter, jitter) * h per axis, as topocut.sim.objects does.
    """
    g = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"), -1).reshape(-1, 3)
    if surface:
        g = g[((g == 0) | (g == np.array([nx, ny, nz]) - 1)).any(1)]
    g = g + np.random.default_rng(seed).uniform(-jitter, jitter, g.shape)
    return (g * h).astype(np.float64)


def yaw_pose(points: np.ndarray, yaw: float, offset=(0.5, 0.5, 0.05)) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    return (points - points.mean(0)) @ R.T + np.asarray(offset)


def pose_invariance(cfg: RewardConfig | None = None, yaws_deg=(0, 20, 45, 70, 110),
                    lengths=(64, 56, 48, 40, 36, 32, 28, 24, 16), jitter: float = 0.25) -> dict:
    """Reward vs step for a 5x5xL bar truncated step by step toward the ideal 5x5x32 stick.

    Each yaw rotates the fragment (not the goal); dense and surface-only particles.  With
    jitter = 0 (an exact lattice) FPS meets exact distance ties that rotation breaks differently,
    so the resampled subsets, and the rewards, differ slightly; jittered particles have no ties.
    Returns {"lengths", "yaws_deg", "dense": (Y,S), "surface": (Y,S)}.
    """
    cfg = cfg or RewardConfig()
    out = {"lengths": list(lengths), "yaws_deg": list(yaws_deg)}
    for mode in ("dense", "surface"):
        goal = lattice_box(5, 5, 32, surface=mode == "surface", jitter=jitter, seed=1)
        R = np.zeros((len(yaws_deg), len(lengths)))
        for i, yaw in enumerate(yaws_deg):
            for j, L in enumerate(lengths):
                bar = lattice_box(5, 5, L, surface=mode == "surface", jitter=jitter)  # cut from one end: same particles
                frag = yaw_pose(bar[:, [2, 0, 1]], np.deg2rad(yaw))
                R[i, j] = spectral_reward([frag], [goal], cfg).per_goal[0]  # R(d) of the piece
        out[mode] = R
    return out


def shape_gallery(h: float = H) -> dict:
    """Named pieces (lattice units x h): slices of 3/4/6 layers, sticks, dice, a sphere and a cube."""
    g = np.stack(np.meshgrid(*[np.arange(-8, 9)] * 3, indexing="ij"), -1).reshape(-1, 3)
    sphere = g[np.linalg.norm(g, axis=1) <= 7.5] * h
    return {"slice3": lattice_box(3, 20, 14, h), "slice4": lattice_box(4, 20, 14, h),
            "slice6": lattice_box(6, 20, 14, h), "stick4": lattice_box(4, 4, 14, h),
            "stick5": yaw_pose(lattice_box(5, 5, 14, h), 0.6), "die4": lattice_box(4, 4, 4, h),
            "die5": yaw_pose(lattice_box(5, 5, 5, h), 1.0), "cube12": lattice_box(12, 12, 12, h), "sphere": sphere}


def loss_matrix(cfg: RewardConfig | None = None) -> tuple[list[str], np.ndarray]:
    """Pairwise d(row, column) = d_spec + d_size over the gallery (the distance R sees; column = goal)."""
    from topocut.reward.matching import piece_distance

    shapes = shape_gallery()
    names = list(shapes)
    D = np.array([[piece_distance(shapes[a], shapes[b], cfg) for b in names] for a in names])
    return names, D


# -- hand-built experiments (issue #29): thickness sweep and Q1 on jittered lattices at the 64^3 spacing -------
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


def _plot_q1_hand(res: dict, sweep: dict, out: str) -> None:
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


def metric_table(states, goal, cfg: RewardConfig | None = None) -> dict:
    """Per-step CD, EMD, HD and spectral reward of a sequence of fragment sets against a goal.

    states: list over steps of lists of fragments (n_i,3); goal: a Goal (uses .fragments) or a list
    of goal pieces.  For CD/EMD/HD each goal piece takes its closest fragment (by that metric), the
    step's value is the mean over goal pieces.  Normalised scores lie in [0, 1], higher = better:
    metric score = 1 - value / max over steps; reward score = total / r_max.
    """
    cfg = cfg or RewardConfig()
    goals = [np.asarray(g, np.float64) for g in getattr(goal, "fragments", goal)]
    raw = {"cd": [], "emd": [], "hd": [], "reward": []}
    for frags in states:
        frags = [np.asarray(f, np.float64) for f in frags]
        for name, fn in (("cd", chamfer), ("emd", emd), ("hd", hausdorff)):
            raw[name].append(float(np.mean([min(fn(f, g) for f in frags) for g in goals])))
        raw["reward"].append(spectral_reward(frags, goals, cfg).total)
    table = {k: np.asarray(v) for k, v in raw.items()}
    for k in ("cd", "emd", "hd"):
        table[f"{k}_score"] = 1.0 - table[k] / max(table[k].max(), 1e-12)
    table["reward_score"] = table["reward"] / cfg.r_max
    return table


def _fragments(x: np.ndarray, labels: np.ndarray) -> list[np.ndarray]:
    return [x[labels == c] for c in np.unique(labels) if c >= 0]


def _face_cut(x: np.ndarray, labels: np.ndarray, normal: np.ndarray, thickness: float, board_z: float):
    """A cut `thickness` inside the +normal face of the largest piece (the uncut block), as a teleoperator
    would place it: cuts push the block, so the ideal planes' fixed world positions drift off the face."""
    from topocut.sim.action import KnifeAction

    frags = _fragments(x, labels)
    block = min(frags, key=lambda f: f.mean(0) @ normal).astype(np.float64)  # the -a1-most piece
    s = block @ normal
    face = np.percentile(s, 99)  # robust to a few particles dragged out by the previous cut
    point = block.mean(0) + (face - thickness - s.mean()) * normal
    return KnifeAction.from_plane(normal, point, board_z)


def q1_sequence(n_grid: int = 64, thickness: float = 0.03, wrong: str = "yaw", error: float = 30.0, push: bool = False,
                object: str = "cube", seed: int = 0, cfg: RewardConfig | None = None, log=print) -> dict:
    """Paper Q1 in the simulator: slice `object` with three good cuts, a wrong 4th cut, then a correction.

    Cuts i = 1..3 take a slab of `thickness` off the block's +a1 face (the goal: slice, max_cuts=4).  The
    right 4th cut P4 is planned the same way; the wrong cut 4 is P4 yawed by `error` degrees about its
    centre (wrong="yaw") or shifted by `error` metres along -a1 (wrong="shift": a thicker slab); cut 5
    (correction) is the planned P4.  A branch from the state after cut 3 makes P4 as the 4th cut instead.  Each step's fragments come
    from topocut.topology.discover (labels kept across cuts).  Returns metric_table over
    [uncut, 1, 2, 3, 4 wrong, 5 corrected, 4 right] plus the cut planes, piece sizes and timings.
    """
    import time

    from topocut.goals import TaskConfig, make_goal
    from topocut.sim import CuttingEnv, init_taichi
    from topocut.sim.action import KnifeAction
    from topocut.sim.config import SimConfig
    from topocut.sim.objects import ObjectPose
    from topocut.topology import discover

    init_taichi("cpu")
    env = CuttingEnv(SimConfig(n_grid=n_grid), batch_size=1)
    st = env.reset(object, ObjectPose(), seed=seed)
    board_z = env.cfg.board_z
    goal = make_goal(TaskConfig(name="slice", thickness=thickness, max_cuts=4), object, ObjectPose(),
                     spacing=env.cfg.spacing, board_z=board_z, seed=seed)
    normal = goal.planes[0].normal  # a1: every ideal slice plane is normal to it
    labels = np.zeros(len(st.x[0]), np.int32)  # one piece before any cut
    states, names, planes, sizes, times = [_fragments(st.x[0], labels)], ["uncut"], [None], [[len(st.x[0])]], []

    def cut(action, labels, name):
        t = time.perf_counter()
        env.cut(action)
        if push:
            env.push()
        st = env.state()
        labels = discover(st.x[0], st.damage[0], st.sweeps[0], previous_labels=labels).labels
        frags = _fragments(st.x[0], labels)
        states.append(frags), names.append(name), planes.append(action.to_vector().tolist())
        sizes.append(sorted((len(f) for f in frags), reverse=True)), times.append(time.perf_counter() - t)
        log(f"{name}: plane {np.round(action.to_vector(), 4)}  pieces {sizes[-1]}  {times[-1]:.1f} s")
        return labels

    for i in range(3):
        labels = cut(_face_cut(env.state().x[0], labels, normal, thickness, board_z), labels, f"cut {i + 1}")
    saved, labels3 = env.get_state(0), labels.copy()
    right = _face_cut(env.state().x[0], labels, normal, thickness, board_z)
    if wrong == "yaw":
        bad = KnifeAction(right.x, right.y, right.yaw + np.deg2rad(error), right.tilt)
    elif wrong == "shift":
        bad = KnifeAction(right.x - error * normal[0], right.y - error * normal[1], right.yaw, right.tilt)
    else:
        raise ValueError(f"q1 wrong={wrong!r}: expected one of 'yaw', 'shift'")
    labels = cut(bad, labels, "cut 4 wrong")
    labels = cut(right, labels, "cut 5 corrected")
    env.set_state(saved, b=0)
    cut(right, labels3, "cut 4 right")
    table = metric_table(states, goal, cfg)
    return {"steps": names, **{k: v.tolist() for k, v in table.items()}, "planes": planes, "piece_sizes": sizes,
            "goal_piece_sizes": [len(f) for f in goal.fragments], "cut_seconds": times,
            "config": {"n_grid": n_grid, "thickness": thickness, "wrong": wrong, "error": error, "push": push, "object": object},
            "_states": states}


def _plot_q1(res: dict, out: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4), gridspec_kw={"width_ratios": [1.3, 1]})
    main, right = list(range(6)), 6  # table rows: uncut, 1, 2, 3, 4 wrong, 5 corrected | 4 right
    for key, label, style in (("cd_score", "CD", "C0"), ("emd_score", "EMD", "C1"), ("hd_score", "HD", "C2"),
                              ("reward", "spectral reward", "C3")):
        y = np.asarray(res[key])
        ax.plot(main, y[main], marker="o", color=style, lw=2.5 if key == "reward" else 1.2, label=label)
        ax.plot([3, 4], [y[3], y[right]], ls="--", marker="s", color=style, lw=1.2)
    ax.axvspan(3.6, 4.4, color="r", alpha=0.08)
    ax.set_xticks(main, ["uncut", "1", "2", "3", "4\n(wrong)", "5\n(corrected)"])
    ax.set_xlabel("cut (dashed / squares: the right 4th cut instead)")
    ax.set_ylabel("score (CD/EMD/HD: 1 - d / max d; reward: total)")
    ax.set_title("slice cube, 3 cm slabs: per-step scores")
    ax.legend(fontsize=8)
    for i, (name, frags) in enumerate(zip(("cut 4 wrong", "cut 5 corrected", "cut 4 right"), (4, 5, 6))):
        for j, f in enumerate(sorted(res["_states"][frags], key=lambda f: -f[:, 0].mean())):
            ax2.scatter(f[:, 0], f[:, 1] + 0.25 * (2 - i), s=1, color=f"C{j}")
        ax2.text(0.3, 0.25 * (2 - i) + 0.6, name, fontsize=8)
    ax2.set_aspect("equal")
    ax2.set_xlabel("x (a1)")
    ax2.set_yticks([])
    ax2.set_title("pieces seen from above (x-y), one colour per fragment")
    fig.tight_layout()
    fig.savefig(out, dpi=120)


def _plot_pose(res: dict, out: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6), sharey=True)
    steps = np.arange(len(res["lengths"]))
    for ax, mode in zip(axes, ("dense", "surface")):
        for i, yaw in enumerate(res["yaws_deg"]):
            ax.plot(steps, res[mode][i], marker="o", ms=3, label=f"yaw {yaw} deg")
        ax.set_xticks(steps, [str(L) for L in res["lengths"]])
        ax.set_xlabel("bar length (particles) along the cutting trajectory; goal 5x5x32")
        ax.set_title(f"{mode} particles: max spread {np.ptp(res[mode], axis=0).max():.1e}")
    axes[0].set_ylabel("R(d) of the piece")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=120)


def _plot_matrix(names, D, out: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    fig, ax = plt.subplots(figsize=(6.4, 5.4))
    im = ax.imshow(np.maximum(D, 1e-4), norm=LogNorm(), cmap="viridis")
    ax.set_xticks(range(len(names)), names, rotation=45, ha="right")
    ax.set_yticks(range(len(names)), names)
    ax.set_xlabel("reference piece (sets sigma)")
    for i in range(len(names)):
        for j in range(len(names)):
            ax.text(j, i, f"{D[i, j]:.2g}", ha="center", va="center", fontsize=6, color="w")
    fig.colorbar(im, ax=ax, label="d_spec")
    fig.tight_layout()
    fig.savefig(out, dpi=120)

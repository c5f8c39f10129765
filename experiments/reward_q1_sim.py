"""Paper Q1 in the simulator (docs/reward.md): three good cuts, a wrong 4th, a correction, scored per step by
CD, EMD, HD and the spectral reward (``metric_table``).  ``python experiments/reward_figures.py q1`` draws it."""
from __future__ import annotations

import numpy as np

from topocut.metrics import chamfer, emd, hausdorff
from topocut.reward.config import RewardConfig
from topocut.reward.matching import spectral_reward


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

    from topocut.sim import CuttingEnv, init_taichi
    from topocut.sim.action import KnifeAction
    from topocut.sim.config import SimConfig
    from topocut.sim.objects import ObjectPose
    from topocut.tasks import make_goal, task_config
    from topocut.topology import discover

    init_taichi("cpu")
    env = CuttingEnv(SimConfig(n_grid=n_grid), batch_size=1)
    st = env.reset(object, ObjectPose(), seed=seed)
    board_z = env.cfg.board_z
    goal = make_goal(task_config("slice", thickness=thickness, max_cuts=4), object, ObjectPose(),
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


def draw_q1_sequence(res: dict, out: str) -> None:
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


"""The thickness sweep under ``reward.size_tolerance`` (docs/reward.md#resolution): R(d) of one edge slab r times
the goal's 3 cm thickness, cut from a yawed cube lattice, for tolerances of 0, 0.5 and 1 particle spacing at the
64^3 and the 128^3 particle spacings (N_C success marked *).

    python experiments/size_tolerance.py          # ~1 min on the 2-core CPU
"""
import argparse

import numpy as np

YAW = 0.3  # the slab's normal oblique to the lattice
A1 = np.array([np.cos(YAW), np.sin(YAW), 0.0])
A2 = np.array([-np.sin(YAW), np.cos(YAW), 0.0])
T = 0.03
RATIOS = (0.5, 0.7, 0.8, 0.87, 0.9, 1.0, 1.1, 1.13, 1.2, 1.3, 1.5)


def edge_slab(r: float, h: float, seed: int) -> np.ndarray:
    """The particles of a 0.16 m cube (jittered lattice of spacing h, +-h/4) within r T of its +A1 face."""
    ax = [np.arange(-0.12 + h / 2, 0.12, h), np.arange(-0.12 + h / 2, 0.12, h), np.arange(h / 2, 0.16, h)]
    g = np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)
    g = g + np.random.default_rng(seed).uniform(-h / 4, h / 4, g.shape)
    g = g[(np.abs(g @ A1) < 0.08) & (np.abs(g @ A2) < 0.08)]
    return g[g @ A1 > 0.08 - r * T]


def main(argv=None):
    from topocut.reward import RewardConfig, spectral_reward

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tolerances", type=float, nargs="+", default=[0.0, 0.5, 1.0])
    args = ap.parse_args(argv)
    print("| grid | tolerance | " + " | ".join(f"{r}t" for r in RATIOS) + " |")
    print("|---|---|" + "---|" * len(RATIOS))
    for grid in (64, 128):
        h = 0.5 / grid  # the simulator's particle spacing at this grid
        goal = edge_slab(1.0, h, 0)
        for tol in args.tolerances:
            cfg = RewardConfig(size_tolerance=tol)
            cells = []
            for r in RATIOS:
                res = spectral_reward([edge_slab(r, h, 1)], [goal], cfg)
                cells.append(f"{res.per_goal[0]:.2f}" + ("*" if res.cut_count else ""))
            print(f"| {grid}³ | {tol:g} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()

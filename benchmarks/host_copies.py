"""Reading a batch's particles to the host: Taichi's to_numpy (the reference) against ``topocut.sim.runtime.to_host``.

MPPI's rollouts read every scene's positions and damage before and after each cut (CuttingEnv.cut, CuttingEnv.state):
16 scenes x 69k particles at 128^3.  Taichi's to_numpy hands its copy kernel a host array, so on CUDA each read first
copies a zeroed host buffer to the device and back; to_host writes a device tensor and copies it once into pinned
memory.  Both are timed in this process, the reference first, on a loaded cake.

    python benchmarks/host_copies.py --device cuda --n-grid 128 --batch 16
    python benchmarks/host_copies.py --device cpu --n-grid 32 --batch 2      # the same call on the CPU: no change
"""
import argparse
import time

import numpy as np


def timeit(fn, repeat: int) -> float:
    fn()  # compile, warm torch's allocators
    t0 = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - t0) / repeat


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    p.add_argument("--n-grid", type=int, default=64)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--object", default="cake")
    p.add_argument("--repeat", type=int, default=20)
    args = p.parse_args()
    from topocut.sim import runtime
    from topocut.sim.config import SimConfig
    from topocut.sim.env import CuttingEnv
    from topocut.sim.objects import ObjectPose

    runtime.init_taichi(args.device)
    env = CuttingEnv(SimConfig(n_grid=args.n_grid, batch_size=args.batch, arch=args.device), batch_size=args.batch)
    env.reset(args.object, ObjectPose(), seed=0)
    s = env.solver
    print(f"{args.device}, {args.n_grid}^3, {args.batch} scenes of {env.n} particles ({args.object}); ms a call, "
          f"the mean of {args.repeat}")
    print(f"{'read':>22} {'to_numpy ms':>12} {'to_host ms':>11} {'ratio':>7}")
    rows = {"x (B,cap,3) f32": lambda: runtime.to_host(s.x), "damage (B,cap) i32": lambda: runtime.to_host(s.damage),
            "F (B,cap,3,3) f32": lambda: runtime.to_host(s.F), "CuttingEnv.state()": env.state}
    for name, fn in rows.items():
        times = {}
        for how in ("numpy", "auto"):  # the reference first
            runtime.HOST_COPY = how
            times[how] = timeit(fn, args.repeat)
        runtime.HOST_COPY = "numpy"
        a = fn() if name != "CuttingEnv.state()" else fn().x
        runtime.HOST_COPY = "auto"
        b = fn() if name != "CuttingEnv.state()" else fn().x
        same = np.array_equal(a, b) and a.dtype == b.dtype
        print(f"{name:>22} {1e3 * times['numpy']:12.2f} {1e3 * times['auto']:11.2f} "
              f"{times['numpy'] / times['auto']:6.2f}x{'' if same else '  (DIFFERENT ARRAYS)'}")


if __name__ == "__main__":
    main()

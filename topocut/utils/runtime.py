"""One seed for numpy, torch, Taichi and Warp; one device choice for all three backends."""
from __future__ import annotations

import logging
import os
import random

import numpy as np

log = logging.getLogger(__name__)
DEVICES = ("auto", "cpu", "cuda")


class DeviceUnavailable(RuntimeError):
    """`device=cuda` was asked for on a machine without a CUDA device."""


def cuda_available() -> bool:
    try:
        import torch

        return torch.cuda.is_available()
    except ImportError:  # pragma: no cover - torch is a dependency
        return False


def resolve_device(device: str) -> str:
    """Map ``auto|cpu|cuda`` to ``cpu`` or ``cuda``; asking for cuda without one is an error."""
    if device not in DEVICES:
        raise ValueError(f"device={device!r} is not valid; choose one of {', '.join(DEVICES)}")
    if device == "auto":
        device = "cuda" if cuda_available() else "cpu"
    elif device == "cuda" and not cuda_available():
        raise DeviceUnavailable("device=cuda was requested but no CUDA device is visible "
                                "(torch.cuda.is_available() is False); use device=cpu or device=auto")
    log.info("device: %s (taichi arch=%s, warp device=%s, torch device=%s)", device,
             "cuda" if device == "cuda" else "cpu", "cuda:0" if device == "cuda" else "cpu", device)
    return device


def seed_everything_all(seed: int) -> None:
    """Seed python, numpy, torch (with dataloader workers) and record the seed for Taichi/Warp.

    Taichi takes its seed at ``ti.init(random_seed=...)`` (see ``topocut.sim.init_taichi``), and
    Warp's random functions take explicit seeds, so both read ``TOPOCUT_SEED``.  What Lightning's
    ``seed_everything(seed, workers=True)`` does, without importing Lightning: its import pulls in torchmetrics
    and, where installed, transformers and torch._dynamo (30-40 s of every stage=mppi process on the lent GPU
    machine, docs/benchmarks.md); the training stages' Trainer reads the same two variables.
    """
    import torch

    random.seed(seed)
    np.random.seed(seed % (2**32))
    torch.manual_seed(seed)  # every device's generator, CUDA's included
    os.environ["TOPOCUT_SEED"] = str(seed)
    os.environ["PL_GLOBAL_SEED"] = str(seed)
    os.environ["PL_SEED_WORKERS"] = "1"


def host_threads() -> int:
    """Threads one process may use for its host work (the piece split, the piece sizes): OMP_NUM_THREADS when set
    (joblib's loky workers get cpu_count // n_jobs there, so 8 demonstration processes on 16 cores do not run 16
    threads each), else every core."""
    try:
        n = int(os.environ.get("OMP_NUM_THREADS", ""))
    except ValueError:
        n = 0
    return max(1, n if n > 0 else (os.cpu_count() or 1))


_BLAS = None  # threadpoolctl's controller of the loaded BLAS libraries, made on first use
_POOL: dict = {}  # host_map's pool, kept between calls: {"workers": n, "pool": ThreadPoolExecutor}
if hasattr(os, "register_at_fork"):  # a forked child has none of its parent's threads: it makes its own pool
    os.register_at_fork(after_in_child=_POOL.clear)


def one_blas_thread():
    """A context in which BLAS runs on one thread.  The host's products are (N,3) @ (3,k): threaded OpenBLAS
    spends more on waking and joining its threads than on the product, worst beside other busy threads (a 10^5
    particle piece's size descriptor: 108 ms on 2 busy cores, 39 ms in this context, the same bits)."""
    global _BLAS
    from threadpoolctl import ThreadpoolController

    if _BLAS is None:
        _BLAS = ThreadpoolController()
    return _BLAS.limit(limits=1, user_api="blas")


def host_map(fn, items) -> list:
    """[fn(item) for item in items], in ``host_threads()`` threads (numpy's and scipy's large array work releases
    the GIL) with BLAS on one thread (``one_blas_thread``).  The pool lives between calls: a cut maps its scenes
    once or twice, and starting 16 threads a call cost more than some of the work.  Called from one of the pool's
    own threads it runs serially (a nested map must not wait on a pool its caller fills)."""
    import threading

    items = list(items)
    cap = host_threads()
    with one_blas_thread():
        if min(len(items), cap) <= 1 or threading.current_thread().name.startswith("topocut-host"):
            return [fn(item) for item in items]
        if _POOL.get("workers") != cap:
            from concurrent.futures import ThreadPoolExecutor

            if "pool" in _POOL:
                _POOL["pool"].shutdown(wait=False)
            _POOL.update(workers=cap, pool=ThreadPoolExecutor(max_workers=cap, thread_name_prefix="topocut-host"))
        return list(_POOL["pool"].map(fn, items))

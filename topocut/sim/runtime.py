"""The process's Taichi runtime: starting it (init_taichi), freeing it (reset_taichi), its kernel cache on disk.

Every simulator, the device split of pieces and the tests start Taichi through ``init_taichi``.  Besides ti.init's
options it memoises the source excerpt Taichi writes for each AST node it transforms (``memoize_source_positions``).
"""
import os

import numpy as np
import taichi as ti

_STATE = {"arch": None}
_ON_RESET: list = []  # callables dropping module-level Taichi objects before reset_taichi frees them


KERNEL_CACHE_BYTES = 1 << 30  # Taichi's default, 100 MiB, is less than this project's kernels


def offline_cache_size() -> dict:
    """ti.init's cap on the kernel cache on disk, unless TI_OFFLINE_CACHE_MAX_SIZE_OF_FILES sets one.  Taichi's 100 MiB
    default holds fewer kernels than the grids, batch sizes and materials of one test suite compile (~100 MiB on the
    CPU backend); past the cap each process exit deletes the least recently used quarter, and the next process to use
    those kernels compiles them again (3-40 s each)."""
    return {} if os.environ.get("TI_OFFLINE_CACHE_MAX_SIZE_OF_FILES") else {
        "offline_cache_max_size_of_files": KERNEL_CACHE_BYTES}


def init_taichi(arch: str = "cpu", seed: int = 0, debug: bool = False, cpu_threads: "int | None" = None) -> str:
    """Initialise Taichi once per process (idempotent); returns the arch in use.

    A second call is a no-op; asking for another arch than the one running is
    an error (re-initialising would free every simulator's fields).
    ``cpu_threads=1`` makes CPU runs bit-reproducible (atomic adds then run in
    a fixed order).
    """
    from taichi.lang import impl

    if arch not in ("cpu", "cuda"):
        raise ValueError(f"arch={arch!r}; valid: cpu, cuda")
    if impl.get_runtime().prog is not None:
        running = "cuda" if impl.current_cfg().arch == ti.cuda else "cpu"
        if _STATE["arch"] is not None and running != arch:
            raise RuntimeError(f"Taichi already runs on {running}; cannot switch to {arch} in this process")
        _STATE["arch"] = running
        return running
    memoize_source_positions()
    kw = dict(default_fp=ti.f32, random_seed=seed, debug=debug, offline_cache=True, log_level=ti.WARN,
              **offline_cache_size())
    # an explicit cpu_threads wins over TI_CPU_MAX_NUM_THREADS (make test sets it for the stages its tests start)
    # without Taichi's "overridden by ti.init argument" warning
    held = os.environ.pop("TI_CPU_MAX_NUM_THREADS", None) if cpu_threads else None
    if cpu_threads:
        kw["cpu_max_num_threads"] = int(cpu_threads)
    try:
        ti.init(arch=ti.cuda if arch == "cuda" else ti.cpu, **kw)
    finally:
        if held is not None:
            os.environ["TI_CPU_MAX_NUM_THREADS"] = held
    if arch == "cuda" and impl.current_cfg().arch != ti.cuda:
        ti.reset()
        raise RuntimeError("arch=cuda requested but Taichi found no usable CUDA device; use sim.arch=cpu")
    _STATE["arch"] = arch
    return arch


HOST_COPY = "auto"  # to_host on CUDA: auto (through torch, pinned), numpy (Taichi's to_numpy: benchmarks' reference)


def to_host(field):
    """``field.to_numpy()`` (same shape and dtype), without its round trip on CUDA.

    Taichi's to_numpy hands the kernel a host array, so the launch first copies that (zeroed) array to a device
    buffer, synchronises, runs, synchronises and copies it back: twice the bytes, through pageable memory.  On CUDA
    the field is written into a device tensor instead and copied once into pinned host memory (torch's cached
    pinned blocks).  MPPI's rollouts read every scene's particles after each cut: 16 x 69k at 128^3."""
    if HOST_COPY == "numpy" or _STATE["arch"] != "cuda":
        return field.to_numpy()
    import torch

    out = field.to_torch(device="cuda").to("cpu", non_blocking=True)  # pinned, queued on torch's stream
    torch.cuda.current_stream().synchronize()
    return out.numpy()


def row_sums(field, n: int) -> np.ndarray:
    """``field.to_numpy()[:, :n].sum(1)`` (int64) of a (B,N) integer field, summed on the device on CUDA: only B
    numbers cross to the host (a cut counts its scenes' damaged particles before and after)."""
    if HOST_COPY == "numpy" or _STATE["arch"] != "cuda":
        return field.to_numpy()[:, :n].sum(1, dtype=np.int64)
    import torch

    return field.to_torch(device="cuda")[:, :n].sum(1, dtype=torch.int64).cpu().numpy()


def to_device(arr):
    """``arr`` (a numpy array) as a kernel's ndarray argument: on CUDA a device tensor (one copy up, complete when
    this returns), else the array itself.  Handed a host array, a CUDA launch copies it up, synchronises, runs,
    synchronises and copies it back (see to_host)."""
    if _STATE["arch"] != "cuda":
        return arr
    import torch

    return torch.from_numpy(arr).to("cuda")


def cpu_threads() -> int:
    """Threads of the running Taichi runtime's CPU backend; 0 on a GPU or before init_taichi."""
    from taichi.lang import impl

    if impl.get_runtime().prog is None or impl.current_cfg().arch not in (ti.x64, ti.arm64):
        return 0
    return int(impl.current_cfg().cpu_max_num_threads)


def reset_taichi() -> None:
    """Free the process's Taichi runtime (every field and kernel); the next init_taichi starts a new one.

    Taichi's kernel cache on disk is keyed by each kernel's IR, which names its fields' SNode ids, and those ids count
    up over a runtime's life.  So a simulator built after others compiles kernels a previous process cached under
    other ids.  The tests reset before each file: a file's simulators then get the same ids, and hit the cache,
    whichever files its worker ran before.  Objects registered in ``_ON_RESET`` (the device split's) are dropped
    first; anything else still holding fields must not be used after this.
    """
    from taichi.lang import impl

    for drop in _ON_RESET:
        drop()
    if impl.get_runtime().prog is not None:  # also a runtime started by a plain ti.init (teleop's viewer)
        ti.reset()
    _STATE["arch"] = None


_EXCERPTS: dict = {}  # memoize_source_positions: a node's place -> Taichi's excerpt of it
_TAICHI_POS_INFO = None  # Taichi's own ASTTransformerContext.get_pos_info, once memoize_source_positions ran


def memoize_source_positions() -> None:
    """Taichi formats a source excerpt (file, line, a caret line, through TextWrapper) for every AST node it
    transforms, at every call site of a @ti.func it inlines, and does so even when the compiled kernel then comes
    from the cache on disk: of a small simulator's first cut on the CPU (3.5-4 s, all of it the kernels' start), ~2 s
    went there, 31,110 excerpts of 3,715 distinct nodes.  The excerpt is a function of the node's place in its
    source, so each is made once per process.  Idempotent; the text is Taichi's own."""
    global _TAICHI_POS_INFO
    from taichi.lang.ast import ast_transformer_utils as utils

    ctx = utils.ASTTransformerContext
    if getattr(ctx.get_pos_info, "memoized", False):
        return
    _TAICHI_POS_INFO = ctx.get_pos_info

    def get_pos_info(self, node):
        key = (self.file, self.lineno_offset, self.indent, self.func.func.__name__, type(node).__name__,
               node.lineno, node.end_lineno, node.col_offset, node.end_col_offset, self.src[node.lineno - 1])
        text = _EXCERPTS.get(key)
        if text is None:
            text = _EXCERPTS[key] = _TAICHI_POS_INFO(self, node)
        return text

    get_pos_info.memoized = True
    ctx.get_pos_info = get_pos_info

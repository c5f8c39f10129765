"""Which GPU a worker process runs on: every visible GPU of a node used by the processes joblib starts.

``make paper`` runs its demonstration parts, seed trainings and evaluation tasks in joblib's loky worker
processes (pipelines/all.py, topocut/eval/runner.py, Hydra's joblib launcher).  Joblib decides which worker takes
which job; this module only decides which device a worker binds to, once, before it touches CUDA: worker k (in
the order the workers start their first job) takes GPU k mod M of the M the launching process sees, through
``CUDA_VISIBLE_DEVICES``, so Taichi, Warp and torch all see that one GPU as device 0.  Workers live as long as
joblib keeps them, so a device is a worker's for its lifetime and J workers over M GPUs are J/M a GPU.

The launching process announces the GPUs in ``TOPOCUT_WORKER_GPUS`` (``share_gpus``: ``<its pid>:<gpu ids>:<a
directory>``); a worker claims the next free slot in that directory (an exclusive file create, atomic on one
host).  The launching process itself never binds (its pid is the owner), and with one GPU or none nothing
changes.  On Slurm (hydra/launcher=submitit) each job gets its own GPU from the scheduler instead.
"""
from __future__ import annotations

import atexit
import logging
import os
import shutil
import tempfile

ENV = "TOPOCUT_WORKER_GPUS"
_BOUND: dict = {}  # in a worker: {"device": the GPU id it bound to, or None}
log = logging.getLogger("topocut")


def visible_gpus() -> list[str]:
    """The GPU ids this process sees: CUDA_VISIBLE_DEVICES's entries where it is set, else 0 .. n-1 for the
    n devices torch counts (none on a CPU build or a machine without a GPU)."""
    env = os.environ.get("CUDA_VISIBLE_DEVICES")
    if env is not None:
        return [d.strip() for d in env.split(",") if d.strip() and d.strip() != "-1"]
    try:
        import torch

        return [str(i) for i in range(torch.cuda.device_count())]
    except Exception:  # noqa: BLE001 - no torch / no driver: no GPU
        return []


def share_gpus(gpus: list[str] | None = None) -> list[str]:
    """In the launching process, before joblib starts workers: announce ``gpus`` (default: the visible ones)
    to them through TOPOCUT_WORKER_GPUS, if there are two or more and nothing announced them yet (an outer
    launcher's announcement stands).  Returns the GPUs announced (empty: workers keep the default device)."""
    if os.environ.get(ENV):
        return parse(os.environ[ENV])[1]
    gpus = visible_gpus() if gpus is None else list(gpus)
    if len(gpus) < 2:
        return []
    slots = tempfile.mkdtemp(prefix="topocut-gpus-")
    atexit.register(shutil.rmtree, slots, ignore_errors=True)
    os.environ[ENV] = f"{os.getpid()}:{','.join(gpus)}:{slots}"
    log.info("placing worker processes over %d GPUs (%s)", len(gpus), ", ".join(gpus))
    return gpus


def parse(value: str) -> tuple[int, list[str], str]:
    """TOPOCUT_WORKER_GPUS -> (the launching pid, the GPU ids, the slot directory)."""
    owner, gpus, slots = value.split(":", 2)
    return int(owner), [g for g in gpus.split(",") if g], slots


def claim_slot(slots: str) -> int:
    """The lowest slot number no other worker has claimed in ``slots`` (an exclusive create: two workers
    starting at once never get the same one)."""
    k = 0
    while True:
        try:
            os.close(os.open(os.path.join(slots, f"slot-{k}"), os.O_CREAT | os.O_EXCL | os.O_WRONLY))
            return k
        except FileExistsError:
            k += 1


def device_for(slot: int, gpus: list[str]) -> str:
    """The GPU of the worker holding ``slot``: round robin over ``gpus``."""
    return gpus[slot % len(gpus)]


def bind_worker() -> str | None:
    """In a worker process, before anything initialises CUDA: bind it to its GPU (CUDA_VISIBLE_DEVICES) and
    return the id; None in the launching process, without an announcement, or once bound to nothing.  Called
    again, it returns the first answer (a worker's CUDA context cannot move)."""
    if "device" in _BOUND:
        return _BOUND["device"]
    value = os.environ.get(ENV)
    device = None
    ddp_rank = any(os.environ.get(v) for v in ("LOCAL_RANK", "RANK")) and os.environ.get("WORLD_SIZE", "1") != "1"
    if value and not ddp_rank:  # a DDP rank sees every GPU: Lightning gives it its own by LOCAL_RANK
        owner, gpus, slots = parse(value)
        if owner != os.getpid() and gpus and os.path.isdir(slots):
            device = device_for(claim_slot(slots), gpus)
            os.environ["CUDA_VISIBLE_DEVICES"] = device
            del os.environ[ENV]  # this worker's own workers (an evaluation's processes) stay on its GPU
            log.info("worker %d bound to GPU %s", os.getpid(), device)
    _BOUND["device"] = device
    return device

"""`python -m topocut.run ...` for the tests, forked from a server that imported the heavy modules once.

Why: every stage run a test starts paid ~3 CPU-seconds of imports (torch, Taichi, Warp, Hydra, Lightning, the
config) before any work, over ~100 runs in `make test` on a 2-core machine.  Here a server process (one per test
worker, started with the worker's environment) imports them once and forks each run.  The child does what
`python -m topocut.run` does: its own argv, environment, working directory and ``sys.path[0]``, fresh random
states, the module run as ``__main__`` (runpy, as ``-m``), non-daemon threads joined and exit handlers run, the
exit status returned; its stdout and stderr (file descriptors 1 and 2, so Taichi's C++ output too) captured as
``subprocess.run(capture_output=True, text=True)`` captures them.  (multiprocessing's forkserver would re-import
the parent's ``__main__``, pytest's, in every child; so this small server instead.)

A server serves the runs whose environment matches the one it was started with in the variables read when those
modules load (``IMPORT_TIME_ENV``: OpenMP's threads, Taichi's, CUDA's devices, Python's own but PYTHONPATH); up to
``MAX_SERVERS`` such environments get one each.  Not forked, a real process instead: a command that is not
``python -m topocut.run``; a further environment; ``TOPOCUT_TEST_FORK=0``.  The commands the docs print run as written, as real
processes (tests/test_docs_commands.py), as do the tests that kill a run midway (Popen).
"""
from __future__ import annotations

import atexit
import json
import os
import select
import signal
import subprocess
import sys
import tempfile
import threading
import time
import traceback
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# what the stages import before their work (the entry point's modules, each stage's own, imported inside them)
PRELOAD = ("torch", "taichi", "warp", "hydra", "omegaconf", "lightning", "zarr", "scipy.spatial", "trimesh", "rich",
           "topocut.config", "topocut.data.store", "topocut.utils.logger", "topocut.utils.runtime", "pipelines.all",
           "pipelines.simulate", "pipelines.mppi", "pipelines.merge", "pipelines.pretrain", "pipelines.bc",
           "pipelines.eval", "pipelines.teleop", "topocut.sim.env", "topocut.episode", "topocut.reward",
           "topocut.topology", "topocut.eval.protocol", "topocut.eval.report", "topocut.models.module",
           "topocut.policies", "topocut.planning.mppi", "topocut.data.episodes", "joblib", "threadpoolctl")
# read by the preloaded modules as they load (OpenMP sizes its pool when torch loads it; Taichi and CUDA read
# theirs at import), so a run that sets them differently gets an interpreter of its own
IMPORT_TIME_ENV = ("OMP_", "MKL_", "KMP_", "GOMP_", "TI_", "CUDA_", "PYTHON", "TORCH", "LD_", "WARP_", "OPENBLAS_",
                   "NVIDIA_", "MALLOC_")
# set by libraries as they load, in every process that imports them (the server's and the run's too), so they say
# nothing about how a run's modules load: joblib's KMP_INIT_AT_FORK, threadpoolctl's KMP_DUPLICATE_LIB_OK, torch's
# inductor cache directory and NVML check.  A test process gains them whenever a test first imports those libraries,
# and its next runs looked like a new environment (CI on 2026-11-30: a worker's third key, its runs unforked and
# test_stage_runner failing).  Each server reports what its preloading set (``Popen.set_on_import``), and
# test_stage_runner checks the report against this list.
SET_ON_IMPORT = ("KMP_INIT_AT_FORK", "KMP_DUPLICATE_LIB_OK", "TORCHINDUCTOR_CACHE_DIR", "PYTORCH_NVML_BASED_CUDA_CHECK")
MAX_SERVERS = 2  # import-time environments served at once (a test may change one, e.g. pop a variable)
_servers: dict = {}  # the import-time environment (sorted items) -> its server process
_lock = threading.Lock()


def _import_time_env(env) -> dict:
    """The variables a run must share with the server; PYTHONPATH is not one (the child puts it on sys.path), nor
    those the libraries set as they load (SET_ON_IMPORT)."""
    return {k: v for k, v in env.items()
            if k.startswith(IMPORT_TIME_ENV) and k != "PYTHONPATH" and k not in SET_ON_IMPORT}


# -- the server (its own process) ------------------------------------------------------------------------------
def serve() -> None:
    """Preload, reply {"set_on_import": the import-time variables the preloading set}, then per request line
    {args, env, cwd, out, err}: fork, reply {"pid"}, wait, reply {"code"}."""
    import importlib

    replies = os.fdopen(os.dup(1), "wb")  # the reply channel; what the modules print goes to stderr instead
    os.dup2(2, 1)
    before = dict(os.environ)
    for name in PRELOAD:
        try:
            importlib.import_module(name)
        except Exception:  # noqa: BLE001 - a module that does not load here loads in the run, as it would
            pass
    new = sorted(k for k in os.environ if k not in before and k.startswith(("PYTORCH", *IMPORT_TIME_ENV)))
    replies.write(json.dumps({"set_on_import": new}).encode() + b"\n")
    replies.flush()
    for line in sys.stdin.buffer:
        req = json.loads(line)
        pid = os.fork()
        if pid == 0:
            replies.close()
            _child(**req)  # never returns
        replies.write(json.dumps({"pid": pid}).encode() + b"\n")
        replies.flush()
        _, status = os.waitpid(pid, 0)
        replies.write(json.dumps({"code": os.waitstatus_to_exitcode(status)}).encode() + b"\n")
        replies.flush()


def _finalize_taichi() -> None:
    """Free the run's Taichi runtime as the interpreter's exit would.  Taichi writes the kernels a process compiled to
    its cache on disk when its runtime is freed (ti.reset, or the program's destructor at exit), never through atexit;
    a forked run ends in os._exit, so without this no forked run ever cached a kernel: every suite compiled again,
    in every run, what only forked runs use (the diverging MPPI of test_contracts: 41-43 s a run, 18 s cached)."""
    if "taichi" not in sys.modules:
        return
    try:
        from topocut.sim.runtime import reset_taichi

        reset_taichi()  # the project's own: drops what holds fields first, frees a runtime however it was started
    except Exception:  # noqa: BLE001 - the cache is a saving; the run's own outcome is already decided
        traceback.print_exc()


def _child(args: list[str], env: dict, cwd: str, out: str, err: str) -> None:
    import random
    import runpy

    code = 1
    try:
        for fd, path, flags in ((0, os.devnull, os.O_RDONLY), (1, out, os.O_WRONLY), (2, err, os.O_WRONLY)):
            f = os.open(path, flags)
            os.dup2(f, fd)
            os.close(f)
        sys.stdin = open(0, closefd=False)  # noqa: SIM115 - the process's own streams, closed by its exit
        sys.stdout = open(1, "w", closefd=False)  # noqa: SIM115 - block-buffered, as into a pipe
        sys.stderr = open(2, "w", buffering=1, closefd=False)  # noqa: SIM115
        signal.signal(signal.SIGINT, signal.default_int_handler)
        os.environ.clear()
        os.environ.update(env)
        os.chdir(cwd)
        extra = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
        sys.path[:1] = [cwd, *extra]  # `python -m`: the working directory, then PYTHONPATH's entries
        random.seed()  # a fresh interpreter's random states, not the server's
        if "numpy" in sys.modules:
            sys.modules["numpy"].random.seed()
        sys.argv = ["-m", *args]
        try:
            runpy.run_module("topocut.run", run_name="__main__", alter_sys=True)
            code = 0
        except SystemExit as e:
            if e.code is None or isinstance(e.code, int):
                code = e.code or 0
            else:
                print(e.code, file=sys.stderr)
        except BaseException:  # noqa: BLE001 - the interpreter's own report of an uncaught exception
            traceback.print_exc()
        threading._shutdown()  # as the interpreter exits: threading's exit hooks (loky's, concurrent.futures'),
        atexit._run_exitfuncs()  # non-daemon threads joined, then the atexit functions
        _finalize_taichi()
        sys.stdout.flush()
        sys.stderr.flush()
    finally:
        os._exit(code)


# -- the client (the test's process) ---------------------------------------------------------------------------
def _key(env) -> tuple:
    return tuple(sorted(_import_time_env(env).items()))


def _server_for(env: dict):
    """The server started with ``env``'s import-time variables (started now if fewer than MAX_SERVERS run), or None."""
    key = _key(env)
    if key not in _servers:
        if len(_servers) >= MAX_SERVERS:
            return None
        proc = subprocess.Popen([sys.executable, "-c", "from tests.stage_runner import serve; serve()"], cwd=REPO,
                                env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        _servers[key] = proc
        atexit.register(proc.kill)
        proc.set_on_import = _reply(proc, None)["set_on_import"]  # once its preloading is done
    return _servers[key]


def _forkable(cmd: list[str], env: dict) -> bool:
    if os.environ.get("TOPOCUT_TEST_FORK", "1") == "0":
        return False
    if len(cmd) < 3 or cmd[0] != sys.executable or list(cmd[1:3]) != ["-m", "topocut.run"]:
        return False
    return _key(env) in _servers or len(_servers) < MAX_SERVERS


def _reply(proc, deadline: float | None) -> dict | None:
    """The server's next reply line, or None past the deadline."""
    while True:
        left = None if deadline is None else deadline - time.monotonic()
        if left is not None and left <= 0:
            return None
        ready, _, _ = select.select([proc.stdout], [], [], left)
        if ready:
            line = proc.stdout.readline()
            if not line:
                raise RuntimeError("tests/stage_runner.py: the stage server died")
            return json.loads(line)


def run(cmd: list[str], cwd=None, env: dict | None = None, timeout: float | None = None,
        check: bool = False) -> subprocess.CompletedProcess:
    """``subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)``, forked from
    the preloaded server where the command allows it (the module docstring)."""
    cmd = [str(c) for c in cmd]
    env = dict(os.environ) if env is None else dict(env)
    cwd = str(Path(cwd or os.getcwd()).resolve())
    proc = _server_for(env) if _forkable(cmd, env) else None
    if proc is None:
        return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout, check=check)
    with _lock, tempfile.TemporaryDirectory(prefix="stage-run-") as tmp:
        out, err = Path(tmp, "stdout"), Path(tmp, "stderr")
        out.touch()
        err.touch()
        req = {"args": cmd[3:], "env": env, "cwd": cwd, "out": str(out), "err": str(err)}
        proc.stdin.write(json.dumps(req).encode() + b"\n")
        proc.stdin.flush()
        pid = _reply(proc, None)["pid"]
        done = _reply(proc, None if timeout is None else time.monotonic() + timeout)
        if done is None:
            os.kill(pid, signal.SIGKILL)
            _reply(proc, None)
        stdout, stderr = (f.read_text(errors="replace") for f in (out, err))
    if done is None:
        raise subprocess.TimeoutExpired(cmd, timeout, output=stdout, stderr=stderr)
    result = subprocess.CompletedProcess(cmd, done["code"], stdout, stderr)
    if check:
        result.check_returncode()
    return result

"""tests/stage_runner.py: a stage run forked from the preloaded server gives what `python -m topocut.run` gives."""
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests import stage_runner

REPO = Path(__file__).resolve().parents[1]
STAMP = re.compile(r"^\[\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}\]")  # the log lines' time


def _cmd(root, *overrides):
    return [sys.executable, "-m", "topocut.run", *overrides, "logger=none", f"outputs_root={root}"]


def _lines(text: str) -> list[str]:
    return [STAMP.sub("[time]", ln) for ln in text.splitlines() if not ln.startswith("[Taichi] version")]


@pytest.fixture(scope="module", autouse=True)
def own_servers():
    """Room for this file's servers whatever environments the worker's earlier files started servers for: only
    the worker's server for this process's own environment (if it has one) is kept in view, and the servers these
    tests start are killed after them."""
    shared = {k: p for k, p in stage_runner._servers.items() if k == stage_runner._key(os.environ)}
    servers = dict(shared)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(stage_runner, "_servers", servers)
        yield servers
    for key, proc in servers.items():
        if key not in shared:
            proc.kill()
            proc.wait()


@pytest.mark.parametrize("overrides", [("stage=simulate", "sim.n_grid=-3"), ("stage=pretrain", "data.version=v999")])
def test_a_forked_run_exits_and_prints_as_a_real_process(tmp_path, overrides):
    env = dict(os.environ, WANDB_MODE="disabled", HYDRA_FULL_ERROR="0")
    assert stage_runner._forkable(_cmd(tmp_path, *overrides), env)
    forked = stage_runner.run(_cmd(tmp_path / "f", *overrides), cwd=REPO, env=env, timeout=120)
    real = subprocess.run(_cmd(tmp_path / "f", *overrides), cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=120)
    assert forked.returncode == real.returncode == 2, forked.stderr + real.stderr
    assert _lines(forked.stderr) == _lines(real.stderr)
    assert _lines(forked.stdout) == _lines(real.stdout)  # but for Taichi's banner, printed where it was imported


def test_the_variables_libraries_set_as_they_load_are_the_ones_the_key_ignores():
    """The server's preloading (the stages' modules, joblib and threadpoolctl) starts from the test process's
    environment; every import-time variable it sets is in SET_ON_IMPORT, so a test process that loads those
    libraries after its first stage run keeps its server."""
    env = dict(os.environ)
    appeared = set(stage_runner._server_for(env).set_on_import)
    assert appeared <= set(stage_runner.SET_ON_IMPORT), appeared - set(stage_runner.SET_ON_IMPORT)
    assert stage_runner._key(dict(env, **dict.fromkeys(stage_runner.SET_ON_IMPORT, "1"))) == stage_runner._key(env)
    # where the test process had not loaded them yet, their loading sets joblib's and threadpoolctl's variables
    fresh = {k: v for k, v in env.items() if k not in stage_runner.SET_ON_IMPORT}
    out = subprocess.run([sys.executable, "-c", "import json, os, joblib, threadpoolctl; print(json.dumps(list(os.environ)))"],
                         env=fresh, capture_output=True, text=True, timeout=60)
    assert {"KMP_INIT_AT_FORK", "KMP_DUPLICATE_LIB_OK"} <= set(json.loads(out.stdout)) - set(fresh), out.stderr


def test_what_is_not_forked(tmp_path, monkeypatch):
    env = dict(os.environ)
    cmd = _cmd(tmp_path, "stage=simulate")
    assert stage_runner._forkable(cmd, env)
    assert stage_runner._key(dict(env, PYTHONPATH=str(tmp_path))) == stage_runner._key(env)  # on the child's sys.path
    assert stage_runner._key(dict(env, OMP_NUM_THREADS="7")) != stage_runner._key(env)  # read as torch loads OpenMP
    monkeypatch.setattr(stage_runner, "_servers", {stage_runner._key(env): None, ("other",): None})
    assert stage_runner._forkable(cmd, env)  # served
    assert not stage_runner._forkable(cmd, dict(env, OMP_NUM_THREADS="7"))  # past MAX_SERVERS: a real process
    assert not stage_runner._forkable(["python3", "-m", "topocut.run"], env)  # another interpreter
    assert not stage_runner._forkable([sys.executable, "-c", "pass"], env)


def test_a_forked_run_past_its_timeout_is_killed(tmp_path):
    with pytest.raises(subprocess.TimeoutExpired):
        stage_runner.run(_cmd(tmp_path, "stage=simulate"), cwd=REPO, timeout=0.05)
    # the server serves the next run
    assert stage_runner.run(_cmd(tmp_path, "stage=simulate", "sim.n_grid=-3"), cwd=REPO, timeout=120).returncode == 2


KERNEL_THEN_EXIT = r"""
import os, sys
import taichi as ti
sys.path.insert(0, {repo!r})
from tests import stage_runner
ti.init(arch=ti.cpu, offline_cache=True, offline_cache_file_path={cache!r}, log_level=ti.ERROR)
x = ti.field(ti.f32, shape=8)

@ti.kernel
def fill(v: ti.f32):
    for i in x:
        x[i] = v * i

fill(2.0)
assert x[3] == 6.0
if {finalize}:
    stage_runner._finalize_taichi()
os._exit(0)  # as a forked run ends
"""


@pytest.mark.parametrize("finalize", [False, True])
def test_a_run_ending_in_os_exit_caches_its_kernels_only_once_taichi_is_freed(tmp_path, finalize):
    """Taichi writes a process's kernels to its cache on disk when its runtime is freed, not at exit: a forked run
    (os._exit) cached none until _finalize_taichi, and every suite compiled its kernels again."""
    cache = tmp_path / "ticache"
    script = tmp_path / "kernel_then_exit.py"  # a file: Taichi reads a kernel's source from it
    script.write_text(KERNEL_THEN_EXIT.format(repo=str(stage_runner.REPO), cache=str(cache), finalize=finalize))
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120,
                          env=dict(os.environ, TI_CPU_MAX_NUM_THREADS="1"))
    assert proc.returncode == 0, proc.stderr[-2000:]
    cached = list(cache.rglob("*.tic"))
    assert bool(cached) == finalize, (finalize, cached)

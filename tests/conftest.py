"""Shared test setup."""
import pytest


@pytest.fixture(scope="module", autouse=True)
def _taichi_single_threaded():
    """A fresh Taichi runtime per test file, single-threaded on the CPU: atomic adds then run in a fixed
    order, so two runs of the same cut are bit-identical (teleop replay, batched vs sequential rollouts).

    Fresh per file (make test gives each file whole to one worker): a file's fields then get the same SNode ids
    whichever files ran before it, so its kernels hit Taichi's cache on disk (topocut.sim.runtime.reset_taichi)."""
    from topocut.sim.runtime import init_taichi, reset_taichi

    reset_taichi()
    init_taichi("cpu", seed=0, cpu_threads=1)
    yield


@pytest.fixture(scope="module")
def one_thread():
    """One torch intra-op thread: for tiny models OpenMP's second thread only adds spin-wait, about 10x
    slower on a loaded 2-core machine. Modules opt in with ``pytestmark = pytest.mark.usefixtures(...)``."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)

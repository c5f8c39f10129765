"""Shared test setup."""
import pytest


@pytest.fixture(scope="session", autouse=True)
def _taichi_single_threaded():
    """One Taichi runtime per test process, single-threaded on the CPU: atomic adds then run in a fixed
    order, so two runs of the same cut are bit-identical (teleop replay, batched vs sequential rollouts)."""
    from topocut.sim.mpm import init_taichi

    init_taichi("cpu", seed=0, cpu_threads=1)
    yield

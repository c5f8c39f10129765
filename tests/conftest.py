"""Shared test setup."""
import pytest

# The longest files first (`make test` passes --no-loadscope-reorder, so pytest-xdist hands files out in this order;
# by default it orders them by their number of tests): the answer key, ~8-10 min on one core, started near the end
# left one worker idle while it ran.  Measured on 2026-11-30 (make test 22:37); the rest keep their collection order.
LONGEST_FIRST = ("test_answer_key_sim.py", "test_sim_separation.py", "test_stages.py", "test_paper_cost.py",
                 "test_reference_writing.py", "test_reference_scooping.py", "test_docs_commands.py",
                 "test_eval_stats.py", "test_reference_check.py", "test_eval_videos.py")


def pytest_collection_modifyitems(session, config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: the rest in collection order


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


def taichi_threads(threads: int) -> None:
    """A fresh Taichi CPU runtime with ``threads`` threads (the fields held before are freed)."""
    from topocut.sim.runtime import init_taichi, reset_taichi

    reset_taichi()
    init_taichi("cpu", cpu_threads=threads)


@pytest.fixture(scope="module")
def taichi_two_threads():
    """Two Taichi threads for a file: the device split's and fields' atomics race as on a GPU (their results must
    not change).  Modules opt in with ``pytestmark = pytest.mark.usefixtures("taichi_two_threads")``."""
    taichi_threads(2)
    yield
    taichi_threads(1)


@pytest.fixture
def taichi_one_thread():
    """One Taichi thread for a test in a two-thread file: the simulator's own atomic adds in a fixed order, so
    two envs' cuts agree bit for bit."""
    taichi_threads(1)
    yield
    taichi_threads(2)

"""Worker processes over a node's GPUs (topocut.utils.devices, issue #53): round robin by the order workers
start, each bound once through CUDA_VISIBLE_DEVICES, the launching process and DDP ranks never."""
import os
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context

import pytest

from topocut.utils import devices as D


@pytest.fixture
def fresh(monkeypatch):
    """No announcement and no binding of this (the launching) process; both restored afterwards."""
    monkeypatch.setenv(D.ENV, "")
    monkeypatch.setattr(D, "_BOUND", {})
    for var in ("CUDA_VISIBLE_DEVICES", "LOCAL_RANK", "RANK", "WORLD_SIZE"):
        monkeypatch.setenv(var, "")  # recorded, so that teardown restores what the test process had
        monkeypatch.delenv(var)
    return monkeypatch


def test_jobs_over_devices_round_robin():
    assert [D.device_for(k, ["0", "1"]) for k in range(5)] == ["0", "1", "0", "1", "0"]
    assert [D.device_for(k, ["2", "5", "7"]) for k in range(7)] == ["2", "5", "7", "2", "5", "7", "2"]


def _claim(slots):
    return D.claim_slot(slots)


def test_workers_starting_at_once_claim_distinct_slots(tmp_path):
    with ProcessPoolExecutor(6, mp_context=get_context("spawn")) as pool:
        got = list(pool.map(_claim, [str(tmp_path)] * 12))
    assert sorted(got) == list(range(12))


def _bound_job(_):
    device = D.bind_worker()
    time.sleep(0.3)  # both workers take a job before either takes a second
    return os.getpid(), device, os.environ.get("CUDA_VISIBLE_DEVICES"), os.environ.get(D.ENV)


def test_each_worker_binds_once_to_its_own_gpu_and_the_launcher_never(fresh):
    assert D.share_gpus(["0", "1"]) == ["0", "1"]
    owner, gpus, slots = D.parse(os.environ[D.ENV])
    assert owner == os.getpid() and gpus == ["0", "1"] and os.path.isdir(slots)
    assert D.share_gpus(["3", "4", "5"]) == ["0", "1"]  # announced once: an outer launcher's stands
    with ProcessPoolExecutor(2, mp_context=get_context("spawn")) as pool:
        rows = list(pool.map(_bound_job, range(6)))
    by_pid = {}
    for pid, device, visible, announced in rows:
        by_pid.setdefault(pid, set()).add((device, visible))
        assert announced is None  # a bound worker's own workers stay on its GPU
    assert len(by_pid) == 2 and all(len(v) == 1 for v in by_pid.values())  # bound once, for good
    assert sorted(d for (d, v), in by_pid.values()) == ["0", "1"]  # one worker per GPU
    assert all(d == v for (d, v), in by_pid.values())  # Taichi, Warp and torch see it as device 0
    assert D.bind_worker() is None and "CUDA_VISIBLE_DEVICES" not in os.environ  # the launcher keeps every GPU


def test_one_gpu_or_none_announces_nothing(fresh):
    assert D.share_gpus([]) == [] and D.share_gpus(["0"]) == []
    assert not os.environ.get(D.ENV)
    assert D.bind_worker() is None


def test_visible_gpus_follow_cuda_visible_devices(fresh):
    fresh.setenv("CUDA_VISIBLE_DEVICES", "2, 3")
    assert D.visible_gpus() == ["2", "3"]
    fresh.setenv("CUDA_VISIBLE_DEVICES", "-1")
    assert D.visible_gpus() == []


def test_a_ddp_rank_is_not_bound(fresh, tmp_path):
    fresh.setenv(D.ENV, f"{os.getpid() + 1}:0,1:{tmp_path}")  # announced by another process
    fresh.setenv("LOCAL_RANK", "1")
    fresh.setenv("WORLD_SIZE", "2")
    assert D.bind_worker() is None and "CUDA_VISIBLE_DEVICES" not in os.environ
    assert list(tmp_path.iterdir()) == []  # no slot taken


def test_a_worker_outside_ddp_binds(fresh, tmp_path):
    fresh.setenv(D.ENV, f"{os.getpid() + 1}:4,6:{tmp_path}")
    assert D.bind_worker() == "4" and os.environ["CUDA_VISIBLE_DEVICES"] == "4"
    assert D.bind_worker() == "4"  # the first answer stands
    assert not os.environ.get(D.ENV)

"""topocut.utils.training: DataLoader workers inside a joblib (loky) job, as under Hydra's joblib launcher."""
import pytest


def _load_with_workers(num_workers: int) -> float:
    import torch
    from torch.utils.data import DataLoader, TensorDataset

    from topocut.utils.training import worker_context

    data = TensorDataset(torch.arange(8, dtype=torch.float32))
    loader = DataLoader(data, batch_size=4, num_workers=num_workers, multiprocessing_context=worker_context(num_workers))
    return float(sum(batch[0].sum() for batch in loader))


def test_dataloader_workers_start_inside_a_loky_worker():
    joblib = pytest.importorskip("joblib")
    # plain torch fails there: loky's default start method gives Process objects DataLoader cannot start
    out = joblib.Parallel(n_jobs=2, backend="loky")(joblib.delayed(_load_with_workers)(1) for _ in range(2))
    assert out == [sum(range(8))] * 2


def test_worker_context_is_default_outside_loky_and_for_no_workers():
    from topocut.utils.training import worker_context

    assert worker_context(0) is None and worker_context(2) is None  # pytest runs with the standard start method

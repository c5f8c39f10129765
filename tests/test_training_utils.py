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


class _Fit:
    """The parts of a Lightning Trainer that finish_fit and MetricHistory read."""

    def __init__(self, rank=0, metrics=None, epoch=0):
        self.global_rank, self.is_global_zero = rank, rank == 0
        self.callback_metrics, self.current_epoch = dict(metrics or {}), epoch


def _writer(tmp_path):
    from topocut.data.store import ArtifactStore

    writer, _ = ArtifactStore(tmp_path).begin("checkpoint", "perception", {"k": 1})
    return writer


def test_finish_fit_writes_on_rank_zero_only(tmp_path):
    from topocut.utils.training import MetricHistory, finish_fit, work_dir

    writer = _writer(tmp_path)
    work = work_dir(writer)
    assert work.parent == writer.path.parent and not str(work).startswith(str(writer.path))
    work.mkdir()
    (work / "last.ckpt").write_text("weights")
    history = MetricHistory(work / "history.json")
    assert finish_fit(_Fit(rank=1, metrics={"val/loss": 0.5}), writer, work, history) is None
    assert list(writer.path.iterdir()) == []  # rank 1 touches nothing: rank 0 commits
    metrics = finish_fit(_Fit(rank=0, metrics={"val/loss": 0.5}), writer, work, history)
    assert metrics == {"val/loss": 0.5}
    assert (writer.path / "model.ckpt").read_text() == "weights"
    assert {p.name for p in writer.path.iterdir()} == {"model.ckpt", "loss.png", "history.json"}


def test_history_survives_a_resume_and_gives_the_metrics_of_a_finished_fit(tmp_path):
    from topocut.utils.training import MetricHistory, finish_fit, work_dir

    writer = _writer(tmp_path)
    work = work_dir(writer)
    work.mkdir()
    (work / "last.ckpt").write_text("weights")
    first = MetricHistory(work / "history.json")
    for epoch, loss in enumerate([0.9, 0.7, 0.6]):
        first.on_train_epoch_end(_Fit(metrics={"train/loss": loss}, epoch=epoch), None)
    # killed after epoch 2's rows were saved but before its checkpoint: the resumed run repeats epoch 2
    resumed = MetricHistory(work / "history.json")
    assert [r["train/loss"] for r in resumed.rows] == [0.9, 0.7, 0.6]
    resumed.on_train_epoch_end(_Fit(metrics={"train/loss": 0.55}, epoch=2), None)
    assert [(r["epoch"], r["train/loss"]) for r in resumed.rows] == [(0, 0.9), (1, 0.7), (2, 0.55)]
    # a fit resumed after its last epoch trains nothing and logs nothing: metrics come from the history
    again = MetricHistory(work / "history.json")
    assert finish_fit(_Fit(metrics={}), writer, work, again) == {"train/loss": 0.55}

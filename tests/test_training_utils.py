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


def _last_ckpt(work):
    """A Lightning-shaped last.ckpt: the model, its hyper-parameters, and the training state to resume from."""
    import torch

    torch.save({"state_dict": {"w": torch.arange(3.0)}, "hyper_parameters": {"k": 1}, "epoch": 7,
                "optimizer_states": [{"state": {0: {"exp_avg": torch.ones(3)}}}], "lr_schedulers": [{}]},
               work / "last.ckpt")


def test_finish_fit_writes_on_rank_zero_only(tmp_path):
    from topocut.utils.training import MetricHistory, finish_fit, work_dir

    writer = _writer(tmp_path)
    work = work_dir(writer)
    assert work.parent == writer.path.parent and not str(work).startswith(str(writer.path))
    work.mkdir()
    _last_ckpt(work)
    history = MetricHistory(work / "history.json")
    assert finish_fit(_Fit(rank=1, metrics={"val/loss": 0.5}), writer, work, history) is None
    assert list(writer.path.iterdir()) == []  # rank 1 touches nothing: rank 0 commits
    metrics = finish_fit(_Fit(rank=0, metrics={"val/loss": 0.5}), writer, work, history)
    assert metrics == {"val/loss": 0.5}
    import torch

    model = torch.load(writer.path / "model.ckpt", weights_only=False)
    assert set(model) == {"state_dict", "hyper_parameters", "epoch"}  # the optimiser's and scheduler's state left out
    assert torch.equal(model["state_dict"]["w"], torch.arange(3.0)) and model["epoch"] == 7
    assert {p.name for p in writer.path.iterdir()} == {"model.ckpt", "loss.png", "history.json"}


def test_history_survives_a_resume_and_gives_the_metrics_of_a_finished_fit(tmp_path):
    from topocut.utils.training import MetricHistory, finish_fit, work_dir

    writer = _writer(tmp_path)
    work = work_dir(writer)
    work.mkdir()
    _last_ckpt(work)
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


def test_forked_step_and_epoch_names_are_left_out_of_history_and_metrics(tmp_path):
    from topocut.utils.training import MetricHistory, finish_fit, work_dir

    writer = _writer(tmp_path)
    work = work_dir(writer)
    work.mkdir()
    _last_ckpt(work)
    logged = {"train/loss": 4.0, "train/loss_step": 6.0, "train/loss_epoch": 4.0, "val/loss": 1.0, "lr_step": 0.1}
    history = MetricHistory(work / "history.json")
    history.on_train_epoch_end(_Fit(metrics=logged), None)
    assert history.rows == [{"epoch": 0, "phase": "train", "train/loss": 4.0, "val/loss": 1.0, "lr_step": 0.1}]
    assert finish_fit(_Fit(metrics=logged), writer, work, history) == {"train/loss": 4.0, "val/loss": 1.0,
                                                                        "lr_step": 0.1}


def _dynamics():
    from topocut.models import DynamicsModule

    module = DynamicsModule({"num_points": 4, "hidden": 8, "num_heads": 2, "num_layers": 1, "pointnet_dims": [8]})

    def patch(losses):
        module._step = lambda batch: (None, None, dict.fromkeys(("loss", "loss_pos", "loss_topo"), losses()))
    return module, patch


def _pddp():
    from topocut.policies import PDDPConfig, PolicyTrainConfig
    from topocut.policies.module import PDDPModule

    module = PDDPModule(PDDPConfig(n_blocks=1, hidden=16, obs_dim=16, n_heads=2, cond_dim=16, time_freq_dim=16,
                                   goal_hidden=8), "none", train=PolicyTrainConfig(num_points=4, num_goal_points=4))

    def patch(losses):
        module.loss = lambda batch, **kw: losses()
    return module, patch


def _pose():
    from topocut.policies.baselines.module import PoseDiffusionModule

    module = PoseDiffusionModule(kind="dp3", enc_dim=8, down_dims=(8, 16), horizon=2)

    def patch(losses):
        module.compute_loss = lambda batch, generator=None: losses()
    return module, patch


@pytest.mark.parametrize("build", [_dynamics, _pddp, _pose], ids=["dynamics", "pddp", "pose"])
def test_history_records_the_epoch_mean_of_the_training_loss(build, tmp_path):
    """Batches of 2, 2 and 1 samples with losses 5, 1 and 6: the epoch's loss is (2*5 + 2*1 + 6) / 5 = 3.6,
    not the last batch's 6 (what loss.png and history.json showed)."""
    import lightning as L
    import torch
    from torch.utils.data import DataLoader

    from topocut.utils.training import MetricHistory

    torch.manual_seed(0)
    module, patch = build()
    values = iter([5.0, 1.0, 6.0])  # one per batch
    anchor = next(p for p in module.parameters() if p.requires_grad)  # a loss the optimiser can step on

    def losses():
        return torch.tensor(next(values)) + 0 * anchor.sum()
    patch(losses)
    batches = [{"x_t": torch.zeros(b, 4, 3), "points": torch.zeros(b, 4, 3), "mask": torch.zeros(b, 4)}
               for b in (2, 2, 1)]
    history = MetricHistory()
    trainer = L.Trainer(accelerator="cpu", max_epochs=1, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, callbacks=[history],
                        default_root_dir=tmp_path, log_every_n_steps=1)
    trainer.fit(module, DataLoader(batches, batch_size=None))
    row = history.rows[0]
    assert row["train/loss"] == pytest.approx(3.6) and "train/loss_step" not in row
    if build is _dynamics:
        assert row["train/loss_pos"] == pytest.approx(3.6) and row["train/loss_topo"] == pytest.approx(3.6)


def test_build_trainer_writes_last_ckpt_every_epoch_and_a_resume_continues(tmp_path):
    """A fit killed after epoch k must find work/last.ckpt of epoch k (Lightning's save_last with save_top_k=0
    wrote it only when fit returned); resuming from it trains the remaining epochs only."""
    from types import SimpleNamespace

    import lightning as L
    import torch
    from lightning.pytorch.callbacks import Callback
    from torch.utils.data import DataLoader, TensorDataset

    from topocut.utils.training import build_trainer, resume_path

    class Tiny(L.LightningModule):
        def __init__(self):
            super().__init__()
            self.lin = torch.nn.Linear(1, 1)

        def training_step(self, batch, i):
            return self.lin(batch[0]).pow(2).mean()

        def validation_step(self, batch, i):
            self.log("val/loss", self.lin(batch[0]).pow(2).mean())

        def configure_optimizers(self):
            return torch.optim.SGD(self.parameters(), lr=0.01)

    class Watch(Callback):  # what a process killed at the start of each epoch would leave behind
        def __init__(self):
            self.epochs, self.saved = [], []

        def on_train_epoch_start(self, trainer, module):
            self.epochs.append(trainer.current_epoch)
            last = tmp_path / "work" / "last.ckpt"
            if last.exists():
                ck = torch.load(last, map_location="cpu", weights_only=False)
                self.saved.append((trainer.current_epoch, ck["epoch"], ck["global_step"]))

    cfg = SimpleNamespace(accelerator="cpu", devices=1, strategy="auto", precision="32-true", max_steps=-1,
                          log_every_n_steps=1)
    data = DataLoader(TensorDataset(torch.ones(6, 1)), batch_size=2)  # 3 steps per epoch
    watch = Watch()
    build_trainer(cfg, 2, tmp_path / "work", progress=False, callbacks=[watch]).fit(Tiny(), data, data)
    assert watch.saved == [(1, 0, 3)]  # before epoch 1: epoch 0's checkpoint, written during the fit
    assert sorted(p.name for p in (tmp_path / "work").iterdir()) == ["last.ckpt"]
    assert torch.load(tmp_path / "work" / "last.ckpt", weights_only=False)["global_step"] == 6
    again = Watch()
    fit = build_trainer(cfg, 3, tmp_path / "work", progress=False, callbacks=[again])
    fit.fit(Tiny(), data, data, ckpt_path=resume_path(tmp_path / "work"))
    assert again.epochs == [2] and fit.global_step == 9  # resumed after epoch 1: epoch 2 only
    assert torch.load(tmp_path / "work" / "last.ckpt", weights_only=False)["global_step"] == 9
    # trainer.profiler: Lightning's report of the fit in the run's directory, one row per hook with its calls
    cfg.profiler = "simple"
    build_trainer(cfg, 2, tmp_path / "work2", progress=False, run_dir=tmp_path / "run").fit(Tiny(), data, data)
    rows = {r[0]: r[1:] for r in (
        [c.strip() for c in line.strip().strip("|").split("|")] for line in
        (tmp_path / "run" / "fit-profile.txt").read_text().splitlines() if line.startswith("|"))}
    assert rows["[Strategy]SingleDeviceStrategy.training_step"][1] == "6"  # 2 epochs x 3 steps
    assert rows["run_training_epoch"][1] == "2" and float(rows["run_training_epoch"][2]) > 0
    with pytest.raises(ValueError, match="trainer.profiler='fast'.*simple"):
        build_trainer(SimpleNamespace(**{**vars(cfg), "profiler": "fast"}), 1, tmp_path / "w3", progress=False)


_LOG_SCRIPT = """
import logging, sys
if {root_first}:
    logging.basicConfig(stream=sys.stderr, format="ROOT %(message)s", level=logging.INFO)  # as Hydra does
import lightning  # noqa: F401  (adds its own console handler)
if not {root_first}:
    logging.basicConfig(stream=sys.stderr, format="ROOT %(message)s", level=logging.INFO)
from topocut.utils.training import route_lightning_logs
route_lightning_logs()
logging.getLogger("lightning.pytorch.utilities.rank_zero").info("GPU available: False")
logging.getLogger("lightning.fabric.utilities.rank_zero").info("seed set")
"""


@pytest.mark.parametrize("root_first", [True, False])
def test_lightning_lines_are_printed_once_through_the_root_handler(root_first):
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _LOG_SCRIPT.format(root_first=root_first)], capture_output=True,
                         text=True, timeout=120, check=True)
    lines = [ln for ln in out.stderr.splitlines() if "GPU available" in ln or "seed set" in ln]
    assert lines == ["ROOT GPU available: False", "ROOT seed set"], out.stderr

"""Lightning plumbing shared by the training stages: trainer construction, loss history, splits."""
from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import torch
from lightning.pytorch.callbacks import Callback


def epoch_metrics(metrics) -> dict[str, float]:
    """Scalar copies of ``trainer.callback_metrics`` without Lightning's forked names.

    A value logged with on_step and on_epoch appears as ``name`` (the epoch mean once the epoch ends),
    ``name_step`` (the last batch) and ``name_epoch``; only ``name`` is kept.
    """
    out = {}
    for k, v in metrics.items():
        base = k.rsplit("_", 1)[0]
        if k.endswith(("_step", "_epoch")) and base in metrics:
            continue
        try:
            out[k] = float(v)
        except (TypeError, ValueError):
            continue
    return out


class EpochMeans(torch.nn.Module):
    """Sample-weighted means of scalars over an epoch and over all DDP ranks (one torchmetrics MeanMetric each).

    Call ``update`` for every name at every step, with an empty tensor when a batch has no sample of that kind:
    the metrics synchronise across ranks when computed, so every rank must hold every metric.  ``log(module)``
    at epoch end logs the names that saw any sample (NaN values are ignored with their weight) and resets.
    """

    def __init__(self, names):
        super().__init__()
        from torchmetrics import MeanMetric

        self.names = tuple(names)
        self.means = torch.nn.ModuleDict({n: MeanMetric(nan_strategy="ignore") for n in self.names})

    def update(self, name: str, values, weight=None) -> None:
        """``values``: per-sample values (weight 1 each), or a batch mean with ``weight`` = the batch size."""
        metric = self.means[name]
        v = torch.as_tensor(values).detach().to(device=metric.device, dtype=torch.float32).reshape(-1)
        w = torch.ones_like(v) if weight is None else torch.as_tensor(weight, dtype=torch.float32,
                                                                      device=v.device).expand_as(v)
        metric.update(v, w)

    def compute(self) -> dict[str, torch.Tensor]:
        """The epoch means (the same on every rank), for the names with any sample; then reset."""
        out = {}
        for name in self.names:  # a fixed order: each compute is a collective under DDP
            value = self.means[name].compute()
            self.means[name].reset()
            if torch.isfinite(value):
                out[name] = value
        return out

    def log(self, module, prog_bar=()) -> dict[str, torch.Tensor]:
        values = self.compute()
        for name, value in values.items():  # already global: sync_dist only keeps Lightning's DDP check quiet
            module.log(name, value, prog_bar=name in prog_bar, sync_dist=True)
        return values


class MetricHistory(Callback):
    """Epoch-level copies of the logged scalars, for plots and metrics.json.

    With ``path`` the rows are saved after every epoch (rank 0) and loaded again by the next run, so a resumed
    fit keeps the epochs trained before the interruption (a repeated epoch replaces its earlier row).
    """

    def __init__(self, path: Path | None = None):
        self.path = Path(path) if path is not None else None
        self.rows: list[dict] = json.loads(self.path.read_text()) if self.path and self.path.exists() else []

    def _record(self, trainer, phase: str) -> None:
        row = {"epoch": trainer.current_epoch, "phase": phase, **epoch_metrics(trainer.callback_metrics)}
        self.rows = [r for r in self.rows if (r["epoch"], r["phase"]) != (row["epoch"], phase)] + [row]
        if self.path is not None and trainer.is_global_zero:
            self.dump(self.path)

    def on_train_epoch_end(self, trainer, pl_module) -> None:
        self._record(trainer, "train")

    def last(self) -> dict:
        return {k: v for k, v in (self.rows[-1] if self.rows else {}).items() if k not in ("phase",)}

    def plot(self, path: Path, keys=("train/loss", "val/loss")) -> Path:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(5, 3.2))
        for key in keys:
            pts = [(r["epoch"], r[key]) for r in self.rows if key in r]
            if pts:
                ax.plot(*zip(*pts), marker=".", label=key)
        ax.set_xlabel("epoch")
        ax.set_ylabel("loss")
        if ax.lines:
            ax.legend()
        fig.tight_layout()
        fig.savefig(path, dpi=120)
        plt.close(fig)
        return Path(path)

    def dump(self, path: Path) -> None:
        from topocut.data.store import write_json_atomic

        write_json_atomic(Path(path), self.rows)


def route_lightning_logs() -> None:
    """Print each Lightning log line once, in the run's format, and keep it in the run's log file.

    ``import lightning`` gives the ``lightning`` logger a console handler of its own ("INFO: ..."), while its
    sub-loggers propagate to the root, which Hydra gives a console and a file handler: every line came out
    twice.  Where the root has handlers, Lightning's own console handlers go and its loggers propagate.
    """
    if not logging.getLogger().handlers:
        return  # a bare script: Lightning's own handlers are the only ones
    for name in ("lightning", "lightning.pytorch", "lightning.fabric"):
        lg = logging.getLogger(name)
        for h in list(lg.handlers):
            if type(h) is logging.StreamHandler:  # Lightning's, not a FileHandler (a StreamHandler subclass)
                lg.removeHandler(h)
        lg.propagate = True


class EpochLines(Callback):
    """One log line per epoch, every metric under its whole name, in place of Lightning's progress bar where the
    output is not a terminal (a log file, a CI log): the bar's last frame landed there squeezed into a narrow
    column, names cut short (``val/cluster_err_re…  -231.000``) and no line per epoch."""

    def on_train_epoch_end(self, trainer, pl_module) -> None:  # after the epoch's validation
        if trainer.sanity_checking or not trainer.is_global_zero:
            return
        metrics = epoch_metrics(trainer.callback_metrics)
        logging.getLogger("topocut.progress").info(
            "epoch %d/%d: %s", trainer.current_epoch + 1, trainer.max_epochs,
            ", ".join(f"{k} {v:.4g}" for k, v in metrics.items()))


def build_trainer(trainer_cfg, max_epochs: int, ckpt_dir: Path, logger=False, progress: bool = True,
                  callbacks=(), gradient_clip_val: float | None = None, run_dir: Path | None = None):
    """A Lightning Trainer from the `trainer` config group (accelerator, devices, strategy, precision, profiler).

    ``ckpt_dir/last.ckpt`` is rewritten after every epoch (after its validation), the resume point of
    ``resume_path``.  (Lightning's ``save_last=True`` with ``save_top_k=0`` writes it only when fit returns.)
    ``trainer.profiler`` other than none: Lightning's profiler of that name, its report ``fit-profile.txt`` in
    ``run_dir`` (else ``ckpt_dir``).
    """
    import lightning as L
    from lightning.pytorch.callbacks import ModelCheckpoint
    from rich.console import Console

    route_lightning_logs()
    if progress and not Console().is_terminal:  # a log: lines per epoch, not a bar's last frame (EpochLines)
        progress, callbacks = False, [*callbacks, EpochLines()]
    ckpt = ModelCheckpoint(dirpath=str(ckpt_dir), filename="last", monitor=None, save_top_k=1, every_n_epochs=1,
                           enable_version_counter=False)
    return L.Trainer(accelerator=trainer_cfg.accelerator, devices=trainer_cfg.devices, strategy=trainer_cfg.strategy,
                     precision=trainer_cfg.precision, max_epochs=max_epochs, max_steps=trainer_cfg.max_steps,
                     logger=logger, callbacks=[ckpt, *callbacks], enable_progress_bar=progress,
                     log_every_n_steps=trainer_cfg.log_every_n_steps, default_root_dir=str(ckpt_dir),
                     gradient_clip_val=gradient_clip_val, enable_model_summary=False, deterministic=False,
                     profiler=build_profiler(getattr(trainer_cfg, "profiler", "none"), run_dir or ckpt_dir))


def build_profiler(name: str, dirpath: Path):
    """Lightning's profiler called ``name`` writing ``dirpath/fit-profile.txt``; None for none."""
    if name == "none":
        return None
    from lightning.pytorch import profilers

    kinds = {"simple": profilers.SimpleProfiler, "advanced": profilers.AdvancedProfiler,
             "pytorch": profilers.PyTorchProfiler}
    if name not in kinds:
        raise ValueError(f"trainer.profiler={name!r} is not a profiler; valid: none, {', '.join(kinds)}")
    return kinds[name](dirpath=str(dirpath), filename="profile")


def work_dir(writer) -> Path:
    """Lightning's checkpoints while a version is trained: beside its partial directory, not inside it, so that
    they are not part of the committed files and survive until the version is committed (the resume point)."""
    return writer.path.parent / f".work-{writer.key}"


# What a committed model leaves out of Lightning's checkpoint: it is loaded (load_from_checkpoint), never resumed
# (an interrupted fit resumes from the work area's last.ckpt). Adam's two moments are 2/3 of a checkpoint's bytes,
# and committed checkpoints travel between machines in pieces (docs/results.md)
TRAINING_STATE = ("optimizer_states", "lr_schedulers")


def model_checkpoint(src: Path, dst: Path) -> None:
    """``src`` (a Lightning checkpoint) without TRAINING_STATE, saved at ``dst``."""
    ckpt = torch.load(src, map_location="cpu", weights_only=False)
    for key in TRAINING_STATE:
        ckpt.pop(key, None)
    torch.save(ckpt, dst)


def finish_fit(fit, writer, work: Path, history: MetricHistory) -> dict | None:
    """After ``fit.fit``: on global rank 0, write the last checkpoint's model to ``model.ckpt`` in the version
    (``model_checkpoint``) and ``loss.png`` and ``history.json``; returns the final metrics (the last epoch's row
    of ``history`` when the fit was resumed from a checkpoint that had already finished).  Other DDP ranks return
    None and touch no file: under Lightning's DDP launcher every rank runs the stage's code, and only rank 0
    commits.
    """
    if not fit.is_global_zero:
        return None
    metrics = epoch_metrics(fit.callback_metrics)
    if not metrics:  # resumed after its last epoch: this process trained and logged nothing
        metrics = {k: v for k, v in history.last().items() if k != "epoch"}
    model_checkpoint(Path(work) / "last.ckpt", writer.path / "model.ckpt")
    history.plot(writer.path / "loss.png")
    history.dump(writer.path / "history.json")
    return metrics


def resume_path(ckpt_dir: Path) -> str | None:
    """'last.ckpt' of an interrupted fit in this work area, if any (Lightning resumes from it)."""
    last = Path(ckpt_dir) / "last.ckpt"
    return str(last) if last.exists() else None


def split_episodes(objects: list[str], val_fraction: float, seed: int, held_out=()) -> dict[str, list[int]]:
    """Episode indices per split: train/val among seen objects, 'unseen' for held-out objects."""
    unseen = [e for e, o in enumerate(objects) if o in held_out]
    seen = np.array([e for e, o in enumerate(objects) if o not in held_out], dtype=np.int64)
    np.random.default_rng(seed).shuffle(seen)
    n_val = int(round(val_fraction * len(seen)))
    if val_fraction > 0 and len(seen) > 1:
        n_val = max(n_val, 1)
    n_val = min(n_val, max(len(seen) - 1, 0))
    return {"train": sorted(seen[n_val:].tolist()), "val": sorted(seen[:n_val].tolist()), "unseen": unseen}


def data_loader(dataset, batch_size: int, num_workers: int = 0, pin_memory: bool | None = None, **kw):
    """A training run's DataLoader: ``num_workers`` > 0 keeps its workers through the fit (started in the
    platform's way inside a joblib worker: ``worker_context``); batches pinned in page-locked memory when
    ``pin_memory`` (None: when CUDA is present).  ``kw``: shuffle, drop_last, ..."""
    import torch
    from torch.utils.data import DataLoader

    pin = torch.cuda.is_available() if pin_memory is None else bool(pin_memory)
    return DataLoader(dataset, batch_size=batch_size, num_workers=num_workers, persistent_workers=num_workers > 0,
                      pin_memory=pin, multiprocessing_context=worker_context(num_workers), **kw)


def worker_context(num_workers: int):
    """multiprocessing context for DataLoader workers (None: torch's default).

    Inside a worker of Hydra's joblib launcher the default start method is loky's, whose Process torch's
    DataLoader cannot start ("'Process' object has no attribute 'env'", then Lightning's "Please call
    `iter(combined_loader)` first"); there we ask for the platform's standard method instead.
    """
    import multiprocessing as mp
    import sys

    if num_workers <= 0 or mp.get_start_method(allow_none=True) in (None, "fork", "spawn", "forkserver"):
        return None
    return mp.get_context("fork" if sys.platform.startswith("linux") else "spawn")

"""stage=pretrain: the dynamics model F (and its encoder Φ) on a dataset version -> checkpoint/perception."""
from __future__ import annotations

import json
import shutil

from pipelines._common import as_dict
from topocut.utils.context import RunContext


def checkpoint_name(model) -> str:
    return "perception" if model.model == "graph_transformer" else f"perception-{model.model}"


def run(ctx: RunContext, model, trainer, data) -> dict:
    # Lightning's import (~7 s on a 2-core CPU) in the run, not when the config check imports this module
    from topocut.models import DynamicsModule, EpisodeDataModule
    from topocut.utils.training import MetricHistory, build_trainer, finish_fit, resume_path, work_dir

    ds_path = ctx.store.resolve("dataset", data.dataset, data.version)
    inputs = {"dataset": ctx.store.ref(ds_path)}
    config = as_dict(("model", model), ("trainer", trainer), ("seed", ctx.seed))
    for key in ("jobs", "profiler"):  # how many trainings run at once, what is measured: not what is trained
        config["trainer"].pop(key, None)
    name = checkpoint_name(model)
    writer, existing = ctx.store.begin("checkpoint", name, config, inputs, extra={"seed": ctx.seed,
                                                                                  "device": ctx.device})
    if existing is not None:
        return {"checkpoint": str(existing), "reused": True}
    dm = EpisodeDataModule(str(ds_path / "data.zarr"), num_points=model.num_points, sort=model.sort,
                           noise_std=model.noise_std if model.noise else 0.0, num_labels=model.num_labels,
                           batch_size=trainer.batch_size, num_workers=trainer.num_workers,
                           val_fraction=trainer.val_fraction, held_out_objects=trainer.held_out_objects,
                           seed=ctx.seed)
    module = DynamicsModule(model)
    work = work_dir(writer)  # Lightning's own checkpoints while training (resume point)
    history = MetricHistory(work / "history.json")
    fit = build_trainer(trainer, trainer.max_epochs, work, logger=ctx.logger.lightning(ctx.run_dir),
                        progress=ctx.progress, callbacks=[history], run_dir=ctx.run_dir)
    fit.fit(module, datamodule=dm, ckpt_path=resume_path(work))
    metrics = finish_fit(fit, writer, work, history)
    if metrics is None:  # a DDP rank other than 0: rank 0 commits
        return {"rank": fit.global_rank}
    (writer.path / "metrics.json").write_text(json.dumps({"metrics": metrics, "split": dm.split}, indent=2))
    summary = {"model": model.model, "parameters": sum(p.numel() for p in module.parameters()),
               "train_episodes": len(dm.split["train"]), **{k: round(v, 5) for k, v in metrics.items()}}
    path = writer.commit(summary)
    shutil.rmtree(work, ignore_errors=True)
    ctx.logger.log_image("pretrain/loss", path / "loss.png")
    return {"checkpoint": str(path), **summary}

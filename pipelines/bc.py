"""stage=bc: behaviour cloning on a dataset version -> one checkpoint per policy.

The learned policies of ``topocut.policies.registry``: ``pddp`` (frozen pretrained encoder Φ from
checkpoint/perception), ``pddp_noperc`` (raw points, encoder trained from scratch with the policy),
``pddp_graphconv`` (self-attention GraphConv encoder trained with the policy), and the baselines ``dp3`` and
``3dda`` (one knife pose per step, DDPM/DDIM), all on the same episodes and the same inputs
(``topocut.policies.inputs``: the observation, the action history, the goal cloud with its piece labels).

The run's ``seed`` is the training seed (weights, batches, the train/val episode split); it keys the checkpoint and
is recorded in its manifest.  Several seeds are a Hydra multirun, ``python -m topocut.run -m stage=bc seed=0,1,2``:
one version per seed, which ``stage=eval eval.train_seeds=3`` evaluates and pools (docs/evaluation.md).
"""
from __future__ import annotations

import json
import shutil

from pipelines._common import as_dict
from topocut.policies import registry
from topocut.utils.context import RunContext


def _loaders(dataset, split, batch_size: int, num_workers: int):
    """Training and validation loaders (``data_loader``: with ``num_workers`` > 0, workers that live through the
    fit; PolicyDataset's per-item FPS made a PDDP epoch wait on its loader 3/4 of the time with none on an H200)."""
    from topocut.utils.training import data_loader

    train, val = split["train"], split["val"] + split["unseen"]
    return (data_loader(dataset(train), batch_size, num_workers, shuffle=True, drop_last=len(train) > batch_size),
            data_loader(dataset(val), batch_size, num_workers) if val else None)


# policy.train keys each learned policy's training sets itself (registry.training_setup): a value given on the
# command line would be overwritten, so it is refused instead, naming what sets it
SET_PER_POLICY = {
    "encoder": "each policy's own encoder (the registry: pddp pretrained, pddp_noperc none, pddp_graphconv "
               "graphconv); choose the policy with stage.run.policies",
    "encoder_ckpt": "data.encoder and data.encoder_version (the perception checkpoint stage=pretrain made)",
    "seed": "the run's seed (seed=...)",
}


def check_train_keys(train) -> None:
    """ConfigError (exit status 2) naming a ``policy.train`` key of SET_PER_POLICY given a value other than its
    default."""
    from topocut.config import ConfigError
    from topocut.policies.config import PolicyTrainConfig

    default = PolicyTrainConfig()
    for key, source in SET_PER_POLICY.items():
        if getattr(train, key) != getattr(default, key):
            raise ConfigError(f"policy.train.{key}={getattr(train, key)!r}: stage=bc takes it from {source}; "
                             f"leave policy.train.{key} at {getattr(default, key)!r}")


def run(ctx: RunContext, policy, trainer, data, policies: list[str]) -> dict:
    # Lightning's import (~7 s on a 2-core CPU) in the run, not when the config check imports this module
    from topocut.data.episodes import EpisodeDataset
    from topocut.utils.training import MetricHistory, build_trainer, finish_fit, resume_path, split_episodes, work_dir

    registry.check(policies, "stage.run.policies", registry.learned())
    check_train_keys(policy.train)
    ds_path = ctx.store.resolve("dataset", data.dataset, data.version)
    ds = EpisodeDataset(ds_path / "data.zarr", in_memory=True)
    steps = [ds[i] for i in range(len(ds))]
    objects = [str(ds.meta(e).get("object", "")) for e in range(ds.num_episodes)]
    ep_split = split_episodes(objects, policy.train.val_fraction, ctx.seed, trainer.held_out_objects)
    if not ep_split["train"]:
        raise ValueError(f"{ds_path}: no training episodes (held out: {trainer.held_out_objects})")
    split = {k: [i for e in v for i in range(*ds.episode_range(e))] for k, v in ep_split.items()}
    results = {}
    for name in policies:
        inputs = {"dataset": ctx.store.ref(ds_path)}
        encoder_ckpt = None
        if registry.get(name).encoder == "pretrained":
            enc_path = ctx.store.resolve("checkpoint", data.encoder, data.encoder_version)
            inputs["encoder"] = ctx.store.ref(enc_path)
            encoder_ckpt = str(enc_path / "model.ckpt")
        config = as_dict(("policy", policy), ("trainer", trainer), ("kind", name), ("seed", ctx.seed))
        for key in ("jobs", "profiler"):  # how many trainings run at once, what is measured: not what is trained
            config["trainer"].pop(key, None)
        for key in ("val_sample_every", "sample"):  # how often val/mask_acc is measured, where the FPS runs: likewise
            config["policy"]["train"].pop(key, None)
        writer, existing = ctx.store.begin("checkpoint", name, config, inputs, extra={"seed": ctx.seed})
        if existing is not None:
            results[name] = {"checkpoint": str(existing), "seed": ctx.seed, "reused": True}
            continue
        module, dataset, clip = registry.training_setup(name, policy, steps, split["train"], ctx.seed, encoder_ckpt)
        train_dl, val_dl = _loaders(dataset, split, policy.train.batch_size, policy.train.num_workers)
        work = work_dir(writer)
        history = MetricHistory(work / "history.json")
        fit = build_trainer(trainer, policy.train.max_epochs, work, logger=ctx.logger.lightning(ctx.run_dir),
                            progress=ctx.progress, callbacks=[history], gradient_clip_val=clip,
                            run_dir=ctx.run_dir / name)
        fit.fit(module, train_dl, val_dl, ckpt_path=resume_path(work))
        metrics = finish_fit(fit, writer, work, history)
        if metrics is None:  # a DDP rank other than 0: rank 0 commits
            results[name] = {"rank": fit.global_rank}
            continue
        metrics = {k: round(v, 5) for k, v in metrics.items()}
        (writer.path / "metrics.json").write_text(json.dumps({"metrics": metrics, "split": ep_split}, indent=2))
        path = writer.commit({"policy": name, "seed": ctx.seed, **metrics})
        shutil.rmtree(work, ignore_errors=True)
        ctx.logger.log({f"bc/{name}/{k}": v for k, v in metrics.items()})
        results[name] = {"checkpoint": str(path), "seed": ctx.seed, **metrics}
    return results

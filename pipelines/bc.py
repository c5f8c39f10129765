"""stage=bc: behaviour cloning on a dataset version -> one checkpoint per policy.

``pddp`` (frozen pretrained encoder Φ from checkpoint/perception), ``pddp_noperc``
(raw points, encoder trained from scratch with the policy), ``pddp_graphconv``
(self-attention GraphConv encoder trained with the policy), and the baselines
``dp3`` and ``3dda`` (one knife pose per step, DDPM/DDIM), all on the same episodes.
"""
from __future__ import annotations

import dataclasses
import json
import shutil

import torch

from pipelines._common import as_dict
from topocut.utils.context import RunContext
from topocut.utils.training import MetricHistory, build_trainer, finish_fit, resume_path, split_episodes, work_dir

PDDP_ENCODERS = {"pddp": "pretrained", "pddp_noperc": "none", "pddp_graphconv": "graphconv"}
BASELINES = {"dp3": "dp3", "3dda": "3dda"}
POLICIES = (*PDDP_ENCODERS, *BASELINES)


def _loaders(dataset, split, batch_size: int, num_workers: int):
    train, val = split["train"], split["val"] + split["unseen"]
    make = torch.utils.data.DataLoader
    return (make(dataset(train), batch_size=batch_size, shuffle=True, num_workers=num_workers,
                 drop_last=len(train) > batch_size),
            make(dataset(val), batch_size=batch_size, num_workers=num_workers) if val else None)


def run(ctx: RunContext, policy, trainer, data, policies: list[str]) -> dict:
    from topocut.data.episodes import EpisodeDataset

    bad = [p for p in policies if p not in POLICIES]
    if bad:
        raise ValueError(f"stage.run.policies: unknown policy {bad[0]!r}; valid: {', '.join(POLICIES)}")
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
        if PDDP_ENCODERS.get(name) == "pretrained":
            enc_path = ctx.store.resolve("checkpoint", data.encoder, data.encoder_version)
            inputs["encoder"] = ctx.store.ref(enc_path)
            encoder_ckpt = str(enc_path / "model.ckpt")
        config = as_dict(("policy", policy), ("trainer", trainer), ("kind", name), ("seed", ctx.seed))
        writer, existing = ctx.store.begin("checkpoint", name, config, inputs, extra={"seed": ctx.seed})
        if existing is not None:
            results[name] = {"checkpoint": str(existing), "reused": True}
            continue
        if name in PDDP_ENCODERS:
            module, dataset = _pddp(policy, PDDP_ENCODERS[name], encoder_ckpt, steps, ctx.seed)
            max_epochs, clip = policy.train.max_epochs, policy.train.grad_clip
        else:
            module, dataset = _baseline(BASELINES[name], policy, steps, split["train"], ctx.seed)
            max_epochs, clip = policy.train.max_epochs, 1.0
        train_dl, val_dl = _loaders(dataset, split, policy.train.batch_size, policy.train.num_workers)
        work = work_dir(writer)
        history = MetricHistory(work / "history.json")
        fit = build_trainer(trainer, max_epochs, work, logger=ctx.logger.lightning(ctx.run_dir),
                            progress=ctx.progress, callbacks=[history],
                            gradient_clip_val=clip if name not in PDDP_ENCODERS else None)
        fit.fit(module, train_dl, val_dl, ckpt_path=resume_path(work))
        metrics = finish_fit(fit, writer, work, history)
        if metrics is None:  # a DDP rank other than 0: rank 0 commits
            results[name] = {"rank": fit.global_rank}
            continue
        metrics = {k: round(v, 5) for k, v in metrics.items()}
        (writer.path / "metrics.json").write_text(json.dumps({"metrics": metrics, "split": ep_split}, indent=2))
        path = writer.commit({"policy": name, **metrics})
        shutil.rmtree(work, ignore_errors=True)
        ctx.logger.log({f"bc/{name}/{k}": v for k, v in metrics.items()})
        results[name] = {"checkpoint": str(path), **metrics}
    return results


def _pddp(policy, encoder: str, encoder_ckpt, steps, seed: int):
    from topocut.policies.module import PDDPModule, PolicyDataset

    train_cfg = dataclasses.replace(policy.train, encoder=encoder, encoder_ckpt=encoder_ckpt, seed=seed)
    module = PDDPModule(policy.net, encoder, encoder_ckpt, train_cfg)

    def dataset(indices):
        return PolicyDataset(steps, train_cfg.num_points, train_cfg.num_goal_points, seed=seed, indices=indices)

    return module, dataset


def _baseline(kind: str, policy, steps, train_idx, seed: int):
    from topocut.policies.baselines.module import PoseDiffusionModule, PoseStepDataset, action_stats

    module = PoseDiffusionModule(kind=kind, num_points=policy.train.num_points,
                                 num_goal_points=policy.train.num_goal_points, lr=policy.train.lr)
    module.set_action_stats(action_stats([steps[i] for i in train_idx], module.hparams.pos_scale))
    full = PoseStepDataset(steps, policy.train.num_points, policy.train.num_goal_points,
                           pos_scale=module.hparams.pos_scale, seed=seed)

    def dataset(indices):
        return torch.utils.data.Subset(full, list(indices))

    return module, dataset

"""Small pieces every stage shares: the episode's object pose, config dicts for manifests, opening a sim artifact."""
from __future__ import annotations

import dataclasses

import numpy as np


def object_pose(obj, seed: int):
    """The object's pose for a run: randomised from the seed alone, or the nominal pose."""
    from topocut.sim.objects import ObjectPose, random_pose

    if not obj.randomize_pose:
        return ObjectPose()
    rng = np.random.default_rng(seed)
    return random_pose(rng, translation=obj.translation, yaw_deg=obj.yaw_deg,
                       scale=(obj.scale_min, obj.scale_max))


def as_dict(*named) -> dict:
    """{name: dataclass-as-dict} for manifests and artifact keys."""
    out = {}
    for name, obj in named:
        out[name] = dataclasses.asdict(obj) if dataclasses.is_dataclass(obj) else obj
    return out


def begin_sim(ctx, name: str, config: dict, sim):
    """Open the versioned ``sim`` artifact ``name`` and start Taichi on the run's device.

    Returns (writer, None, sim on ctx.device), or (None, the stage's result, None) when a finished
    artifact with this config already exists (it is reused, nothing is simulated).
    """
    from topocut.sim import init_taichi

    writer, existing = ctx.store.begin("sim", name, config, extra={"seed": ctx.seed, "device": ctx.device})
    if existing is not None:
        return None, {"artifact": str(existing), "reused": True}, None
    init_taichi(arch=ctx.device, seed=ctx.seed)
    return writer, None, dataclasses.replace(sim, arch=ctx.device)  # one backend for Taichi, Warp and torch

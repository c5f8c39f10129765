"""Small pieces every stage shares: the episode's object pose, config dicts for manifests."""
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

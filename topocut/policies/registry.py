"""The policy registry: every policy the benchmark knows, in one list.

Name -> ``PolicySpec``: its display name (Table 1), whether it is learned (trained by ``stage=bc``, loaded from a
checkpoint by ``stage=eval``), its family ("scripted", "pddp": score-entropy diffusion over cut masks, "pose":
DDPM over one knife pose), the perception encoder (PDDP) or network kind (pose baselines), and the observation
fields it reads.  Every learned policy reads the same ``topocut.policies.inputs.INPUT_FIELDS`` -- the goal cloud
*with its piece labels* included -- built by ``topocut.policies.inputs.policy_inputs``.

The stages ask this module instead of keeping their own lists: ``pipelines/bc.py`` (what it trains and how:
``training_setup``), ``pipelines/eval.py`` (what it builds and loads: ``load_learned``), the pose baselines'
module (``pose_kinds``); ``display_names()`` is Table 1's row labels.

Torch-free at import; the builders import their modules when called.
"""
from __future__ import annotations

from dataclasses import dataclass

from topocut.policies.inputs import INPUT_FIELDS

FAMILIES = ("scripted", "pddp", "pose")


@dataclass(frozen=True)
class PolicySpec:
    name: str
    display: str  # row label of the Table 1 report
    family: str  # scripted | pddp | pose
    inputs: tuple = ()  # observation fields the policy reads
    encoder: str | None = None  # PDDP: the perception encoder (topocut.policies.encoders.ENCODER_KINDS)
    kind: str | None = None  # pose baselines: the denoiser network (PoseDiffusionModule.kind)
    reference: bool = False  # a reference row (not selectable in eval.policies)

    @property
    def learned(self) -> bool:
        return self.family != "scripted"


_SPECS = (
    # scripted: built by stage=eval from the goal, the simulator or the planner config
    PolicySpec("oracle", "Oracle (goal planes)", "scripted", ("goal",)),
    PolicySpec("heuristic", "Heuristic", "scripted", ()),  # the nominal pose's planes, open loop
    PolicySpec("mppi", "MPPI (expert)", "scripted", ("goal", "sim_state", "particle_labels", "cuts_done")),
    # learned (stage=bc -> checkpoint/<name>), all on the same inputs
    PolicySpec("dp3", "DP3", "pose", INPUT_FIELDS, kind="dp3"),
    PolicySpec("3dda", "3D Diffuser Actor", "pose", INPUT_FIELDS, kind="3dda"),
    PolicySpec("pddp_noperc", "Ours w/o Perception", "pddp", INPUT_FIELDS, encoder="none"),
    PolicySpec("pddp_graphconv", "Ours (GraphConv)", "pddp", INPUT_FIELDS, encoder="graphconv"),
    PolicySpec("pddp", "PDDP (Ours)", "pddp", INPUT_FIELDS, encoder="pretrained"),
)
REFERENCES = (PolicySpec("teleop", "Human Tele-Op", "scripted", (), reference=True),)  # replayed teleop logs
POLICIES: dict[str, PolicySpec] = {s.name: s for s in _SPECS}


def get(name: str) -> PolicySpec:
    """The spec of a policy; a KeyError names the valid ones."""
    try:
        return POLICIES[name]
    except KeyError:
        raise KeyError(f"unknown policy {name!r}; valid: {', '.join(POLICIES)}") from None


def names() -> tuple:
    return tuple(POLICIES)


def learned() -> tuple:
    return tuple(n for n, s in POLICIES.items() if s.learned)


def scripted() -> tuple:
    return tuple(n for n, s in POLICIES.items() if not s.learned)


def pddp_encoders() -> dict:
    """{PDDP variant: its encoder kind}."""
    return {n: s.encoder for n, s in POLICIES.items() if s.family == "pddp"}


def pose_kinds() -> tuple:
    """The pose-diffusion baselines' network kinds (PoseDiffusionModule.kind)."""
    return tuple(s.kind for s in POLICIES.values() if s.family == "pose")


def display_names() -> dict:
    """{name: Table 1 row label} in the report's row order: scripted, the teleop reference, learned."""
    order = [s for s in _SPECS if not s.learned] + list(REFERENCES) + [s for s in _SPECS if s.learned]
    return {s.name: s.display for s in order}


def check(names_, key: str = "policies", allowed=None) -> None:
    """ValueError naming the first unknown policy of ``names_`` (``allowed``: the valid subset, default all)."""
    allowed = tuple(POLICIES) if allowed is None else tuple(allowed)
    bad = [n for n in names_ if n not in allowed]
    if bad:
        raise ValueError(f"{key}: unknown policy {bad[0]!r}; valid: {', '.join(allowed)}")


# -- builders of the learned policies ------------------------------------------------------------------------
def training_setup(name: str, policy, steps, train_indices, seed: int, encoder_ckpt: str | None = None):
    """(LightningModule, dataset(indices) -> torch Dataset, gradient_clip_val for the Trainer or None) that train
    the learned policy ``name`` with the ``policy`` config group (net, train) on dataset step dicts ``steps``.

    PDDP clips its gradients itself (``configure_gradient_clipping``); the pose baselines get the Trainer's 1.0.
    """
    import dataclasses

    spec = get(name)
    if spec.family == "pddp":
        from topocut.policies.module import PDDPModule, PolicyDataset

        train_cfg = dataclasses.replace(policy.train, encoder=spec.encoder, encoder_ckpt=encoder_ckpt, seed=seed)
        module = PDDPModule(policy.net, spec.encoder, encoder_ckpt, train_cfg)

        def pddp_dataset(indices):
            return PolicyDataset(steps, train_cfg.num_points, train_cfg.num_goal_points, seed=seed, indices=indices,
                                 mask_label=train_cfg.mask_label)

        return module, pddp_dataset, None
    if spec.family == "pose":
        import torch

        from topocut.policies.baselines.module import PoseDiffusionModule, PoseStepDataset, action_stats

        module = PoseDiffusionModule(kind=spec.kind, num_points=policy.train.num_points,
                                     num_goal_points=policy.train.num_goal_points, lr=policy.train.lr)
        module.set_action_stats(action_stats([steps[i] for i in train_indices], module.hparams.pos_scale))
        full = PoseStepDataset(steps, policy.train.num_points, policy.train.num_goal_points,
                               pos_scale=module.hparams.pos_scale, seed=seed)

        def pose_dataset(indices):
            return torch.utils.data.Subset(full, list(indices))

        return module, pose_dataset, 1.0
    raise ValueError(f"policy {name!r} is scripted: stage=bc trains {', '.join(learned())}")


def load_learned(name: str, path, device: str = "cpu", seed: int = 0, board_z: float = 0.05, sampler=None):
    """The Policy of a learned policy's checkpoint file ``path`` (``model.ckpt`` of checkpoint/<name>/vNNN).

    ``seed`` seeds the policy's sampler (the evaluation's, whatever seed trained the weights); ``sampler``: PDDP's
    SamplerConfig (default SamplerConfig())."""
    spec = get(name)
    if spec.family == "pddp":
        from topocut.policies.config import SamplerConfig
        from topocut.policies.module import PDDPPolicy

        return PDDPPolicy(str(path), sampler=sampler or SamplerConfig(), device=device, seed=seed, board_z=board_z)
    if spec.family == "pose":
        from topocut.policies.baselines.module import load_pose_policy

        return load_pose_policy(path, seed=seed, device=device)
    raise ValueError(f"policy {name!r} is scripted: it has no checkpoint")

"""The policy registry: every policy the benchmark knows, in one list.

Name -> ``PolicySpec``: its display name (Table 1), whether it is learned (trained by ``stage=bc``, loaded from a
checkpoint by ``stage=eval``), its family ("scripted", "pddp": score-entropy diffusion over cut masks, "pose":
DDPM over one knife pose), the perception encoder (PDDP) or network kind (pose baselines), and the observation
fields it reads.  Every learned policy reads the same ``topocut.policies.inputs.INPUT_FIELDS`` -- the goal cloud
*with its piece labels* included -- built by ``topocut.policies.inputs.policy_inputs``.

The stages ask this module instead of keeping their own lists: ``pipelines/bc.py`` (what it trains and how:
``training_setup``), ``topocut/eval/runner.py`` (what it builds and loads: ``build_scripted``, ``load_learned``), the pose baselines'
module (``pose_kinds``); ``display_names()`` is Table 1's row labels.

Torch-free at import; the builders import their modules when called.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from topocut.policies.inputs import INPUT_FIELDS
from topocut.utils.import_path import is_import_path

FAMILIES = ("scripted", "pddp", "pose")


@dataclass(frozen=True)
class PolicySpec:
    name: str
    display: str  # row label of the Table 1 report
    family: str  # scripted | pddp | pose
    inputs: tuple = ()  # observation fields the policy reads (a scripted policy's class says the same: ``observation_fields``)
    encoder: str | None = None  # PDDP: the perception encoder (topocut.policies.encoders.ENCODER_KINDS)
    kind: str | None = None  # pose baselines: the denoiser network (PoseDiffusionModule.kind)
    reference: bool = False  # a reference row (not selectable in eval.policies)
    builder: str | None = None  # scripted: "module:function" taking a ScriptedSetup (topocut.policies.scripted)

    @property
    def learned(self) -> bool:
        return self.family != "scripted"


_SCRIPTED = "topocut.policies.scripted"
_SPECS = (
    # scripted: built by stage=eval through their builder from the goal, the simulator or the planner config
    PolicySpec("oracle", "Oracle (goal planes)", "scripted", ("goal", "particles", "cuts_done"),
               builder=f"{_SCRIPTED}:oracle"),
    PolicySpec("heuristic", "Heuristic", "scripted", (), builder=f"{_SCRIPTED}:heuristic"),
    PolicySpec("mppi", "MPPI (expert)", "scripted", ("goal", "sim_state", "particle_labels", "cuts_done"),
               builder=f"{_SCRIPTED}:mppi"),
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


def check(names_, key: str = "policies", allowed=None, external: bool = False, kwargs: dict | None = None) -> None:
    """ValueError naming the first unknown policy of ``names_`` (``allowed``: the valid subset, default all).

    ``external``: ``module.path:ClassName`` entries are valid too, each checked by ``load_external`` with its
    constructor arguments ``kwargs[ClassName]`` (eval.policy_kwargs)."""
    allowed = tuple(POLICIES) if allowed is None else tuple(allowed)
    kwargs = dict(kwargs or {})
    for n in names_:
        if external and is_import_path(n):
            kwargs.pop(load_external(n, key, kwargs).cls.__name__, None)
        elif n not in allowed:
            own = " or 'module.path:ClassName' (your own policy class, docs/evaluation.md)" if external else ""
            raise ValueError(f"{key}: unknown policy {n!r}; valid: {', '.join(allowed)}{own}")
    if kwargs:
        names = [n.rpartition(":")[2].rpartition(".")[2] for n in names_ if is_import_path(n)]
        raise ValueError(f"eval.policy_kwargs.{next(iter(kwargs))}: no {key} entry 'module.path:"
                         f"{next(iter(kwargs))}'; its keys are the class names of those entries "
                         f"({', '.join(names) or 'none here'})")


# -- bring-your-own policies: ``module.path:ClassName`` entries of eval.policies ------------------------------
PROTOCOL = "reset(goal, seed=None) and act(obs) -> KnifeAction | None"  # topocut.policies.base.Policy


@dataclass(frozen=True)
class ExternalPolicy:
    """A policy class named by import path (``eval.policies=[oracle,mypkg.module:MyPolicy]``)."""

    entry: str  # "module.path:ClassName", as given: the report's policy key
    cls: type
    display: str  # row label: the class's ``display_name`` attribute, else its name

    @property
    def run(self) -> str:
        return run_dir(self.entry)

    def build(self, kwargs: dict | None = None):
        """An instance (constructed with ``kwargs``: eval.policy_kwargs.<ClassName>, default none) that the
        evaluation passes only the documented observation."""
        return _ProtocolPolicy(self.cls(**(kwargs or {}).get(self.cls.__name__, {})), self.entry)

    def fingerprint(self) -> str:
        """What keys the evaluation artifact for this entry: the entry and its module's source (changed code is a
        new evaluation, not a reused one)."""
        import hashlib
        import inspect

        try:
            src = Path(inspect.getsourcefile(self.cls) or "").read_bytes()
        except (OSError, TypeError):
            src = b""
        return f"policy/{self.entry}@{hashlib.sha256(src).hexdigest()[:12]}"


def run_dir(entry: str) -> str:
    """The episode folder (run) name of an eval.policies entry: filesystem-safe and one-to-one ('.' -> '-',
    ':' -> '+', neither of which a Python identifier holds); a registered name is its own."""
    return entry.replace(".", "-").replace(":", "+") if is_import_path(entry) else entry


def _valid(key: str) -> str:
    return (f"valid: a registered policy ({', '.join(POLICIES)}) or 'module.path:ClassName' naming a class "
            f"with {PROTOCOL} and a constructor that needs no arguments beyond eval.policy_kwargs.<ClassName>, its "
            "module importable (PYTHONPATH; docs/evaluation.md)")


def load_external(entry: str, key: str = "eval.policies", kwargs: dict | None = None) -> ExternalPolicy:
    """The class an import-path entry names, checked against the Policy protocol (the calls evaluate_episode
    makes) and its constructor against ``kwargs[ClassName]``; a ValueError names ``key``, the entry, what is wrong
    and what is valid."""
    import importlib
    import inspect

    module_name, _, attr = entry.partition(":")
    where = f"{key}: {entry!r}"
    if not module_name or not attr or ":" in attr:
        raise ValueError(f"{where} is not of the form 'module.path:ClassName'; {_valid(key)}")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as e:
        raise ValueError(f"{where}: cannot import module {module_name!r} ({e}); {_valid(key)}") from e
    except Exception as e:  # noqa: BLE001 - the user's module failed while importing
        raise ValueError(f"{where}: importing {module_name!r} raised {type(e).__name__}: {e}") from e
    obj = module
    for part in attr.split("."):
        obj = getattr(obj, part, None)
    if not inspect.isclass(obj):
        classes = sorted(n for n, c in vars(module).items()
                         if inspect.isclass(c) and c.__module__ == module.__name__ and not n.startswith("_")
                         and callable(getattr(c, "reset", None)) and callable(getattr(c, "act", None)))
        what = "no class" if obj is None else "no class (a non-class object)"
        raise ValueError(f"{where}: module {module_name!r} has {what} {attr!r}; its classes with reset and act: "
                         f"{', '.join(classes) or 'none'}; {_valid(key)}")
    problems = []
    for method, args in (("reset", ("goal",)), ("act", ("obs",))):
        fn = getattr(obj, method, None)
        if not callable(fn):
            problems.append(f"has no method {method}")
            continue
        try:  # the bound method of an instance: the class's function less self
            inspect.signature(fn).bind(*((None,) if _is_instance_method(obj, method) else ()), *args)
        except TypeError:
            problems.append(f"{method}{inspect.signature(fn)} cannot be called as {method}({', '.join(args)})")
        except ValueError:  # no signature (a builtin): trust it
            pass
    given = (kwargs or {}).get(obj.__name__, {})
    try:
        inspect.signature(obj).bind(**given)
    except TypeError as e:
        problems.append(f"its constructor {obj.__name__}{inspect.signature(obj)} "
                        + (f"does not take eval.policy_kwargs.{obj.__name__}={given} ({e})" if given else
                           f"needs arguments (eval.policy_kwargs.{obj.__name__} gives them)"))
    except ValueError:
        pass
    if problems:
        raise ValueError(f"{where}: class {obj.__name__} does not satisfy the Policy protocol: "
                         f"{'; '.join(problems)}; {_valid(key)}")
    return ExternalPolicy(entry, obj, str(getattr(obj, "display_name", None) or obj.__name__))


def _is_instance_method(cls, name: str) -> bool:
    import inspect

    raw = inspect.getattr_static(cls, name, None)
    return inspect.isfunction(raw)


def display_name(name: str) -> str:
    """A policy's row label: the registry's, an import-path entry's own (its class's ``display_name`` or name;
    the entry's class part where it cannot be imported here), else the name."""
    if name in POLICIES or any(s.name == name for s in REFERENCES):
        return display_names()[name]
    if is_import_path(name):
        try:
            return load_external(name).display
        except ValueError:
            return name.rpartition(":")[2].rpartition(".")[2] or name
    return name


class _ProtocolPolicy:
    """An external policy as the evaluation runs it: ``reset`` passes the seed where the class takes one, ``act``
    sees the documented observation (``topocut.policies.base.OBS_KEYS``) only and must return a KnifeAction or
    None (anything else fails the episode with a TypeError, not the evaluation)."""

    def __init__(self, policy, entry: str):
        self.policy, self.entry = policy, entry

    def reset(self, goal, seed: int | None = None) -> None:
        from topocut.policies.base import reset_policy

        reset_policy(self.policy, goal, seed=seed)

    def act(self, obs: dict):
        from topocut.policies.base import OBS_KEYS
        from topocut.sim.action import KnifeAction

        action = self.policy.act({k: obs[k] for k in OBS_KEYS})
        if action is not None and not isinstance(action, KnifeAction):
            raise TypeError(f"{self.entry}: act returned {type(action).__name__}; the Policy protocol returns a "
                            "topocut.sim.action.KnifeAction (or None to stop)")
        return action


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
        module.set_demo_tilt([steps[i] for i in train_indices])  # vertical demonstrations: vertical planes

        def pddp_dataset(indices):
            return PolicyDataset(steps, train_cfg.num_points, train_cfg.num_goal_points, seed=seed, indices=indices,
                                 mask_label=train_cfg.mask_label, sample=train_cfg.sample)

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


def build_scripted(name: str, setup):
    """The Policy of a scripted policy, from its spec's builder and ``setup`` (topocut.policies.scripted.ScriptedSetup)."""
    import importlib

    spec = get(name)
    if spec.learned or spec.builder is None:
        raise ValueError(f"policy {name!r} is learned: load it from its checkpoint (load_learned)")
    module, _, func = spec.builder.partition(":")
    return getattr(importlib.import_module(module), func)(setup)


def load_learned(name: str, path, device: str = "cpu", seed: int = 0, board_z: float = 0.05, sampler=None):
    """The Policy of a learned policy's checkpoint file ``path`` (``model.ckpt`` of checkpoint/<name>/vNNN).

    ``seed`` seeds the policy's sampler (the evaluation's, whatever seed trained the weights); ``sampler``: PDDP's
    SamplerConfig (default SamplerConfig())."""
    spec = get(name)
    if spec.family == "pddp":
        from topocut.policies.config import SamplerConfig
        from topocut.policies.deploy import PDDPPolicy

        return PDDPPolicy(str(path), sampler=sampler or SamplerConfig(), device=device, seed=seed, board_z=board_z)
    if spec.family == "pose":
        from topocut.policies.baselines.module import load_pose_policy

        return load_pose_policy(path, seed=seed, device=device)
    raise ValueError(f"policy {name!r} is scripted: it has no checkpoint")

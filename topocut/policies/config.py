"""Configs of the PDDP policy (network + discrete diffusion) and of its training.

Plain-typed dataclasses so Hydra can register them as structured-config schemas.
Sizes follow the paper's appendix "Policy Model Architecture - PDDP".
"""
from __future__ import annotations

from dataclasses import dataclass

from topocut.utils.checks import check_choice

GRAPHS = ("uniform", "absorbing")
NOISES = ("loglinear", "geometric")
GOAL_MODES = ("pool", "cross")
GOAL_INPUTS = ("phi", "xyz")
MASK_LABELS = ("goal_side", "plane_side")
SAMPLES = ("loader", "batch")  # where PDDP's observation FPS runs (PolicyTrainConfig.sample)
SCORE_PARAMS = ("denoiser", "direct")
ENCODERS = ("none", "pretrained", "graphconv")
LOSSES = ("dse", "sq")
PREDICTORS = ("analytic", "euler")
PLANE_METHODS = ("svm", "lsq")
PLANE_TILTS = ("auto", "free", "zero")
# a training set's cuts are vertical when none tilts more than this (rad): MPPI with tilt frozen and the oracle's
# slice, stick and dice planes have tilt exactly 0
VERTICAL_TILT = 1e-6


@dataclass
class PDDPConfig:
    # -- discrete diffusion -------------------------------------------------
    graph: str = "uniform"  # "uniform" on 2 states is the paper's bit-flip noise; "absorbing" adds a mask state
    noise: str = "loglinear"  # schedule sigma(t), t in [0, 1]
    noise_eps: float = 1e-3  # loglinear: e^{-sigma(1)} = eps
    sigma_min: float = 1e-4  # geometric
    sigma_max: float = 20.0  # geometric
    num_classes: int = 2  # mask labels (1 = the reference side of the cut plane, topocut.policies.actions)
    score_param: str = "denoiser"  # "denoiser": per-point class logits -> exact log-scores; "direct": SEDD log-scores
    scale_by_sigma: bool = True  # "direct" only: offset log-scores by their sigma-dependent baseline (SEDD trick)
    # -- network ------------------------------------------------------------
    obs_dim: int = 96  # per-point embedding z_t from the encoder
    hidden: int = 96  # DDiT width
    n_blocks: int = 12
    n_heads: int = 4
    mlp_ratio: int = 4  # 96 -> 384 -> 96
    dropout: float = 0.4
    cond_dim: int = 128  # adaLN conditioning width
    time_freq_dim: int = 256  # sinusoidal sigma features
    history_len: int = 3
    pose_dim: int = 7
    goal_hidden: int = 64  # goal encoder obs_dim -> 64 -> hidden over z_g = Φ(X_g, F_g)
    goal_mode: str = "pool"  # "pool": max+mean pooled goal vector joins the conditioning; "cross": cross-attention
    # "phi": the goal cloud and its piece labels through the observation's encoder Φ (z_g = Φ(X_g, F_g), the
    # task's goal); "xyz": the goal's positions only (task-blind: checkpoints saved before goal_input existed)
    goal_input: str = "phi"
    center_points: bool = False  # subtract the observation centroid from observation and goal points

    def validate(self) -> PDDPConfig:
        check_choice("policy.graph", self.graph, GRAPHS)
        check_choice("policy.noise", self.noise, NOISES)
        check_choice("policy.goal_mode", self.goal_mode, GOAL_MODES)
        check_choice("policy.goal_input", self.goal_input, GOAL_INPUTS)
        check_choice("policy.score_param", self.score_param, SCORE_PARAMS)
        if self.hidden % self.n_heads:
            raise ValueError(f"policy.hidden={self.hidden} must be divisible by policy.n_heads={self.n_heads}")
        if self.num_classes < 2:
            raise ValueError(f"policy.num_classes={self.num_classes} must be >= 2")
        return self


@dataclass
class PolicyTrainConfig:
    encoder: str = "pretrained"  # none | pretrained | graphconv (the paper's three perception configurations)
    encoder_ckpt: str | None = None  # pretrain checkpoint for encoder="pretrained"
    num_points: int = 256  # observation points per sample (FPS)
    num_goal_points: int = 256
    # the mask the policy learns: "goal_side" the pose-consistent label (1 = the side of the goal frame's reference
    # direction, topocut.policies.actions); "plane_side" the dataset's stored mask (1 = the canonical plane's +n side)
    mask_label: str = "goal_side"
    loss: str = "dse"  # "dse" (denoising score entropy) | "sq" (squared-error ablation)
    lr: float = 3e-4
    weight_decay: float = 0.0
    warmup_steps: int = 500
    grad_clip: float = 1.0
    ema_decay: float = 0.999
    batch_size: int = 64
    max_epochs: int = 100
    val_fraction: float = 0.1
    val_sample_steps: int = 16  # sampler steps for val/mask_acc
    # val/mask_acc every k-th epoch and the last (val/loss and the floors every epoch): its sampler runs
    # val_sample_steps forward passes a batch, ~5 training steps' time, ~40% of a PDDP epoch when run every
    # epoch (docs/benchmarks.md). How often it is measured, not what is trained: kept out of the artifact key
    val_sample_every: int = 5
    num_workers: int = 0
    # where PDDP's observation FPS runs: "loader" an item at a time in the DataLoader (host numpy, ~5 ms an item
    # of 2,048 points), "batch" the whole batch at once on the training device (PDDPModule.on_after_batch_transfer).
    # The same picks from the same seeds (float64 both ways), so the same training: kept out of the artifact key
    sample: str = "batch"
    seed: int = 0

    def validate(self) -> PolicyTrainConfig:
        check_choice("policy_train.encoder", self.encoder, ENCODERS)
        check_choice("policy_train.loss", self.loss, LOSSES)
        check_choice("policy_train.mask_label", self.mask_label, MASK_LABELS)
        check_choice("policy_train.sample", self.sample, SAMPLES)
        if self.encoder == "pretrained" and not self.encoder_ckpt:
            raise ValueError("policy_train.encoder='pretrained' needs policy_train.encoder_ckpt (a pretrain checkpoint)")
        return self


@dataclass
class SamplerConfig:
    predictor: str = "analytic"  # analytic (Tweedie tau-leaping) | euler
    steps: int = 32
    denoise: bool = True  # final Tweedie step from sigma(eps) to 0
    eps: float = 1e-5  # smallest sampling time
    plane: str = "svm"  # svm | lsq (action reconstruction)
    # the plane's tilt: "zero" fits vertical planes only, "free" any plane; "auto" vertical when every cut the policy
    # was trained on was vertical (its checkpoint records the largest |tilt|), else free (docs/policy.md)
    tilt: str = "auto"
    retries: int = 3  # resample when a mask has one class only

    def validate(self) -> SamplerConfig:
        check_choice("sampler.predictor", self.predictor, PREDICTORS)
        check_choice("sampler.plane", self.plane, PLANE_METHODS)
        check_choice("sampler.tilt", self.tilt, PLANE_TILTS)
        if self.steps < 1:
            raise ValueError(f"sampler.steps={self.steps} must be >= 1")
        return self

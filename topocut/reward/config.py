"""Spectral reward configuration (docs/reward.md explains every choice)."""
from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class RewardConfig:
    # graph / spectrum (paper appendix: num_point = 512, k = 30)
    num_point: int = 512  # FPS resampling size of every fragment
    knn: int = 30  # neighbours per node of the kNN graph
    num_eig: int = 20  # non-trivial eigenpairs kept (the constant mode is dropped)
    # Gaussian width in scene units; None: sigma_scale x the mean kNN distance of the *goal* pieces
    # (the reference sets the resolution; fragments are graphed with the same sigma, so size is not normalised away)
    sigma: float | None = None
    sigma_scale: float = 1.0
    eig_floor: float = 1e-4  # added before log(eigenvalue) (disconnected graphs have zero eigenvalues)
    # eigenvector term: quantiles of the normalised heat kernel signature at t = c / lambda_K
    hks_times: list[float] = field(default_factory=lambda: [2.0, 4.0, 8.0])
    num_quantiles: int = 16
    alpha: float = 1.0  # weight of the eigenvalue term  mean_k (l_x,k - l_y,k)^2 (mean-centred log eigenvalues)
    beta: float = 1.0  # weight of the eigenvector (HKS distribution) term
    # size terms (topocut.reward.size): a * sum_k (dlog e_k)^2 + b * (dlog fill)^2 over the sorted principal
    # extents and the fill V / (e1 e2 e3); a slab r times the goal's thickness is at a log(r)^2 (docs/reward.md#sweep)
    size_weight: float = 3.0
    fill_weight: float = 3.0
    profile_weight: float = 3.0  # the thickness profile along the thinnest axis (quantiles over 2s columns)
    # an extent or profile thickness within this many particle spacings of the goal piece's costs nothing (only the
    # excess counts): below one lattice layer a cut's pieces are the simulator's kerf and jitter, not the policy's
    # choice (docs/reward.md#resolution).  0: every difference counts
    size_tolerance: float = 0.0
    # pen tasks only (cream writing: topocut.tasks.writing_scene.letter_distances): the stroke's handedness on the
    # board, max(0, misfit to its letter - misfit to the letter's mirror image) in letter radii
    # (topocut.reward.planar), times this, is added to its distance; a mirrored R is at ~0.05 (docs/reward.md#handedness)
    handedness_weight: float = 5.0
    min_points: int = 32  # fragments with fewer points get distance inf (reward 0)
    # a piece is described without the strays the blade dragged out of it (threads of particles one link from its
    # core and farther, topocut.reward.strays), unless that leaves out more than this share of it; 0: every
    # particle (docs/reward.md#strays)
    stray_share: float = 0.05
    # piecewise-linear reward R(d) (paper appendix): R_max - gamma d for d <= tau, then slope delta > gamma; clipped at 0
    r_max: float = 1.0
    gamma: float = 1.0
    tau: float = 0.01
    # delta = 4 puts R = 0 at d = 0.2575: a slab 1.34x (or 0.75x) the goal's thickness (d_size = 3 log(r)^2);
    # the size terms, not delta, now make wrong thicknesses earn nothing (docs/reward.md#calibration)
    delta: float = 4.0
    kappa: float | None = None  # total = kappa * sum of fragment values; None: 1 / (number of goal pieces)
    # every fragment is accounted for (docs/reward.md#several-fragments): a fragment assigned to a goal piece is
    # worth R(d) - mismatch_cost (r_max - R(d)) w, one fragment may be the uncut stock (0), every other one is
    # waste, - waste_cost r_max w, with w = min(1, its volume / the mean goal piece's)
    mismatch_cost: float = 1.0
    waste_cost: float = 1.0
    # waste up to the goal's planned offcuts (Goal.offcuts, in goal-piece weights) + offcut_slack goal pieces is
    # forgiven: the physics breaks a rim in two or leaves a sliver heavier than planned (docs/reward.md#planned-offcuts)
    offcut_slack: float = 0.25
    clip_total: bool = True  # total clipped to [0, r_max] (RewardResult.unclipped keeps the sum)
    # a piece assigned to a goal piece counts as a correct cut (N_C) if d <= this, i.e. R(d) >= 0.77 with the
    # defaults: a slab within ~0.86-1.16x the goal thickness (docs/reward.md#sweep); None: tau
    success_distance: float | None = 0.065
    backend: str = "scipy"  # "scipy" (sparse shift-invert eigsh, CPU) or "torch" (batched dense eigh)
    device: str = "cpu"  # torch backend only
    # torch backend: how the Laplacians' smallest eigenpairs are found.  "subspace": the num_eig + 1 smallest by
    # batched shift-invert subspace iteration where the Laplacians were built (topocut.reward.eigen; every matrix
    # at once); "device": torch.linalg.eigh of the whole spectrum there (the reference: cuSOLVER runs a batch one
    # matrix after another, 4.7 ms each on an H100); "host": LAPACK's subset solver (evx; 14 ms a matrix on the
    # H100's host, 10 ms on this 2-core CPU; threads do not help, scipy holds the GIL); "auto": subspace on
    # CUDA, host on the CPU.  Figures: docs/benchmarks.md#spectral-reward
    eig_solver: str = "auto"
    # torch backend: where the fragments' size descriptors (spacing, extents, body, thickness profile) are measured.
    # "host": one fragment at a time in host threads (numpy and KD-trees; the reference); "device": every fragment
    # at once where the reward runs (topocut.reward.size_batch: the same numbers up to rounding); "auto": device on
    # CUDA, host on the CPU.  The scipy backend always measures on the host.  Figures: docs/benchmarks.md
    size_solver: str = "auto"

    def on(self, device: str) -> RewardConfig:
        """This config with the torch backend on ``device`` (the run's resolved device: the reward runs where the
        simulator does); the scipy backend is host-only and unchanged."""
        import dataclasses

        return dataclasses.replace(self, device=device) if self.backend == "torch" else self

    def validate(self) -> RewardConfig:
        if self.delta <= self.gamma:
            raise ValueError(f"reward.delta={self.delta} must exceed reward.gamma={self.gamma} (paper: delta > gamma)")
        if self.backend not in ("scipy", "torch"):
            raise ValueError(f"reward.backend={self.backend!r}; valid: scipy, torch")
        if self.eig_solver not in ("auto", "host", "device", "subspace"):
            raise ValueError(f"reward.eig_solver={self.eig_solver!r}; valid: auto, host, device, subspace")
        if self.size_solver not in ("auto", "host", "device"):
            raise ValueError(f"reward.size_solver={self.size_solver!r}; valid: auto, host, device")
        for k in ("num_point", "knn", "num_eig", "num_quantiles", "min_points"):
            if getattr(self, k) < 1:
                raise ValueError(f"reward.{k}={getattr(self, k)} must be >= 1")
        if self.min_points < self.num_eig + 2:
            raise ValueError(f"reward.min_points={self.min_points} must be >= reward.num_eig + 2 = {self.num_eig + 2}")
        for k in ("size_weight", "fill_weight", "profile_weight", "size_tolerance", "handedness_weight", "mismatch_cost",
                  "waste_cost", "offcut_slack", "stray_share"):
            if getattr(self, k) < 0:
                raise ValueError(f"reward.{k}={getattr(self, k)} must be >= 0")
        if self.sigma is not None and self.sigma <= 0:
            raise ValueError(f"reward.sigma={self.sigma} must be > 0 or None")
        return self

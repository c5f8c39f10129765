"""Simulator settings (Hydra group ``sim``); units and defaults are explained in docs/sim.md."""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from dataclasses import fields as dataclass_fields

PUSH_MODES = ("separate", "press", "settle", "none")
KNIFE_MODES = ("wedge", "sticky")
ARCHS = ("cpu", "cuda")
ROTATIONS = ("auto", "polar", "svd")
SWITCHES = ("auto", "on", "off")
LAYOUTS = ("auto", "aos", "soa")


def _one_of(key: str, value, valid: tuple) -> None:
    """A ValueError ``<key>: <value!r>; valid: a, b, c`` unless ``value`` is one of ``valid``."""
    if value not in valid:
        raise ValueError(f"{key}: {value!r}; valid: {', '.join(valid)}")


@dataclass
class TuningConfig:
    """GPU/performance switches (Hydra group ``sim/tuning``, keys ``sim.tuning.*``; docs/sim.md, "GPU tuning
    switches").  They choose how the substeps are launched, laid out and summed, not the physics: results
    change by float summation order or rounding at most (the SVD against the polar iteration), as
    tests/test_sim_{fused,grid_box,warp_scatter,resort,grid_layout,block_dim}.py check.  ``auto`` resolves
    from the backend (``sim.arch``) and the batch, which the methods below take as arguments."""

    fuse_substeps: int = 16  # substeps per Python call in simulate() (a kernel graph); 1 = a call per phase
    check_every: int = 200  # substeps between divergence checks (a host sync)
    core_rotation: str = "auto"  # healthy core's R: polar (Newton) | svd | auto = polar on cpu, svd on cuda
    grid_box: str = "auto"  # clear/update only the nodes the scatter wrote: on | off | auto (off for B=1 on cuda)
    warp_scatter: str = "auto"  # p2g sums a warp's same-cell stencils by shuffles: on (cuda only) | off | auto = on on cuda
    resort_every: int = -1  # substeps between re-sorts of the scatter's visiting order by cell; 0 never, -1 auto
    grid_layout: str = "auto"  # grid nodes: aos (one struct each) | soa (an array per component) | auto = soa on cuda
    scatter_block_dim: int = 0  # CUDA threads per block of the scatter (caps its registers); 0 = auto
    gather_block_dim: int = 0  # likewise for the gather (g2p); 0 = auto
    device_split: str = "auto"  # a cut's pieces and fields by kernels (pieces_, fields_device.py): on | off | auto = cuda

    def core_rotation_method(self, arch: str) -> str:
        """'svd' on a GPU: skin and core particles share warps, which would otherwise run both the SVD
        (skin, damaged) and the polar iteration (healthy core); on a CPU the cheaper polar iteration wins."""
        if self.core_rotation != "auto":
            return self.core_rotation
        return "svd" if arch == "cuda" else "polar"

    def grid_box_enabled(self, arch: str, batch_size: int) -> bool:
        """The object fills a few percent of the n^3 grid: on a CPU the whole-grid clear and update cost up to a
        third of a substep (48^3, 4 scenes), on an H100 135 of 752 us (84^3, 16 scenes).  When this was
        measured the box's bounds were read before its loops by 3 small serial tasks (~20 us of one scene's 60-90 us
        on an H100), so auto leaves it off for a single scene on a GPU (docs/benchmarks.md); on CUDA the loops now
        read the bounds themselves (MPMSolver.box_threads), and a single scene was not timed again."""
        if self.grid_box != "auto":
            return self.grid_box == "on"
        return arch != "cuda" or batch_size > 1

    def warp_scatter_enabled(self, arch: str) -> bool:
        """The scatter is bound by its global atomics on a GPU (4 per stencil node); lanes of a warp whose
        particles share a base cell add their stencils with shuffles first, so one lane per run issues them
        (docs/sim.md).  Warp shuffles exist only on CUDA."""
        if self.warp_scatter != "auto":
            return self.warp_scatter == "on"
        return arch == "cuda"

    def grid_layout_method(self, arch: str) -> str:
        """'soa' on a GPU, where a warp's scatter atomics land on neighbouring nodes (in one array per component
        they share memory sectors, as we read the timings: a batched substep 10-15% faster on an H100); 'aos' on
        a CPU, where a thread adds a node's four values one after another (arrays 13-17% slower there)."""
        if self.grid_layout != "auto":
            return self.grid_layout
        return "soa" if arch == "cuda" else "aos"

    def block_dims(self, arch: str, batch_size: int) -> tuple[int | None, int | None]:
        """CUDA threads per block of the scatter and of the gather (None on the CPU: Taichi's own chunking).

        Taichi marks every GPU task with launch bounds (maxntid = block_dim, minctasm = 2), so ptxas keeps a
        task's registers at or below 65536 / (2 block_dim): 128 threads leave it uncapped (the scatter takes
        91, the gather 155), 256 cap it at 128, 384 at 85, 512 at 64.  Fewer registers let more warps stay on
        an SM (what a batch needs: its scatter is latency-bound at 28% occupancy), at the risk of spills.
        auto: a batch's scatter takes 512 (H100, 16 scenes: 128 -> 384 took 84^3 190-196 -> 181-187 us per substep,
        128^3 518.2 -> 472.2; H200: 384 -> 512 took 128^3 467-480 -> 443-448 us, 64^3 143.2 -> 139.9; 640 and 768
        slower); a single scene, one partial wave of blocks, keeps 128, and so do the plain
        scatter (not timed above 128) and the gather (384: slower; 64 and 256: no faster).  Results change only by the GPU's float atomics
        order (docs/benchmarks.md)."""
        if arch != "cuda":
            return None, None
        batch_warp = batch_size > 1 and self.warp_scatter_enabled(arch)
        return self.scatter_block_dim or (512 if batch_warp else 128), self.gather_block_dim or 128

    def resort_interval(self, arch: str) -> int:
        """Substeps between re-sorts of the scatter's particle order by base cell (0: never).  Only the warp
        scatter gains from it (longer same-cell runs, fewer atomics), so auto sorts every 64 substeps with it
        and never without it (a counting sort queued on the device, no host sync; docs/benchmarks.md)."""
        if self.resort_every >= 0:
            return self.resort_every
        return 64 if self.warp_scatter_enabled(arch) else 0

    def device_split_enabled(self, arch: str) -> bool:
        """Find a cut's pieces and their velocity fields in Taichi kernels (pieces_device.py, fields_device.py: the
        same labels and fields as the host's pieces.split and pieces.colour) rather than with scipy on the host,
        where they were 40% of a cut's simulation time at 128^3 on a GPU.  auto: on with cuda (one H200 at 128^3
        spacing: 21.8x for one scene, 23.6x for 16; benchmarks/split_device.py), off on a CPU.  There the kernels
        win too since the fields moved (2 cores, 128^3 spacing: 3.1x for one scene, 2.1x for 16), but they compile
        for ~6 s in a process without a warm kernel cache, and a smoke run's few small cuts save less than that."""
        if self.device_split != "auto":
            return self.device_split == "on"
        return arch == "cuda"

    def validate(self, arch: str, batch_size: int, n_grid: int, n_fields: int) -> TuningConfig:
        """Checks of the switches against the sim they tune; a ValueError naming ``sim.tuning.<key>``."""
        def bad(key, msg):
            raise ValueError(f"sim.tuning.{key}: {msg}")

        if not 1 <= self.fuse_substeps <= 256:
            bad("fuse_substeps", f"{self.fuse_substeps} must lie in [1, 256]")
        if self.check_every < 1:
            bad("check_every", f"{self.check_every} must be >= 1 (substeps between divergence checks)")
        _one_of("sim.tuning.core_rotation", self.core_rotation, ROTATIONS)
        _one_of("sim.tuning.grid_box", self.grid_box, SWITCHES)
        _one_of("sim.tuning.warp_scatter", self.warp_scatter, SWITCHES)
        if self.warp_scatter == "on" and arch != "cuda":
            bad("warp_scatter", f"on needs sim.arch=cuda (warp shuffles), got sim.arch={arch!r}; use auto or off")
        if self.warp_scatter_enabled(arch) and batch_size * n_fields * n_grid ** 3 >= 2 ** 31:
            bad("warp_scatter", f"run keys (scene, cell) overflow 32 bits at batch_size={batch_size}, "
                                f"n_grid={n_grid}; use fewer scenes or sim.tuning.warp_scatter=off")
        if arch == "cuda" and self.grid_box_enabled(arch, batch_size) and batch_size * n_fields * n_grid ** 3 >= 2 ** 31:
            bad("grid_box", f"the box loops' node indices (MPMSolver.box_threads) overflow 32 bits at "
                            f"batch_size={batch_size}, n_grid={n_grid}; use fewer scenes")
        _one_of("sim.tuning.device_split", self.device_split, SWITCHES)
        _one_of("sim.tuning.grid_layout", self.grid_layout, LAYOUTS)
        for key in ("scatter_block_dim", "gather_block_dim"):
            bd = getattr(self, key)
            if bd and not (32 <= bd <= 1024 and bd % 32 == 0):
                bad(key, f"{bd}; valid: 0 (auto) or a multiple of 32 in [32, 1024] (CUDA threads per block)")
        if self.resort_every < -1:
            bad("resort_every", f"{self.resort_every}; valid: -1 (auto), 0 (never) or a number of substeps")
        if self.resort_interval(arch) and batch_size * n_grid ** 3 >= 2 ** 31:
            bad("resort_every", f"cell indices overflow 32 bits at batch_size={batch_size}, n_grid={n_grid}; "
                                f"use fewer scenes or sim.tuning.resort_every=0")
        return self


@dataclass
class SimConfig:
    # -- discretisation --------------------------------------------------------
    n_grid: int = 64  # grid nodes per axis over the unit cube (128 on GPU)
    dt: float | None = None  # substep length [s]; None = cfl * CFL bound (see cfl_bound)
    cfl: float = 0.5  # fraction of the CFL bound used when dt is None
    particle_spacing: float | None = None  # lattice spacing; None = half a grid cell
    batch_size: int = 1  # B independent scenes simulated together
    arch: str = "cpu"
    tuning: TuningConfig = field(default_factory=TuningConfig)  # GPU/performance switches (sim.tuning)
    # -- materials (0: plasto-elastic core, 1: von Mises skin) -------------------
    mu: float = 2083.33
    lam: float = 1388.89
    rho_core: float = 4.0
    rho_skin: float = 1.0
    skin_thickness: float = 0.01
    eps_c: float = 0.025  # critical compression: damaged when J <= (1 - eps_c)^m
    eps_s: float = 0.01  # critical stretch: damaged when J >= (1 + eps_s)^m
    m: float = 1.0  # damage sensitivity exponent
    damaged_stiffness: float = 0.01  # mu and lambda scale of a damaged particle (irreversible)
    yield_stress: float = 60.0  # initial von Mises yield stress of the skin
    softening: float = 120.0  # gamma: sigma_y -= gamma * |d eps_p|; damaged at sigma_y <= 0
    j_min: float = 0.05  # runaway-J bounds: outside them the step raises SimulationDiverged
    j_max: float = 20.0
    # -- scene -------------------------------------------------------------------
    gravity: float = 9.8  # along -z; 0 disables
    board: bool = True  # cutting board at z = board_z (friction boundary)
    board_z: float = 0.05
    friction: float = 0.5  # Coulomb coefficient of the board
    walls: bool = True  # domain walls (3 cells thick)
    # -- knife -------------------------------------------------------------------
    knife_half_length: float = 0.3  # along the blade axis u
    knife_height: float = 0.45  # blade height (along -w, above its cutting edge)
    knife_half_thickness: float = 0.002  # along the blade normal n
    knife_margin: float | None = None  # contact inflation of the blade SDF; None = half a grid cell
    kerf_half_width: float | None = None  # the blade damages particles this close to its plane [units]; None = kerf
    knife_mode: str = "wedge"  # wedge: splits material sideways; sticky: nodes inside take the knife velocity
    knife_wedge: float = 0.15  # wedge: sideways opening speed / knife speed (half-angle tangent of the bevel)
    knife_friction: float = 0.2  # Coulomb coefficient on the blade faces
    knife_speed: float = 2.5  # travel speed along w [units/s]
    knife_clearance: float = 0.01  # start height of the edge above the object's top
    osc_amplitude: float = 0.002  # blade oscillation along u [units]
    osc_frequency: float = 60.0  # [Hz]
    cut_substeps: int | None = None  # fixes the substeps of the travel (the speed follows); None = from speed
    dwell_time: float = 0.005  # [s] knife resting on the board before the push / withdrawal
    # -- separation: one velocity field per piece colour (docs/sim.md, "Pieces and contact") ----------
    fields: int = 8  # velocity fields per grid node: touching pieces take different ones (1 = single-field MPM)
    contact_friction: float = 0.3  # Coulomb coefficient between pieces (multi-field contact)
    # -- push (after a cut) --------------------------------------------------------
    push_mode: str = "separate"  # separate | press | settle | none (docs/sim.md)
    push_distance: float = 0.02  # 'separate': the knife slides the piece just cut off this far [units]
    push_time: float = 0.08  # [s] the slide (or the press's hold); a smooth start and stop
    settle_time: float = 0.02  # [s] free settling afterwards
    # [s] free settling after a turn: a laid slab, set down half a cell above the board, comes to rest before it is
    # cut (cut 20 ms after being laid, a donut stick plan's second stick came out 52 mm wide against 43, d 0.107)
    turn_settle_time: float = 0.1
    press_depth: float = 0.006  # 'press': how far a flat plate goes below the object's top
    press_speed: float = 0.3

    def __post_init__(self):
        if isinstance(self.tuning, Mapping):  # SimConfig(tuning={"warp_scatter": "off"}), or a plain DictConfig
            valid = [f.name for f in dataclass_fields(TuningConfig)]
            for key in self.tuning:
                if key not in valid:
                    raise ValueError(f"sim.tuning.{key}: unknown key; valid keys of sim.tuning: {', '.join(valid)}")
            self.tuning = TuningConfig(**self.tuning)

    # -- derived -------------------------------------------------------------------
    @property
    def dx(self) -> float:
        return 1.0 / self.n_grid

    @property
    def spacing(self) -> float:
        return self.particle_spacing if self.particle_spacing is not None else 0.5 * self.dx

    @property
    def margin(self) -> float:
        return self.knife_margin if self.knife_margin is not None else 0.5 * self.dx

    @property
    def kerf(self) -> float:
        """Half-width of the band a cut damages: the blade's own half-thickness, or half a particle spacing where
        that is wider (a particle the plane passes through is cut; docs/sim.md, "Contact").  Not the contact
        inflation ``margin``: that is numerical, and at 3 cm pieces it turned 40% of every slab to mush."""
        if self.kerf_half_width is not None:
            return self.kerf_half_width
        return max(self.knife_half_thickness, 0.5 * self.spacing)

    def wave_speed(self) -> float:
        """Fastest elastic (P-)wave speed sqrt((lam + 2 mu) / rho) over both materials."""
        return math.sqrt((self.lam + 2 * self.mu) / min(self.rho_core, self.rho_skin))

    def max_knife_speed(self) -> float:
        return self.knife_speed + 2 * math.pi * self.osc_frequency * self.osc_amplitude

    def cfl_bound(self) -> float:
        """Largest stable substep: dx / (wave speed + knife speed)."""
        return self.dx / (self.wave_speed() + self.max_knife_speed())

    def substeps(self, seconds: float) -> int:
        """Substeps that cover ``seconds`` of simulated time (durations are in seconds so that a push or a
        dwell lasts as long at every grid; the substep count follows dt)."""
        return int(math.ceil(seconds / self.effective_dt() - 1e-9))

    def effective_dt(self) -> float:
        return self.dt if self.dt is not None else self.cfl * self.cfl_bound()

    def validate(self) -> SimConfig:
        def bad(key, msg):
            raise ValueError(f"sim.{key}: {msg}")

        if self.n_grid < 16:
            bad("n_grid", f"{self.n_grid} is too coarse; use >= 16 (the scales use 48: smoke, 128: paper)")
        _one_of("sim.arch", self.arch, ARCHS)
        _one_of("sim.knife_mode", self.knife_mode, KNIFE_MODES)
        _one_of("sim.push_mode", self.push_mode, PUSH_MODES)
        self.tuning.validate(self.arch, self.batch_size, self.n_grid, self.fields)
        if self.batch_size < 1:
            bad("batch_size", f"{self.batch_size} must be >= 1")
        if not 0 < self.cfl <= 1:
            bad("cfl", f"{self.cfl} must lie in (0, 1]")
        if self.spacing <= 0 or self.spacing > self.dx:
            bad("particle_spacing", f"{self.spacing} must lie in (0, dx={self.dx:.4g}] (2 per cell is usual)")
        for key in ("mu", "lam", "rho_core", "rho_skin", "knife_speed", "knife_half_thickness"):
            if getattr(self, key) <= 0:
                bad(key, f"{getattr(self, key)} must be > 0")
        if not 0 < self.damaged_stiffness <= 1:
            bad("damaged_stiffness", f"{self.damaged_stiffness} must lie in (0, 1]")
        if not (0 < self.eps_c < 1 and self.eps_s > 0 and self.m > 0):
            bad("eps_c", f"need 0 < eps_c < 1, eps_s > 0, m > 0 (got {self.eps_c}, {self.eps_s}, {self.m})")
        if not 0 < self.board_z < 0.5:
            bad("board_z", f"{self.board_z} must lie in (0, 0.5) (domain is the unit cube)")
        bound = self.cfl_bound()
        dt = self.effective_dt()
        if not 0 < dt <= bound:
            bad("dt", f"{dt:.3g} violates the CFL bound dt <= dx / (c + v_knife) = {bound:.3g} "
                      f"(n_grid={self.n_grid}, wave speed c={self.wave_speed():.3g}); set sim.dt <= {bound:.3g} "
                      f"or sim.dt=null to use cfl * bound")
        for key in ("dwell_time", "push_time", "settle_time", "turn_settle_time", "push_distance"):
            if getattr(self, key) < 0:
                bad(key, f"{getattr(self, key)} must be >= 0 ({'units' if key == 'push_distance' else 'seconds'})")
        if not 1 <= self.fields <= 16:
            bad("fields", f"{self.fields}; valid: 1 (single-field MPM) to 16 velocity fields per node")
        if self.contact_friction < 0:
            bad("contact_friction", f"{self.contact_friction} must be >= 0 (a Coulomb coefficient)")
        if not 0 <= self.gravity <= 1000:
            bad("gravity", f"{self.gravity}; valid: 0 to 1000 (units/s^2 along -z; 9.8 is Earth's)")
        if not 0 < self.j_min < 1 < self.j_max:
            bad("j_min", f"need 0 < j_min < 1 < j_max (got {self.j_min}, {self.j_max})")
        for key in ("friction", "knife_friction"):
            if getattr(self, key) < 0:
                bad(key, f"{getattr(self, key)} must be >= 0 (a Coulomb coefficient)")
        if self.cut_substeps is not None and self.cut_substeps < 1:
            bad("cut_substeps", f"{self.cut_substeps} must be >= 1 or null")
        if self.kerf_half_width is not None and not self.kerf_half_width >= 0:
            bad("kerf_half_width", f"{self.kerf_half_width}; valid: null (the blade's half-thickness, at least "
                                   f"half a particle spacing) or a distance >= 0 [units]")
        return self

"""The materials of a cutting scene: one class each, registered by the id particles carry in ``material``.

A material holds its parameters (read from the SimConfig; Python numbers, so kernels bake them in as constants)
and its part of a particle's deformation update as @ti.func methods: ``damage_rule`` (on J = det F before any
return map), ``flows`` (whether F needs its singular values this step) and ``return_map`` (on the singular values).
The stress law, fixed-corotated with Kirchhoff tau = P F^T, is common to all (``FixedCorotated``).
``MaterialUpdate.particle_update``, the start of every p2g, dispatches over the registered materials with
``ti.static`` (one unrolled branch per material, as in Genesis's MPM solver), so a new material is a class with a
fresh id, its three methods and ``@register``; nothing else in the solver changes.

PlastoElasticCore (0): fixed-corotated elasticity with the paper's det F damage: a particle whose J leaves
[(1 - eps_c)^m, (1 + eps_s)^m] is damaged for good and keeps ``damaged_stiffness`` of its stiffness, flowing (no
shear memory).  VonMisesSkin (1): von Mises plasticity on the Hencky strain with softening,
sigma_y -= gamma |d eps_p|; it fractures (is damaged) when sigma_y reaches 0, never through the core's J
thresholds.  The cream pen's cream is VonMisesSkin with the pen's parameters (topocut/sim/pen.py).
docs/sim.md, "Materials".
"""
import taichi as ti

MATERIALS: dict = {}  # id -> material class; MPMSolver makes one instance of each from its SimConfig


def register(cls):
    """Class decorator: particles with ``material == cls.id`` take cls's update (ids are the ``material`` values)."""
    if cls.id in MATERIALS:
        raise ValueError(f"material id {cls.id} is taken by {MATERIALS[cls.id].__name__}")
    MATERIALS[cls.id] = cls
    return cls


def make_materials(cfg) -> tuple:
    """One instance of every registered material, in id order, with its parameters from ``cfg`` (SimConfig)."""
    return tuple(MATERIALS[i](cfg) for i in sorted(MATERIALS))


@ti.func
def polar_rotation(F):
    """R of F = R S by Newton's iteration R <- (R + R^-T) / 2 (F is near a rotation; cheaper than an SVD)."""
    R = F
    for _ in ti.static(range(4)):
        R = 0.5 * (R + R.inverse().transpose())
    return R


@ti.data_oriented
class FixedCorotated:
    """Fixed-corotated elasticity, the stress law every material shares: tau = 2 mu (F - R) F^T + lam J (J - 1) I,
    mu and lam scaled by ``scale`` (``damaged_stiffness`` once the particle is damaged, for good).

    One instance (MPMSolver.elasticity), evaluated once per particle after the materials' return maps rather than
    in each material's branch: a GPU warp of mixed core and skin then runs it once, and the CPU results stay bit
    for bit those of the single-law code (computed inside ti.static branches, LLVM's fast-math rounds tau
    differently)."""

    def __init__(self, cfg):
        self.mu, self.lam = cfg.mu, cfg.lam  # Lame parameters
        self.damaged_stiffness = cfg.damaged_stiffness  # mu and lam scale of a damaged particle

    @ti.func
    def stress(self, F, R, J, scale):
        mu, la = self.mu * scale, self.lam * scale
        return 2 * mu * (F - R) @ F.transpose() + ti.Matrix.identity(ti.f32, 3) * la * J * (J - 1)


@ti.data_oriented
class Material:
    """A registered material's parameters; subclasses add ``damage_rule``, ``flows`` and ``return_map``."""

    id = -1  # padding rows of a batch carry -1: no material

    def __init__(self, cfg):
        self.mu = cfg.mu  # shear modulus (the stress law's, FixedCorotated; the return maps read it too)
        self.rho = cfg.rho_core  # density


@register
class PlastoElasticCore(Material):
    """The food's inside: elastic until det F leaves [jc, js], then damaged for good and flowing."""

    id = 0

    def __init__(self, cfg):
        super().__init__(cfg)
        self.jc, self.js = (1 - cfg.eps_c) ** cfg.m, (1 + cfg.eps_s) ** cfg.m  # critical compression, stretch of J

    @ti.func
    def damage_rule(self, s: ti.template(), b, p, J):
        if J <= self.jc or J >= self.js:
            s.damage[b, p] = 1

    @ti.func
    def flows(self, s: ti.template(), b, p):
        """Only a damaged core flows: a healthy one is elastic (its R from the polar iteration, no SVD)."""
        return s.damage[b, p] == 1

    @ti.func
    def return_map(self, s: ti.template(), b, p, sig, scale):
        """A damaged core particle forgets its shear (flows), keeping a clamped volume ratio."""
        J = ti.min(ti.max(sig[0, 0] * sig[1, 1] * sig[2, 2], 0.3), 3.0)
        c = ti.pow(J, 1.0 / 3.0)
        return ti.Matrix([[c, 0, 0], [0, c, 0], [0, 0, c]])


@register
class VonMisesSkin(Material):
    """The food's skin: plastic on a von Mises yield surface whose yield stress ``sigma_y`` (per particle, starting
    at ``yield_stress``) softens with plastic flow; fractured (damaged) at sigma_y <= 0."""

    id = 1

    def __init__(self, cfg):
        super().__init__(cfg)
        self.rho = cfg.rho_skin
        self.softening = cfg.softening  # gamma

    @ti.func
    def damage_rule(self, s: ti.template(), b, p, J):
        pass  # the skin softens instead (return_map)

    @ti.func
    def flows(self, s: ti.template(), b, p):
        return True

    @ti.func
    def return_map(self, s: ti.template(), b, p, sig, scale):
        """Project the Hencky strain onto the yield surface; soften sigma_y by gamma * |d eps_p|."""
        eps = ti.Vector([ti.log(ti.max(sig[d, d], 1e-4)) for d in ti.static(range(3))])
        dev = eps - eps.sum() / 3.0
        norm = dev.norm() + 1e-12
        sy = ti.max(s.sigma_y[b, p], 0.0)
        if s.damage[b, p]:  # fractured skin (softened to zero) holds no shear
            sy = 0.0
        dgamma = norm - sy / (2 * self.mu * scale)
        if dgamma > 0:
            eps -= dgamma / norm * dev
            s.sigma_y[b, p] = sy - self.softening * dgamma
            if s.sigma_y[b, p] <= 0:
                s.damage[b, p] = 1
        return ti.Matrix([[ti.exp(eps[0]), 0, 0], [0, ti.exp(eps[1]), 0], [0, 0, ti.exp(eps[2])]])


class MaterialUpdate:
    """The deformation update every p2g starts with, dispatching to ``self.materials`` (MPMSolver inherits it
    and owns the fields the materials read and write: F, Jp, damage, sigma_y)."""

    @ti.func
    def particle_update(self, b, p, step):
        """Particle p's deformation update (plasticity, damage, the divergence flag; writes F, Jp) and what it
        scatters: (base node, fx, mass, momentum, APIC affine matrix).  Tools with their own scatter (the
        spoon's one-sided p2g) call it too, so every p2g shares one material model."""
        base = self.base_node(self.x[b, p])
        fx = self.x[b, p] * self.inv_dx - base.cast(ti.f32)
        F = (ti.Matrix.identity(ti.f32, 3) + self.dt * self.C[b, p]) @ self.F[b, p]
        J = F.determinant()
        mat = self.material[b, p]
        for m in ti.static(self.materials):
            if mat == m.id:
                m.damage_rule(self, b, p, J)
        if not (self.cfg.j_min < J < self.cfg.j_max):  # also catches NaN
            ti.atomic_min(self.bad_step[b], step)
        scale = 1.0
        if self.damage[b, p] == 1:
            scale = self.elasticity.damaged_stiffness
        R = ti.Matrix.identity(ti.f32, 3)
        if ti.static(self.rotation == "svd"):  # one SVD for every particle: a GPU warp runs one path
            U, sig, V = ti.svd(F)
            R = U @ V.transpose()
            if self.flows(mat, b, p):
                sig = self.return_map(mat, b, p, sig, scale)
                F = U @ sig @ V.transpose()
                J = sig[0, 0] * sig[1, 1] * sig[2, 2]
        else:
            if self.flows(mat, b, p):  # plastic: needs the singular values
                U, sig, V = ti.svd(F)
                sig = self.return_map(mat, b, p, sig, scale)
                F = U @ sig @ V.transpose()
                R = U @ V.transpose()
                J = sig[0, 0] * sig[1, 1] * sig[2, 2]
            else:  # elastic only
                R = polar_rotation(F)
        self.F[b, p] = F
        self.Jp[b, p] = J
        tau = self.elasticity.stress(F, R, J, scale)  # once for all materials: see FixedCorotated
        mass = self.vol * (self.cfg.rho_skin if mat == 1 else self.cfg.rho_core)
        stress = -self.dt * self.vol * 4 * self.inv_dx * self.inv_dx * tau
        affine = stress + mass * self.C[b, p]
        mom = mass * self.v[b, p]
        return base, fx, mass, mom, affine

    @ti.func
    def flows(self, mat, b, p):
        out = False
        for m in ti.static(self.materials):
            if mat == m.id:
                out = m.flows(self, b, p)
        return out

    @ti.func
    def return_map(self, mat, b, p, sig, scale):
        for m in ti.static(self.materials):
            if mat == m.id:
                sig = m.return_map(self, b, p, sig, scale)
        return sig

"""The materials of a cutting scene, as @ti.func methods MPMSolver inherits (it owns the fields they read).

Core (material 0): fixed-corotated elasticity with the paper's det F damage: a particle whose
J = det F leaves [(1 - eps_c)^m, (1 + eps_s)^m] is damaged for good and keeps `damaged_stiffness` of its
stiffness, flowing (no shear memory).  Skin (material 1): von Mises plasticity on the Hencky strain with
softening, sigma_y -= gamma |d eps_p|; it fractures (is damaged) when sigma_y reaches 0, never through the
core's J thresholds.  Kirchhoff stress tau = P F^T throughout.  docs/sim.md, "Materials".
"""
import taichi as ti


@ti.func
def polar_rotation(F):
    """R of F = R S by Newton's iteration R <- (R + R^-T) / 2 (F is near a rotation; cheaper than an SVD)."""
    R = F
    for _ in ti.static(range(4)):
        R = 0.5 * (R + R.inverse().transpose())
    return R


class Materials:
    """Stress and plasticity of core and skin; ``particle_update`` is the start of every p2g."""

    @ti.func
    def fixed_corotated(self, F, R, J, scale):
        mu, la = self.cfg.mu * scale, self.cfg.lam * scale
        return 2 * mu * (F - R) @ F.transpose() + ti.Matrix.identity(ti.f32, 3) * la * J * (J - 1)

    @ti.func
    def von_mises_return(self, sig, b, p, scale):
        """Project the Hencky strain onto the yield surface; soften sigma_y by gamma * |d eps_p|."""
        eps = ti.Vector([ti.log(ti.max(sig[d, d], 1e-4)) for d in ti.static(range(3))])
        dev = eps - eps.sum() / 3.0
        norm = dev.norm() + 1e-12
        sy = ti.max(self.sigma_y[b, p], 0.0)
        if self.damage[b, p]:  # fractured skin (softened to zero) holds no shear
            sy = 0.0
        dgamma = norm - sy / (2 * self.cfg.mu * scale)
        if dgamma > 0:
            eps -= dgamma / norm * dev
            self.sigma_y[b, p] = sy - self.cfg.softening * dgamma
            if self.sigma_y[b, p] <= 0:
                self.damage[b, p] = 1
        return ti.Matrix([[ti.exp(eps[0]), 0, 0], [0, ti.exp(eps[1]), 0], [0, 0, ti.exp(eps[2])]])

    @ti.func
    def damaged_flow(self, sig):
        """A damaged core particle forgets its shear (flows), keeping a clamped volume ratio."""
        J = ti.min(ti.max(sig[0, 0] * sig[1, 1] * sig[2, 2], 0.3), 3.0)
        c = ti.pow(J, 1.0 / 3.0)
        return ti.Matrix([[c, 0, 0], [0, c, 0], [0, 0, c]])

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
        if mat == 0 and (J <= self.jc or J >= self.js):  # the core's det F damage (the skin softens instead)
            self.damage[b, p] = 1
        if not (self.cfg.j_min < J < self.cfg.j_max):  # also catches NaN
            ti.atomic_min(self.bad_step[b], step)
        scale = 1.0
        R = ti.Matrix.identity(ti.f32, 3)
        if self.damage[b, p] == 1:
            scale = self.cfg.damaged_stiffness
        if ti.static(self.rotation == "svd"):  # one SVD for every particle: a GPU warp runs one path
            U, sig, V = ti.svd(F)
            R = U @ V.transpose()
            if mat == 1 or self.damage[b, p] == 1:
                if mat == 1:
                    sig = self.von_mises_return(sig, b, p, scale)
                else:
                    sig = self.damaged_flow(sig)
                F = U @ sig @ V.transpose()
                J = sig[0, 0] * sig[1, 1] * sig[2, 2]
        else:
            if mat == 1 or self.damage[b, p] == 1:  # plastic: needs the singular values
                U, sig, V = ti.svd(F)
                if mat == 1:
                    sig = self.von_mises_return(sig, b, p, scale)
                else:
                    sig = self.damaged_flow(sig)
                F = U @ sig @ V.transpose()
                R = U @ V.transpose()
                J = sig[0, 0] * sig[1, 1] * sig[2, 2]
            else:  # healthy core: elastic only
                R = polar_rotation(F)
        self.F[b, p] = F
        self.Jp[b, p] = J
        tau = self.fixed_corotated(F, R, J, scale)
        mass = self.vol * (self.cfg.rho_skin if mat == 1 else self.cfg.rho_core)
        stress = -self.dt * self.vol * 4 * self.inv_dx * self.inv_dx * tau
        affine = stress + mass * self.C[b, p]
        mom = mass * self.v[b, p]
        return base, fx, mass, mom, affine

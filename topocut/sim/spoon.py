"""Ice-cream scooping: a kinematic spoon (spherical-cap shell) and a static cup, as SDF colliders on the grid.

Spoon: the part of a spherical shell (inner radius r, thickness t, centre c) on the bowl side of
its rim plane, {x : (x - c) . a <= opening * r} with a the bowl's axis (from the bowl's bottom
towards its opening): opening 0 is a hemisphere.  The axis turns in the x-z plane,
a(phi) = (sin phi, 0, cos phi) (phi = 0: opening up; phi > 0: tipped towards +x), so a pose is
(c, phi) and the rigid velocity at x is v_c + phi_dot y_hat x (x - c).

``scoop_keyframes`` is the primitive of the paper's appendix for one 2-D placement (x, y) on the
block: lower (opening down, above the block), advance while curling upright (the rim cuts a cap of
the block into the bowl), lift while levelling, move over the cup, tilt to pour, withdraw.  The
pose is linear between keyframes.

Cup: a cylindrical wall (inner radius R, thickness w, height H) standing on the board.

Colliders (``collide_tools``, a Taichi kernel run between grid_op and g2p): a grid node within ``margin`` (half a
cell beyond the surface; the shell is thinner than a cell) of a tool may not move into it relative to the tool
(normal from the tool's mid-surface towards the node's side), with Coulomb friction on the tangential part.

Sided transfers (``p2g_sided``, ``g2p_sided``, replacing the solver's p2g and g2p while the spoon is in use): the
grid alone cannot separate material across a shell thinner than a cell, since a particle beside it exchanges
momentum with nodes on the far side (with the solver's transfers the whole block was lifted with the spoon).  As
in CPIC (Hu et al. 2018, the MLS-MPM paper's section on thin boundaries), particles and nodes below the rim plane
have a side of the shell's mid-sphere and a particle only scatters to / gathers from nodes on its side; an
incompatible node lends g2p the particle's own velocity (its normal part not moving into the spoon), and a
particle that still ends inside the shell's volume is put back on its side with the spoon's normal velocity.
"""
import math
from dataclasses import dataclass

import numpy as np
import taichi as ti

from topocut.sim.tools import SpoonConfig


def bowl_axis(phi: float) -> np.ndarray:  # 3,
    return np.array([math.sin(phi), 0.0, math.cos(phi)])


@dataclass
class Keyframe:
    t: float  # time [s] at which the spoon reaches this pose
    c: np.ndarray  # 3, bowl centre
    phi: float  # axis tilt towards +x [rad]
    phase: str = ""


class SpoonPath:
    """Piecewise-linear spoon pose over time: pose(t) -> (c, a, v_c, omega)."""

    def __init__(self, keyframes: list[Keyframe]):
        if len(keyframes) < 2 or any(b.t <= a.t for a, b in zip(keyframes, keyframes[1:])):
            raise ValueError("SpoonPath needs >= 2 keyframes with increasing times")
        self.keys = keyframes

    @property
    def duration(self) -> float:
        return self.keys[-1].t

    def phase(self, t: float) -> str:
        for b in self.keys[1:]:
            if t < b.t:
                return b.phase
        return "done"

    def pose(self, t: float):
        """Centre (3,), axis (3,), centre velocity (3,), angular velocity (3,) at time t (held after the end)."""
        ks = self.keys
        if t >= ks[-1].t:
            return ks[-1].c.copy(), bowl_axis(ks[-1].phi), np.zeros(3), np.zeros(3)
        t = max(t, ks[0].t)
        for a, b in zip(ks, ks[1:]):
            if t < b.t:
                s = (t - a.t) / (b.t - a.t)
                T = b.t - a.t
                c = a.c + s * (b.c - a.c)
                phi = a.phi + s * (b.phi - a.phi)
                return c, bowl_axis(phi), (b.c - a.c) / T, np.array([0.0, (b.phi - a.phi) / T, 0.0])
        raise AssertionError("unreachable")


def scoop_keyframes(spoon: SpoonConfig, place_xy, block_top: float, cup_top: float, t0: float = 0.0,
                    depth: float | None = None, pour_dx: float = 0.0) -> SpoonPath:
    """The scooping primitive starting at time t0 for a placement (x, y) of the bowl's centre on the block.

    The bowl's sphere is centred ``radius - depth`` above the block's top, so it dips ``depth`` (default
    ``spoon.depth``) into it.  ``pour_dx`` moves the pour point along x (negative: short of the cup); the two are
    how experiments/reference_scooping.py makes its wrong scoops, the task itself uses the defaults.  lower: opening down (phi = 180 deg), the shell is the sphere's upper half, still in the air;
    advance: move ``spoon.advance`` along +x while curling upright (phi = 0), so the rim sweeps along
    the sphere through the block and cuts the cap inside it loose (a rigid rotation about the
    sphere's centre moves the shell tangentially: it cuts instead of pushing); lift, level, clear of
    the cup; move over the cup (keeping y); tilt to 110 deg to pour; withdraw.
    """
    r, v = spoon.radius, spoon.speed
    x, y = float(place_xy[0]), float(place_xy[1])
    cz = block_top - (spoon.depth if depth is None else depth) + r  # sphere centre: its lowest point depth below the top
    lift_z = max(block_top, cup_top) + r + spoon.thickness + 0.03
    cup = np.array([spoon.cup_center[0] - 0.5 * r + pour_dx, y, lift_z])  # tipped to +x, the chunk leaves ahead of c
    frames = [Keyframe(t0, np.array([x, y, cz + 0.05]), math.pi, "start")]

    def go(c, phi, phase, speed=v, hold=0.0):
        prev = frames[-1]
        dist = max(np.linalg.norm(np.asarray(c) - prev.c), abs(phi - prev.phi) * r)
        frames.append(Keyframe(prev.t + max(dist / speed, hold, 1e-3), np.asarray(c, float), phi, phase))

    go([x, y, cz], math.pi, "lower")
    go([x + spoon.advance, y, cz], 0.0, "advance")  # upright: the shell now encloses the cap below the top
    go([x + spoon.advance, y, lift_z], 0.0, "lift")
    go(cup, 0.0, "move", speed=2 * v)
    go(cup, math.radians(110.0), "tilt")
    go(cup, math.radians(110.0), "pour", hold=0.15)
    go(cup + np.array([0.0, 0.0, 0.08]), math.radians(110.0), "withdraw")
    return SpoonPath(frames)


def spoon_sdf_np(x, c, a, spoon: SpoonConfig):
    """Signed distance (N,) of points (N,3) to the spoon shell (numpy mirror of the kernel's, for tests)."""
    d = np.asarray(x, float) - c
    rho = np.linalg.norm(d, axis=-1)
    shell = np.abs(rho - (spoon.radius + spoon.thickness / 2)) - spoon.thickness / 2
    cap = d @ a - spoon.opening * spoon.radius
    return np.maximum(shell, cap)


@ti.data_oriented
class ToolColliders:
    """The spoon (per scene, posed every substep) and the cup (static) acting on a solver's grid."""

    def __init__(self, solver, spoon: SpoonConfig, friction: float = 0.4):
        self.s, self.spoon, self.friction = solver, spoon, friction
        self.margin = 0.5 * solver.dx  # contact band beyond the shell: the shell (1 cm) is thinner than a cell
        fb = ti.FieldsBuilder()
        self.pose = ti.Vector.field(3, ti.f32)  # B,4: centre, axis, centre velocity, angular velocity
        self.on = ti.field(ti.i32)
        fb.dense(ti.ij, (solver.B, 4)).place(self.pose)
        fb.place(self.on)
        self._tree = fb.finalize()
        self.on[None] = 1

    def set_pose(self, poses) -> None:
        """poses: (B,4,3) from SpoonPath.pose per scene."""
        self.pose.from_numpy(np.asarray(poses, np.float32).reshape(self.s.B, 4, 3))

    @ti.func
    def contact(self, v, vb, nrm):
        """No penetration into the tool (relative normal velocity >= 0) with Coulomb friction."""
        vr = v - vb
        vn = vr.dot(nrm)
        out = v
        if vn < 0:
            vt = vr - vn * nrm
            vt *= ti.max(0.0, 1 + self.friction * vn / (vt.norm() + 1e-12))
            out = vb + vt
        return out

    # -- sided transfers (CPIC, Hu et al. 2018 "A moving least squares material point method", section 5) ----------
    # The shell (1 cm) is thinner than a cell: with the solver's p2g/g2p a particle beside it exchanges momentum with
    # nodes on the far side, so the block outside the bowl is dragged up with the chunk.  Here every particle and
    # node near the bowl has a side (inside / outside the shell's mid-sphere, where it is below the rim plane) and a
    # particle only scatters to and gathers from nodes on its own side; in g2p an incompatible node contributes the
    # particle's own velocity, its normal part relative to the spoon kept from moving into it.
    @ti.func
    def side(self, b, pos):
        """+1 outside the mid-sphere, -1 inside, 0 where the shell does not separate (above the rim plane, spoon off)."""
        out = 0
        if self.on[None] == 1:
            d = pos - self.pose[b, 0]
            if d.dot(self.pose[b, 1]) < self.spoon.opening * self.spoon.radius:
                out = 1 if d.norm() > self.spoon.radius + self.spoon.thickness / 2 else -1
        return out

    @ti.func
    def near_shell(self, b, pos):
        """Within 3 cells of the mid-sphere (beyond that no node of the particle's 3x3x3 stencil is across it)."""
        d = pos - self.pose[b, 0]
        return self.on[None] == 1 and ti.abs(d.norm() - self.spoon.radius - self.spoon.thickness / 2) < 3 * self.s.dx

    @ti.kernel
    def p2g_sided(self, n: ti.i32, step: ti.i32):
        """The solver's p2g (clear + scatter; MPMSolver.particle_update for the material), sided."""
        s = self.s
        s.clear_grid(step)  # the solver's clear (its grid box, sim.tuning.grid_box, when on)
        ti.loop_config(serialize=s.serial_scatter)  # one CPU thread: plain adds (Scatter.scatter)
        for b, p in ti.ndrange(s.B, s.capacity):
            if p < n and s.active(b, step) and s.live(b, p):
                xp = s.x[b, p]
                base, fx, mass, mom, affine = s.particle_update(b, p, step)  # the solver's material model
                s.grow_box(base)  # writes a subset of base .. base + 2, as the solver's scatter
                w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
                sp = 0
                if self.near_shell(b, xp):
                    sp = self.side(b, xp)
                for off in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
                    ok = True
                    if sp != 0:
                        sn = self.side(b, (base + off).cast(ti.f32) * s.dx)
                        ok = sn == 0 or sn == sp
                    if ok:
                        dpos = (off.cast(ti.f32) - fx) * s.dx
                        weight = w[off[0]][0] * w[off[1]][1] * w[off[2]][2]
                        s.grid_v[b * s.K + s.body[b, p], base + off] += weight * (mom + affine @ dpos)
                        s.grid_m[b * s.K + s.body[b, p], base + off] += weight * mass

    @ti.kernel
    def g2p_sided(self, n: ti.i32, step: ti.i32):
        """The solver's g2p, sided; then particles inside the shell's volume are put back on their side of it."""
        s = self.s
        r_mid = ti.static(self.spoon.radius + self.spoon.thickness / 2)
        half_t = ti.static(self.spoon.thickness / 2)
        for b, p in ti.ndrange(s.B, s.capacity):
            if p < n and s.active(b, step) and s.live(b, p):  # frozen scenes stay put, as in MPMSolver.gather
                xp = s.x[b, p]
                base = s.base_node(xp)
                fx = xp * s.inv_dx - base.cast(ti.f32)
                w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
                sp = 0
                if self.near_shell(b, xp):
                    sp = self.side(b, xp)
                c = self.pose[b, 0]
                nrm = (xp - c).normalized(1e-12) * ti.cast(sp, ti.f32)  # towards the particle's side
                vb = self.pose[b, 2] + self.pose[b, 3].cross(xp - c)
                v_own = s.v[b, p]
                vr = (v_own - vb).dot(nrm)
                if vr < 0:
                    v_own -= vr * nrm
                # topocut.sim.mpm.apic_gather, but a node across the shell lends v_own instead of its velocity
                new_v = ti.Vector.zero(ti.f32, 3)
                new_C = ti.Matrix.zero(ti.f32, 3, 3)
                for off in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
                    dpos = (off.cast(ti.f32) - fx) * s.dx
                    weight = w[off[0]][0] * w[off[1]][1] * w[off[2]][2]
                    g_v = s.grid_v[b * s.K + s.body[b, p], base + off]
                    if sp != 0:
                        sn = self.side(b, (base + off).cast(ti.f32) * s.dx)
                        if sn != 0 and sn != sp:
                            g_v = v_own
                    new_v += weight * g_v
                    new_C += 4 * s.inv_dx * s.inv_dx * weight * g_v.outer_product(dpos)
                xn = xp + s.dt * new_v
                if sp != 0:  # ended inside the shell (or across it): back onto the particle's side, moving with it
                    d = xn - c
                    dist = d.norm() + 1e-12
                    if ti.cast(sp, ti.f32) * (dist - r_mid) < half_t and d.dot(self.pose[b, 1]) < self.spoon.opening * self.spoon.radius:
                        xn = c + d / dist * (r_mid + ti.cast(sp, ti.f32) * (half_t + 1e-4))
                        nn = d / dist * ti.cast(sp, ti.f32)
                        vbn = self.pose[b, 2] + self.pose[b, 3].cross(xn - c)
                        vrel = new_v - vbn
                        vn = vrel.dot(nn)
                        if vn < 0:
                            vt = vrel - vn * nn
                            vt *= ti.max(0.0, 1 + self.friction * vn / (vt.norm() + 1e-12))
                            new_v = vbn + vt
                s.v[b, p], s.C[b, p] = new_v, new_C
                if not (xn.norm() < 10.0):
                    ti.atomic_min(s.bad_step[b], step)
                s.x[b, p] = xn

    @ti.kernel
    def collide_tools(self):
        s = self.s
        r_mid = ti.static(self.spoon.radius + self.spoon.thickness / 2)
        half_t = ti.static(self.spoon.thickness / 2)
        opening = ti.static(self.spoon.opening * self.spoon.radius)
        cup_c = ti.Vector([self.spoon.cup_center[0], self.spoon.cup_center[1]])
        cup_mid = ti.static(self.spoon.cup_radius + self.spoon.cup_wall / 2)
        cup_half = ti.static(self.spoon.cup_wall / 2)
        cup_top = ti.static(s.cfg.board_z + self.spoon.cup_height)
        for g, i, j, k in s.grid_m:  # g = b * K + f: every velocity field of scene b
            b = g // s.K
            if s.grid_m[g, i, j, k] > 0:
                pos = ti.Vector([i, j, k]).cast(ti.f32) * s.dx
                v = s.grid_v[g, i, j, k]
                # cup wall: a tube in (radial distance, z)
                dxy = ti.Vector([pos[0], pos[1]]) - cup_c
                rho = dxy.norm() + 1e-12
                d_wall = ti.abs(rho - cup_mid) - cup_half
                d_top = pos[2] - cup_top
                if ti.max(d_wall, d_top) < self.margin:
                    nrm = ti.Vector([0.0, 0.0, 1.0])
                    if d_wall > d_top:
                        side = ti.math.sign(rho - cup_mid + 1e-9)
                        nrm = ti.Vector([dxy[0] / rho * side, dxy[1] / rho * side, 0.0])
                    v = self.contact(v, ti.Vector.zero(ti.f32, 3), nrm)
                # spoon shell
                if self.on[None] == 1:
                    c, a = self.pose[b, 0], self.pose[b, 1]
                    d = pos - c
                    dist = d.norm() + 1e-12
                    d_shell = ti.abs(dist - r_mid) - half_t
                    d_cap = d.dot(a) - opening
                    if ti.max(d_shell, d_cap) < self.margin and d_cap < 0:
                        nrm = d / dist * ti.math.sign(dist - r_mid + 1e-9)
                        vb = self.pose[b, 2] + self.pose[b, 3].cross(d)
                        v = self.contact(v, vb, nrm)
                s.grid_v[g, i, j, k] = v

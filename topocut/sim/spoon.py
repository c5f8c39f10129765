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

The rim cuts: ``cut_with_rim`` (after g2p) damages the particles inside the shell, as the knife damages
its band (see its docstring for why).

Colliders (``collide_tools``, a Taichi kernel run between the solver's grid_op and g2p): a grid node
within ``margin`` (half a cell beyond the surface; the shell is thinner than a cell) of a tool may not move into it
relative to the tool (normal from the tool's mid-surface towards the node's side), with Coulomb
friction on the tangential part — so material rests in the bowl and is carried with it.
"""
import math
from dataclasses import dataclass

import numpy as np
import taichi as ti


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


def scoop_keyframes(spoon, place_xy, block_top: float, cup_top: float, t0: float = 0.0) -> SpoonPath:
    """The scooping primitive starting at time t0 for a placement (x, y) of the bowl's centre on the block.

    The bowl's sphere is centred ``radius - depth`` above the block's top, so it dips ``depth`` into
    it.  lower: opening down (phi = 180 deg), the shell is the sphere's upper half, still in the air;
    advance: move ``spoon.advance`` along +x while curling upright (phi = 0), so the rim sweeps along
    the sphere through the block and cuts the cap inside it loose (a rigid rotation about the
    sphere's centre moves the shell tangentially: it cuts instead of pushing); lift, level, clear of
    the cup; move over the cup (keeping y); tilt to 110 deg to pour; withdraw.
    """
    r, v = spoon.radius, spoon.speed
    x, y = float(place_xy[0]), float(place_xy[1])
    cz = block_top - spoon.depth + r  # sphere centre: its lowest point is depth below the top
    lift_z = max(block_top, cup_top) + r + spoon.thickness + 0.03
    cup = np.array([spoon.cup_center[0] - 0.5 * r, y, lift_z])  # tipped to +x, the chunk leaves ahead of c
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


def spoon_sdf_np(x, c, a, spoon):
    """Signed distance (N,) of points (N,3) to the spoon shell (numpy mirror of the kernel's, for tests)."""
    d = np.asarray(x, float) - c
    rho = np.linalg.norm(d, axis=-1)
    shell = np.abs(rho - (spoon.radius + spoon.thickness / 2)) - spoon.thickness / 2
    cap = d @ a - spoon.opening * spoon.radius
    return np.maximum(shell, cap)


@ti.data_oriented
class ToolColliders:
    """The spoon (per scene, posed every substep) and the cup (static) acting on a solver's grid."""

    def __init__(self, solver, spoon, friction: float = 0.4):
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

    @ti.kernel
    def cut_with_rim(self, n: ti.i32):
        """Particles inside the shell (inflated by half a cell) are cut: damaged, as the knife's band is.

        The grid cannot separate material across a shell thinner than a cell (a particle beside it
        spreads over nodes on both sides); damaged material keeps 1% of its stiffness and no yield
        stress, so the scooped cap comes loose instead of lifting the block with it.
        """
        s = self.s
        r_mid = ti.static(self.spoon.radius + self.spoon.thickness / 2)
        band = ti.static(self.spoon.thickness / 2) + 0.5 * s.dx
        opening = ti.static(self.spoon.opening * self.spoon.radius)
        for b, p in ti.ndrange(s.B, n):
            if self.on[None] == 1:
                d = s.x[b, p] - self.pose[b, 0]
                if ti.abs(d.norm() - r_mid) < band and d.dot(self.pose[b, 1]) < opening:
                    s.damage[b, p] = 1

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
        for b, i, j, k in s.grid_m:
            if s.grid_m[b, i, j, k] > 0:
                pos = ti.Vector([i, j, k]).cast(ti.f32) * s.dx
                v = s.grid_v[b, i, j, k]
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
                s.grid_v[b, i, j, k] = v

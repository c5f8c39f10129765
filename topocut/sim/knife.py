"""The knife and the contact between pieces: grid-node boundary conditions, @ti.func methods MPMSolver inherits.

Knife: an oriented box (frame u along the blade, w its height axis pointing to the edge, n its normal;
half extents k_half) whose edge midpoint moves from k_o along k_dir, at constant speed for a cut or
with a smooth start and stop for the push (k_smooth), oscillating along u.  In 'wedge' contact the blade
pushes each velocity field to that field's own side of the blade (``field_side``, from the pieces it
holds), at least k_target faster than the blade opens (the bevel) where a node is inside the blade, and
never into it in the one-cell band beside its faces.  Nothing is pushed ahead of the edge.

Pieces: velocity fields at one node belong to different pieces.  Bardenhagen et al. (2000): each field
moves on its own unless it approaches the others along the interface normal, then its normal velocity
relative to the node's centre of mass is removed (Coulomb friction on the rest): pieces press on and rest on
each other, slide, and separate freely, but never pull (no re-bonding).  docs/sim.md, "Pieces and contact".
"""
import math

import taichi as ti


class Knife:
    @ti.kernel
    def arm(self, f: ti.types.ndarray(dtype=ti.f32, ndim=2), k: ti.types.ndarray(dtype=ti.i32, ndim=2)):
        """Every scene's knife in one launch: f (B,22) o, u, w, n, half extents, travel direction (3 each), depth,
        speed, amplitude, target; k (B,4) smooth, sharp, hold, on."""
        for b in range(f.shape[0]):
            for a in ti.static(range(3)):
                self.k_o[b][a], self.k_u[b][a], self.k_w[b][a] = f[b, a], f[b, 3 + a], f[b, 6 + a]
                self.k_n[b][a], self.k_half[b][a], self.k_dir[b][a] = f[b, 9 + a], f[b, 12 + a], f[b, 15 + a]
            self.k_depth[b], self.k_speed[b], self.k_amp[b], self.k_target[b] = f[b, 18], f[b, 19], f[b, 20], f[b, 21]
            self.k_smooth[b], self.k_sharp[b], self.k_hold[b], self.k_on[b] = k[b, 0], k[b, 1], k[b, 2], k[b, 3]

    @ti.func
    def knife_motion(self, b, t):
        """Edge midpoint and velocity of scene b's knife at time t (stopped once it travelled k_depth)."""
        T = ti.max(self.k_depth[b] / self.k_speed[b], 1e-9)
        te = ti.min(t, T)
        s, sv = self.k_speed[b] * te, self.k_speed[b]
        if self.k_smooth[b] == 1:  # s = D (te/T - sin(2 pi te/T) / 2 pi): starts and stops at rest
            ph = 2 * math.pi * te / T
            s = self.k_depth[b] * (te / T - ti.sin(ph) / (2 * math.pi))
            sv = self.k_speed[b] * (1 - ti.cos(ph))
        om = 2 * math.pi * self.cfg.osc_frequency
        edge = self.k_o[b] + self.k_dir[b] * s + self.k_u[b] * self.k_amp[b] * ti.sin(om * te)
        vel = ti.Vector.zero(ti.f32, 3)
        if t < T:
            vel = self.k_dir[b] * sv + self.k_u[b] * self.k_amp[b] * om * ti.cos(om * te)
        return edge, vel

    @ti.func
    def knife_sdf(self, b, pos, edge):
        """Signed distance to the inflated blade box and its outward normal."""
        half = self.k_half[b]
        d = pos - (edge - self.k_w[b] * half[1])
        loc = ti.Vector([d.dot(self.k_u[b]), d.dot(self.k_w[b]), d.dot(self.k_n[b])])
        q = ti.abs(loc) - half
        qo = ti.max(q, 0.0)
        sd = qo.norm() + ti.min(q.max(), 0.0) - self.cfg.margin
        g = ti.Vector.zero(ti.f32, 3)
        if qo.norm() > 0:
            g = qo / qo.norm()
        else:  # inside: the face of largest q
            qm = q.max()
            for i in ti.static(range(3)):
                if q[i] == qm:
                    g = ti.Vector([1.0 if i == 0 else 0.0, 1.0 if i == 1 else 0.0, 1.0 if i == 2 else 0.0])
        g = g * ti.math.sign(loc + 1e-12)
        nrm = g[0] * self.k_u[b] + g[1] * self.k_w[b] + g[2] * self.k_n[b]
        return sd, nrm

    @ti.func
    def collide(self, v, vk, nrm, target, mu):
        """Raise the normal velocity relative to the collider to >= target; Coulomb friction on the rest."""
        vr = v - vk
        vn = vr.dot(nrm)
        out = v
        if vn < target:
            vt = vr - vn * nrm
            vt *= ti.max(0.0, 1 - mu * (target - vn) / (vt.norm() + 1e-12))
            out = vk + vt + target * nrm
        return out

    @ti.func
    def knife_contact(self, b, f, pos, v, t, contact: ti.template()):
        """Field f of scene b at a node at pos after the knife: (velocity, whether the blade acted)."""
        edge, vk = self.knife_motion(b, t)
        sd, nrm = self.knife_sdf(b, pos, edge)
        touched = False
        if contact == 0:  # wedge: each field to its own side of the blade
            side = self.field_side[b * self.K + f]
            sgn = ti.cast(side, ti.f32)
            if side == 0:  # a field of pieces on both sides (an uncut piece): the node's side
                sgn = ti.math.sign((pos - edge).dot(self.k_n[b]) + 1e-12)
            if sd < 0 or (sd < self.dx and ti.abs(nrm.dot(self.k_n[b])) > 0.5):
                # a field whose pieces are on one side only may not move towards the other side (the fields
                # already part the pieces); an uncut piece is split by the bevel's opening speed inside the blade
                target = self.k_target[b] if sd < 0 and side == 0 else 0.0
                v = self.collide(v, vk, self.k_n[b] * sgn, target, self.cfg.knife_friction)
                if side != 0 and side == self.k_hold[b]:  # the push holds the piece it slides (no overshoot)
                    v -= (v - vk).dot(self.k_n[b]) * self.k_n[b]
                touched = True
        else:  # solid: nodes inside move with the body, a contact band around it slides with friction
            if sd < 0:
                v = vk
                touched = True
            elif sd < self.dx:
                v = self.collide(v, vk, nrm, 0.0, self.cfg.knife_friction)
                touched = True
        return v, touched

    @ti.func
    def blade_damage(self, b, p, t):
        """During a cut the blade destroys the material in its kerf: particles within ``cfg.kerf`` of its plane,
        inside its length and above its edge, are damaged.  The kerf is the blade's own thickness, not the
        contact's inflated box: the inflation is half a cell, so a 3 cm slab at 128^3 (5 cm at 64^3) lost 40%
        of its particles to damage and sagged.  They are not moved: the velocity fields already keep each piece
        on its side (moving them out of the blade would pack material into a layer on each face)."""
        if self.k_on[b] == 1 and self.k_sharp[b] == 1:
            edge, _ = self.knife_motion(b, t)
            half = self.k_half[b]
            d = self.x[b, p] - (edge - self.k_w[b] * half[1])
            if (ti.abs(d.dot(self.k_u[b])) <= half[0] and ti.abs(d.dot(self.k_w[b])) <= half[1]
                    and ti.abs(d.dot(self.k_n[b])) <= ti.static(self.cfg.kerf)):
                self.damage[b, p] = 1

    # -- contact between the velocity fields of one node (pieces) --------------------------------------------
    @ti.func
    def field_normal(self, b, f, I):
        """Unit normal at node I from field f towards the node's other fields: grad(M) - 2 grad(m_f), the
        symmetric two-body normal (grad m_other - grad m_f), by central differences of the nodal masses."""
        g_all, g_f = ti.Vector.zero(ti.f32, 3), ti.Vector.zero(ti.f32, 3)
        for d in ti.static(range(3)):
            for sgn in ti.static((-1, 1)):
                J = I
                J[d] = ti.min(ti.max(I[d] + sgn, 0), self.n_grid - 1)
                for h in range(self.n_fields[None]):
                    m = self.grid_m[b * self.K + h, J]
                    g_all[d] += sgn * m
                    if h == f:
                        g_f[d] += sgn * m
        return (g_all - 2 * g_f).normalized(1e-20)

    @ti.func
    def field_contact(self, b, f, I, v, v_cm):
        """Field f's velocity after contact with the node's other fields (centre-of-mass velocity v_cm)."""
        nrm = self.field_normal(b, f, I)
        vr = v - v_cm
        vn = vr.dot(nrm)
        out = v
        if vn > 0 and nrm.norm() > 0.5:  # approaching the others: no interpenetration, friction on the rest
            vt = vr - vn * nrm
            vt *= ti.max(0.0, 1 - self.cfg.contact_friction * vn / (vt.norm() + 1e-12))
            out = v_cm + vt
        return out

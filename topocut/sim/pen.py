"""Cream pen: a nozzle at a fixed height that extrudes a von Mises "cream" into B MPM scenes.

The cream is the solver's plastic material (material 1, fixed-corotated on a von Mises return
map) with a low per-particle yield stress ``pen.yield_stress``; softening is off and the damage
thresholds are out of reach, so it never turns into the cutting tasks' damaged flow: it holds its
shape once it lies on the board (a Bingham-like paste).  It is softer than the food
(``pen.mu``, ``pen.lam``), which raises the stable time step.

Extrusion appends particles: while the pen is on (b = 1) a layer of m particles (the lattice points
within ``nozzle_radius`` spacings of the axis, in the horizontal plane) is written at the nozzle
every time the extruded column has grown by one spacing, i.e. on substep i of a stroke when
floor(i * dt * extrude_speed / spacing) steps up (and on the stroke's first substep); new particles
move straight down at the extrusion speed, at rest horizontally: the bead is laid, not thrown.  The
cream comes to rest about a cell above the highest node that board_contact holds (board_z + dx): at
n_grid 48 and 64 at z ~ 0.08, the nozzle's own height (board_z + pen.height), so it does not fall.  Given
the pen's horizontal velocity, the nozzle ploughed its own bead: the first ~8 layers of every stroke rode
1-2 cm with it and piled up 1.4 spacings (docs/tasks.md#cream-writing).  The solver's active count ``n``
is raised by m.  The layer is the same in every scene (positions follow each scene's pen), so n stays
common to the batch.

Bookkeeping: ``stroke`` (n,) is the stroke id of every particle: a stroke is a maximal run of
extrusion, a new one starts whenever b goes from 0 to 1.  Strokes that do not touch are the
clusters of the written scene (tests check this against topology discovery).
"""

import dataclasses
import math

import numpy as np
import taichi as ti

from topocut.sim.config import SimConfig
from topocut.sim.env import NO_STEP, CuttingEnv, SimulationDiverged
from topocut.sim.tools import PenConfig, nozzle_layer  # noqa: F401 - nozzle_layer re-exported


def cream_sim_config(sim: SimConfig, pen: PenConfig) -> SimConfig:
    """The simulator settings of the cream scene: soft, no softening, damage thresholds never reached."""
    return dataclasses.replace(sim, mu=pen.mu, lam=pen.lam, yield_stress=pen.yield_stress, softening=0.0,
                               eps_c=0.9, eps_s=1e3, m=1.0, cut_substeps=None, friction=pen.friction,
                               fields=1)  # cream is never cut: one velocity field


@ti.data_oriented
class CreamPen:
    """B writing scenes: ``move(delta (B,2), b)`` drives every scene's pen; particles are appended."""

    def __init__(self, sim: SimConfig, pen: PenConfig, batch_size: int = 1, start=(0.5, 0.5)):
        self.pen = pen
        self.env = CuttingEnv(cream_sim_config(sim, pen), batch_size=batch_size)
        self.cfg, self.B, self.dt = self.env.cfg, self.env.B, self.env.dt
        self.spacing = self.cfg.spacing
        self.layer = nozzle_layer(self.spacing, pen.nozzle_radius)  # m,3
        self.m = len(self.layer)
        # reserve the capacity once: a rebuild would drop the solver (env.load_particles sizes it)
        self.env.load_particles(np.full((pen.max_particles, 3), 0.5, np.float32), np.ones(pen.max_particles, np.int32))
        self.env.n = 0
        self.solver = self.env.solver
        self.capacity = pen.max_particles
        self.nozzle_z = self.cfg.board_z + pen.height
        fb = ti.FieldsBuilder()
        self._layer = ti.Vector.field(3, ti.f32)  # m,3
        self._pos, self._vel = ti.Vector.field(3, ti.f32), ti.Vector.field(3, ti.f32)  # B,3 nozzle, new velocity
        fb.dense(ti.i, self.m).place(self._layer)
        fb.dense(ti.i, self.B).place(self._pos, self._vel)
        self._tree = fb.finalize()
        self._layer.from_numpy(self.layer)
        self.reset(start)

    # -- state -------------------------------------------------------------------------
    def reset(self, start=(0.5, 0.5)) -> None:
        self.env.n = 0
        self.solver.sort_by_cell(0, by_cell=False)  # the scatter visits appended particles in memory order
        self.pos = np.tile(np.asarray(start, np.float64).reshape(1, 2), (self.B, 1))  # B,2
        self.stroke = np.zeros(0, np.int32)  # n, stroke id per particle
        self.num_strokes = 0
        self.on = False
        self.stroke_steps = 0  # substeps since the current stroke started
        self.t = 0.0

    @property
    def n(self) -> int:
        return self.env.n

    def get_state(self, b: int = 0) -> dict:
        st = self.env.get_state(b) if self.n else {"x": np.zeros((0, 3), np.float32)}
        return {**st, "pen": self.pos[b].copy(), "stroke": self.stroke.copy(), "num_strokes": self.num_strokes,
                "on": self.on, "stroke_steps": self.stroke_steps, "t": self.t}

    def set_state(self, state: dict) -> None:
        """Load one scene's get_state() into every scene (MPPI rollouts branch from it)."""
        n = len(state["x"])
        if n:
            self.env.set_state({k: v for k, v in state.items() if k in ("x", "v", "C", "F", "sigma_y", "damage",
                                                                          "material")}, b=None)
        else:
            self.solver.sort_by_cell(0, by_cell=False)
        self.env.n = n
        self.pos = np.tile(np.asarray(state["pen"], np.float64).reshape(1, 2), (self.B, 1))
        self.stroke = np.asarray(state["stroke"], np.int32).copy()
        self.num_strokes, self.on = int(state["num_strokes"]), bool(state["on"])
        self.stroke_steps, self.t = int(state["stroke_steps"]), float(state["t"])

    def particles(self) -> tuple[np.ndarray, np.ndarray]:
        """Positions (B,n,3) and stroke ids (n,)."""
        if not self.n:
            return np.zeros((self.B, 0, 3), np.float32), self.stroke
        return self.solver.x.to_numpy()[:, :self.n], self.stroke

    # -- extrusion -------------------------------------------------------------------------
    @ti.kernel
    def _emit(self, n0: ti.i32, sigma_y: ti.f32):
        s = self.solver
        for b, k in ti.ndrange(self.B, self.m):
            p = n0 + k
            s.x[b, p] = self._pos[b] + self._layer[k]
            s.v[b, p] = self._vel[b]
            s.C[b, p] = ti.Matrix.zero(ti.f32, 3, 3)
            s.F[b, p] = ti.Matrix.identity(ti.f32, 3)
            s.Jp[b, p] = 1.0
            s.sigma_y[b, p] = sigma_y
            s.damage[b, p] = 0
            s.material[b, p] = 1

    def emit(self) -> int:
        """Append one layer at every scene's nozzle, moving down at the extrusion speed; returns m."""
        if self.n + self.m > self.capacity:
            raise RuntimeError(f"cream pen: {self.n + self.m} particles exceed task.pen.max_particles="
                               f"{self.capacity}; raise it")
        pos = np.concatenate([self.pos, np.full((self.B, 1), self.nozzle_z)], 1)
        vel = np.tile([0.0, 0.0, -self.pen.extrude_speed], (self.B, 1))  # B,3: laid at rest (module docstring)
        self._pos.from_numpy(pos.astype(np.float32))
        self._vel.from_numpy(vel.astype(np.float32))
        self._emit(self.n, self.pen.yield_stress)
        self.env.n += self.m
        self.stroke = np.concatenate([self.stroke, np.full(self.m, self.num_strokes - 1, np.int32)])
        return self.m

    def layers_due(self, i: int) -> int:
        """Layers a stroke has extruded by its substep i (0-based): 1 + floor(i dt v_e / spacing)."""
        return 1 + int(math.floor(i * self.dt * self.pen.extrude_speed / self.spacing + 1e-9))

    # -- time stepping ----------------------------------------------------------------------
    @ti.kernel
    def board_contact(self):
        """Coulomb contact (task.pen.friction) on the node layer just above the board.

        The solver's board acts on nodes at z <= board_z; resting cream (a bead two particles high)
        puts most of its mass one layer higher, so without this it slides on.  Runs between the
        solver's grid_op and g2p.
        """
        s = self.solver
        top = self.cfg.board_z + s.dx
        for g, i, j, k in s.grid_m:  # every velocity field of every scene
            if s.grid_m[g, i, j, k] > 0 and k * s.dx <= top:
                v = s.grid_v[g, i, j, k]
                if v[2] < 0:
                    vt = ti.Vector([v[0], v[1], 0.0])
                    v = vt * ti.max(0.0, 1 + self.cfg.friction * v[2] / (vt.norm() + 1e-12))
                    s.grid_v[g, i, j, k] = v

    def step(self, vel_xy: np.ndarray, b: bool) -> int:
        """One substep: toggle extrusion, maybe extrude a layer, advance MPM, move the pen; returns particles added."""
        if b and not self.on:
            self.num_strokes += 1
            self.stroke_steps = 0
        self.on = bool(b)
        added = 0
        if self.on:
            due = self.layers_due(self.stroke_steps) - (self.layers_due(self.stroke_steps - 1)
                                                        if self.stroke_steps else 0)
            for _ in range(due):
                added += self.emit()
            self.stroke_steps += 1
        s, k = self.solver, self.env.step_count
        if self.n:
            s.p2g(self.n, k)
            s.grid_op(self.t, 0)
            self.board_contact()
            s.g2p(self.n, k, self.t)
        self.env.step_count += 1
        self.t += self.dt
        self.pos = self.pos + np.asarray(vel_xy, np.float64).reshape(self.B, 2) * self.dt
        if self.env.step_count % self.cfg.tuning.check_every == 0:
            self.check()
        return added

    def check(self) -> None:
        bad = self.solver.bad_step.to_numpy()
        if (bad < NO_STEP).any():
            sc = int(np.argmin(bad))
            raise SimulationDiverged(int(bad[sc]), sc)

    def move(self, delta: np.ndarray, b: bool, speed: float | None = None) -> list[int]:
        """Move every scene's pen by delta (B,2) (or (2,)) in a straight line, extruding iff b.

        All scenes take the same number of substeps (set by the longest move at ``speed``, default
        pen.speed, or pen.travel_speed with b off), so they stay in step; returns the particles added per substep.
        """
        delta = np.broadcast_to(np.asarray(delta, np.float64), (self.B, 2))
        speed = speed or (self.pen.speed if b else self.pen.travel_speed)
        steps = max(1, int(math.ceil(np.linalg.norm(delta, axis=1).max() / (speed * self.dt))))
        vel = delta / (steps * self.dt)
        target = self.pos + delta
        added = [self.step(vel, b) for _ in range(steps)]
        self.pos = target  # no drift from summing dt steps
        self.check()
        return added

    def settle(self, substeps: int | None = None) -> None:
        """Pen off, let the cream come to rest."""
        for _ in range(self.pen.settle_substeps if substeps is None else substeps):
            self.step(np.zeros((self.B, 2)), False)
        self.check()

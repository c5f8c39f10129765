"""CuttingEnv: B cutting scenes, knife cuts and pushes on top of the batched MLS-MPM solver.

A cut moves a thin blade (``KnifeAction``) from just above the object down
along its in-plane travel direction w to the board while it oscillates along
its long axis u; it then rests ``dwell_time`` seconds.  Before it moves, the
pieces its swept surface will separate are found on the host (pieces.py) and
given velocity fields of their own, so the split is the blade's geometry.  In a
batch every scene gets its own substep budget (its travel + dwell) and is
frozen after it, so scene b's cut equals the same cut run alone.  The push
(``SimConfig.push_mode``) then slides the piece just cut off aside with the
blade's flat, and the pieces settle; ``turn`` lays pieces down turned (both in primitives.py).  See docs/sim.md.
"""
from __future__ import annotations

import dataclasses
import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from topocut.sim import pieces as P
from topocut.sim.action import KnifeAction, KnifeSweep
from topocut.sim.config import SimConfig
from topocut.sim.mpm import MPMSolver, init_taichi
from topocut.sim.objects import ObjectPose, sample_object
from topocut.sim.primitives import Primitives

NO_STEP = 2 ** 30


class SimulationDiverged(RuntimeError):
    """NaN/Inf positions or a runaway J = det F; ``step`` is the first bad substep, ``scene`` its scene."""

    def __init__(self, step: int, scene: int):
        super().__init__(f"simulation diverged at substep {step} (scene {scene}): a NaN/Inf position or J = det F "
                         f"outside (sim.j_min, sim.j_max); usual causes: a large sim.gravity or sim.knife_speed, a "
                         f"time step too long for the forces (lower sim.cfl or sim.dt), or J bounds tighter than "
                         f"the motion")
        self.step, self.scene = step, scene


@dataclass
class SimState:
    x: np.ndarray  # B,N,3 f32
    v: np.ndarray  # B,N,3 f32
    material: np.ndarray  # N, i32 (0 core, 1 skin) of scene 0 (get_state(b)["material"]: scene b's)
    damage: np.ndarray  # B,N bool
    sweeps: list = field(default_factory=list)  # B lists: the last cut's KnifeSweep per scene
    piece: np.ndarray | None = None  # B,N i32: which piece the knife has left each particle in (pieces.split)
    counts: np.ndarray | None = None  # B, particles of each scene: scene b's are rows :counts[b] (the rest pad)

    def scene(self, b: int) -> tuple[np.ndarray, np.ndarray]:
        """(x (n_b,3), damage (n_b,)) of scene b without the padding rows of a batch of different objects."""
        n = len(self.x[b]) if self.counts is None else int(self.counts[b])
        return self.x[b, :n], self.damage[b, :n]


@dataclass
class CutInfo:
    sweeps: list  # B, KnifeSweep per scene
    force: np.ndarray  # B,3 mean force the knife exerted on the material over the cut
    peak_force: np.ndarray  # B, largest |force| in one substep
    work: np.ndarray  # B, work done by the knife on the material
    knife_end: np.ndarray  # B,3 edge midpoint where the knife stopped
    newly_damaged: np.ndarray  # B, particles damaged by this cut
    substeps: int  # substeps the batch ran: the largest of substeps_per_scene
    wall_time: float
    substeps_per_scene: np.ndarray | None = None  # B, each scene's own budget (travel + dwell); frozen after it
    split_time: float = 0.0  # [s] of wall_time on the host finding the pieces the cut makes (pieces.py)


def cell_order(x: np.ndarray, n_grid: int) -> np.ndarray:
    """Indices that order particles (N,3) by base cell, then by sampling order (a stable sort).

    Particles of one cell become neighbours in memory, so the lanes of a GPU warp share their stencils
    (MPMSolver.scatter_warp adds them before the atomics) and their grid reads hit the same lines."""
    cell = np.floor(np.asarray(x) * n_grid - 0.5).astype(np.int64)  # N,3: the solver's base node
    return np.lexsort((cell[:, 2], cell[:, 1], cell[:, 0]))


class CuttingEnv(Primitives):
    def __init__(self, cfg: SimConfig | None = None, batch_size: int | None = None):
        cfg = cfg or SimConfig()
        self.B = self.batch_size = int(batch_size or cfg.batch_size)
        if self.B < 1:
            raise ValueError(f"batch_size must be >= 1, got {self.B}")
        # the config's checks and switches (grid box, warp-scatter key range) must see the B actually built
        self.cfg = dataclasses.replace(cfg, batch_size=self.B).validate()
        init_taichi(self.cfg.arch)
        self.dt = self.cfg.effective_dt()
        self.fuse = self.cfg.tuning.fuse_substeps
        self.resort = self.cfg.tuning.resort_interval(self.cfg.arch)
        self.solver: MPMSolver | None = None
        self.n = 0  # particle rows of every scene: the largest scene's count
        self.scene_n: np.ndarray | None = None  # B, each scene's own count where they differ (None: all hold n)
        self.object = None
        self.sweeps: list[list[KnifeSweep]] = [[] for _ in range(self.B)]
        self.piece = np.zeros((self.B, 0), np.int32)  # B,N: piece labels (host; the device holds their fields)
        self.push_side = np.zeros(self.B, np.int32)  # the side of the last cut's blade that was cut off (0: none)
        self.field_conflicts = 0  # neighbouring pieces that had to share a velocity field (pieces.colour)
        # False: a diverged scene raises SimulationDiverged.  True (a batch of independent episodes,
        # topocut.episode): it is frozen from then on and named in ``dead``, and the other scenes go on.
        self.freeze_diverged = False
        self.dead = np.zeros(self.B, bool)
        self.turn_refused: list = [None] * self.B  # per scene, why its turn (of a list of turns) was refused
        self.step_count = 0

    # -- particles ---------------------------------------------------------------------
    def _ensure(self, n: int) -> MPMSolver:
        if self.solver is None or self.solver.capacity < n:
            if self.solver is not None:
                self.solver.destroy()
            capacity = int(math.ceil(n * 1.15 / 1024) * 1024)
            self.solver = MPMSolver(self.cfg, self.B, capacity)
        self.n = n
        return self.solver

    @property
    def counts(self) -> np.ndarray:
        """(B,) particles of each scene (rows :counts[b] of scene b; the rest are padding, material -1)."""
        return np.full(self.B, self.n, np.int64) if self.scene_n is None else self.scene_n.copy()

    def sample(self, object: str, pose: ObjectPose | None = None, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Particles (N,3) and materials (N,) of ``object`` at ``pose``, ordered by base cell (as reset loads them)."""
        x, material = sample_object(object, pose, self.cfg.spacing, self.cfg.skin_thickness, seed, self.cfg.board_z)
        order = cell_order(x, self.cfg.n_grid)
        return x[order], material[order]

    def reset(self, object: str, pose: ObjectPose | None = None, seed: int = 0) -> SimState:
        self.load_particles(*self.sample(object, pose, seed))
        self.object = object
        return self.state()

    def reset_scenes(self, objects: list, poses: list | None = None, seeds: list | None = None) -> SimState:
        """Scene b holds ``objects[b]`` at ``poses[b]`` (sampled with ``seeds[b]``): B episodes of different objects
        and poses in one batch.  Scenes are padded to the largest particle count with particles no phase visits
        (material -1), so each scene evolves as it would alone; ``state().scene(b)`` drops the padding."""
        B = self.B
        poses = list(poses) if poses is not None else [None] * B
        seeds = list(seeds) if seeds is not None else [0] * B
        if not len(objects) == len(poses) == len(seeds) == B:
            raise ValueError(f"reset_scenes: got {len(objects)} objects, {len(poses)} poses, {len(seeds)} seeds "
                             f"for batch_size={B}")
        loaded = [self.sample(o, p, s) for o, p, s in zip(objects, poses, seeds)]
        self.load_scenes([{"x": x, "material": m, "object": o} for (x, m), o in zip(loaded, objects)])
        self.object = objects[0] if len(set(objects)) == 1 else list(objects)
        return self.state()

    def load_scenes(self, states: list[dict]) -> None:
        """Load one get_state()-like dict per scene (their particle counts may differ): scene b's rows
        :len(states[b]["x"]), padding after them."""
        if len(states) != self.B:
            raise ValueError(f"load_scenes got {len(states)} states for batch_size={self.B}")
        counts = np.array([len(np.asarray(st["x"]).reshape(-1, 3)) for st in states], np.int64)
        big = int(np.argmax(counts))
        self.set_state(states[big], b=None)  # every scene the largest: the solver's size, the fields' rows
        for b, st in enumerate(states):
            if b != big:
                self.set_state(st, b=b)

    def load_particles(self, x, material, v=None) -> None:
        """Put particles (N,3), materials (N,) and optional velocities (N,3) into every scene, at rest state."""
        x = np.asarray(x, np.float32).reshape(-1, 3)
        self.set_state({"x": x, "material": np.asarray(material, np.int32),
                        "v": np.zeros_like(x) if v is None else np.asarray(v, np.float32)}, b=None)

    # -- state -------------------------------------------------------------------------
    def state(self) -> SimState:
        """Every scene's particles (B,n,...); where scenes hold different counts, rows past counts[b] are padding
        (``SimState.scene(b)`` drops them)."""
        s, n = self._need(), self.n
        return SimState(x=s.x.to_numpy()[:, :n], v=s.v.to_numpy()[:, :n], material=s.material.to_numpy()[0, :n],
                        damage=s.damage.to_numpy()[:, :n].astype(bool), sweeps=[list(w) for w in self.sweeps],
                        piece=self.piece.copy(), counts=self.counts)

    def get_state(self, b: int = 0) -> dict:
        s = self._need()
        if not 0 <= b < self.B:
            raise ValueError(f"scene b={b} out of range [0, {self.B})")
        n = int(self.counts[b])
        obj = self.object[b] if isinstance(self.object, list) else self.object
        return {"x": s.x.to_numpy()[b, :n], "v": s.v.to_numpy()[b, :n], "C": s.C.to_numpy()[b, :n],
                "F": s.F.to_numpy()[b, :n], "sigma_y": s.sigma_y.to_numpy()[b, :n],
                "damage": s.damage.to_numpy()[b, :n].astype(bool), "material": s.material.to_numpy()[b, :n],
                "sweeps": [w.asdict() for w in self.sweeps[b]], "object": obj,
                "piece": self.piece[b, :n].copy(), "body": s.body.to_numpy()[b, :n]}

    def set_state(self, state: dict, b: int | None = None) -> None:
        """Load a get_state() dict into scene b (None: every scene). Missing C/F/sigma_y/damage mean rest state,
        a missing ``piece`` one piece (the fields of a state without ``body`` are coloured anew).  A scene may
        take a state of another particle count than the others (up to the solver's capacity): its rows past
        that count become padding (material -1) and ``counts`` records it."""
        x = np.asarray(state["x"], np.float32).reshape(-1, 3)
        n = len(x)
        if b is not None and not 0 <= b < self.B:
            raise ValueError(f"scene b={b} out of range [0, {self.B})")
        whole = b is None or self.B == 1
        if whole:
            s = self._ensure(n)
            self.scene_n = None
            self.piece = np.zeros((self.B, n), np.int32)
        else:
            s = self._need()
            if n > s.capacity:
                raise ValueError(f"state has {n} particles but scene {b} has room for {s.capacity}; load the "
                                 f"largest state with b=None first (CuttingEnv.load_scenes does)")
            counts = self.counts
            counts[b] = n
            if counts.max() > self.n:  # the other scenes' extra rows are padding already (material -1)
                self.piece = np.pad(self.piece, ((0, 0), (0, int(counts.max()) - self.n)))
            self.n = int(counts.max())
            self.scene_n = None if (counts == self.n).all() else counts
        scenes = range(self.B) if whole else [b]
        self.dead[list(scenes)] = False
        defaults = {"v": np.zeros((n, 3)), "C": np.zeros((n, 3, 3)), "F": np.broadcast_to(np.eye(3), (n, 3, 3)),
                    "sigma_y": np.full(n, self.cfg.yield_stress), "damage": np.zeros(n)}
        piece = np.zeros(n, np.int32) if state.get("piece") is None else np.asarray(state["piece"], np.int32)
        if state.get("body") is not None:
            body = np.asarray(state["body"], np.int32)
        else:
            body = P.colour(x, piece, self.cfg.n_grid, self.cfg.fields)[0] if piece.max(initial=0) > 0 else piece
        defaults["body"] = body
        state = {**state, "body": body}
        targets = {"x": s.x, "v": s.v, "C": s.C, "F": s.F, "sigma_y": s.sigma_y, "damage": s.damage, "body": s.body}
        for key, fld in targets.items():
            arr = fld.to_numpy()  # B,cap,...
            val = np.asarray(state.get(key, defaults.get(key)))
            for sb in scenes:
                arr[sb, :n] = val
                arr[sb, n:] = 0  # past the scene's particles: nothing (padding, or the rows no loop reaches)
            fld.from_numpy(arr)
        mat = s.material.to_numpy()  # B,cap
        for sb in scenes:
            if "material" in state:
                mat[sb, :n] = np.asarray(state["material"], np.int32)
            else:  # keep the scene's materials; rows that were padding become core
                mat[sb, :n] = np.maximum(mat[sb, :n], 0)
            mat[sb, n:] = -1
        s.material.from_numpy(mat)
        s.Jp.from_numpy(np.linalg.det(s.F.to_numpy()).astype(np.float32))
        s.sort_by_cell(self.n, self.resort > 0)  # the scatter's order must cover exactly particles 0 .. n-1
        sweeps = [KnifeSweep.fromdict(d) if isinstance(d, dict) else d for d in state.get("sweeps", [])]
        for sb in scenes:
            self.sweeps[sb] = list(sweeps)
            self.piece[sb, :n], self.piece[sb, n:] = piece, 0
        self.push_side[list(scenes)] = 0
        s.n_fields[None] = max(int(s.n_fields[None]), int(body.max(initial=0)) + 1)  # only grows: see _set_fields
        if whole:
            self.object = state.get("object", self.object)
        elif "object" in state and state["object"] != self.object:  # scenes of different objects: one name each
            names = list(self.object) if isinstance(self.object, list) else [self.object] * self.B
            names[b] = state["object"]
            self.object = names
        s.bad_step.fill(NO_STEP)
        s.k_on.fill(0)
        self._set_frozen()

    def _need(self) -> MPMSolver:
        if self.solver is None:
            raise RuntimeError("no particles loaded: call reset(object) or set_state(...) first")
        return self.solver

    # -- time stepping -------------------------------------------------------------------
    def _check(self) -> None:
        bad = self.solver.bad_step.to_numpy()
        if (bad < NO_STEP).any():
            if not self.freeze_diverged:
                b = int(np.argmin(bad))
                raise SimulationDiverged(int(bad[b]), b)
            self.dead |= bad < NO_STEP
            self.solver.bad_step.fill(NO_STEP)
            frozen = self.solver.frozen_at.to_numpy()
            self.solver.frozen_at.from_numpy(np.where(self.dead, 0, frozen).astype(np.int32))

    def _set_frozen(self, at=None) -> None:
        """frozen_at: scene b moves in substeps < at[b] (None: always); a diverged scene (``dead``) never."""
        at = np.full(self.B, NO_STEP) if at is None else np.asarray(at, np.int64)
        self.solver.frozen_at.from_numpy(np.where(self.dead, 0, np.minimum(at, NO_STEP)).astype(np.int32))

    def simulate(self, substeps: int, t0: float = 0.0, contact: int = 0) -> None:
        """Advance every scene by ``substeps`` substeps.

        An armed knife follows its motion from time t0; ``contact`` 0 treats it as a
        wedge, 1 as a solid body (sticky inside, sliding contact band).  Whole chunks of
        ``sim.fuse_substeps`` substeps go to one ``MPMSolver.advance`` call (a kernel graph),
        the rest to ``substep`` (same kernels, same result bit for bit); the host syncs only
        for the divergence check, every ``check_every`` substeps and at the end.
        """
        s = self._need()
        k, every = self.fuse, self.cfg.tuning.check_every
        i = 0
        while i < substeps:
            m = k if substeps - i >= k > 1 else 1
            if m > 1:
                ts = [t0 + (i + j) * self.dt for j in range(m)]  # the same float64 times substep() gets
                s.advance(self.n, self.step_count, ts, contact)
            else:
                s.substep(self.n, self.step_count, t0 + i * self.dt, contact)
            i += m
            self.step_count += m
            if self.resort and self.step_count // self.resort > (self.step_count - m) // self.resort:
                s.sort_by_cell(self.n)
            if i // every > (i - m) // every:
                self._check()
        self._check()

    def _arm_knife(self, o, u, w, nrm, half, depth, speed, amp, direction=None, target=None, smooth=0,
                   on=None, sharp=0, hold=None) -> None:
        """Knife pose per scene (B,3 arrays); ``speed``/``target`` scalars or one per scene.  It travels ``depth``
        along ``direction`` (default w, its own edge direction), smoothly started and stopped if ``smooth``."""
        s = self.solver
        direction = w if direction is None else direction
        for fld, val in ((s.k_o, o), (s.k_u, u), (s.k_w, w), (s.k_n, nrm), (s.k_half, half), (s.k_dir, direction)):
            fld.from_numpy(np.asarray(val, np.float32).reshape(self.B, 3))
        per_scene = lambda v: np.ascontiguousarray(np.broadcast_to(np.asarray(v, np.float32), (self.B,)))  # noqa: E731
        s.k_depth.from_numpy(per_scene(depth))
        s.k_speed.from_numpy(per_scene(speed))
        s.k_amp.from_numpy(per_scene(amp))
        s.k_target.from_numpy(per_scene(self.cfg.knife_wedge * np.asarray(speed) if target is None else target))
        s.k_smooth.fill(int(smooth))
        s.k_sharp.fill(int(sharp))  # a cut: the blade damages what it occupies (not the push, not the press)
        s.k_hold.from_numpy(np.zeros(self.B, np.int32) if hold is None else np.asarray(hold, np.int32))
        s.k_on.from_numpy(np.ones(self.B, np.int32) if on is None else np.asarray(on, np.int32))
        s.reset_knife_stats()

    # -- pieces -------------------------------------------------------------------------
    def _split(self, x: list[np.ndarray], sweeps: list[KnifeSweep], idle=None) -> None:
        """Before a cut: the pieces its swept surfaces make, their velocity fields and the fields' sides.

        ``x``: each scene's particles (n_b,3).  Scenes holding the same particles (MPMSolver rollouts from one
        state) share one neighbour search.  ``idle`` (B,) scenes are not cut: their pieces stay."""
        cfg, s = self.cfg, self.solver
        bonds = {}
        body = s.body.to_numpy()
        side = np.zeros((self.B, cfg.fields), np.int32)
        reach = cfg.knife_half_thickness + cfg.margin + 2 * cfg.dx  # where the wedge acts on a node's fields
        searched = []  # scenes whose neighbour search ran; a scene holding the same particles reuses it
        idle = np.zeros(self.B, bool) if idle is None else idle
        for b in range(self.B):
            if idle[b]:
                continue
            key = next((c for c in searched if x[c].shape == x[b].shape and np.array_equal(x[c], x[b])), None)
            if key is None:
                searched.append(b)
                bonds[b] = P.bonds(x[b], cfg.spacing)
            else:
                bonds[b] = bonds[key]

        counts = self.counts

        def one(b):  # numpy / scipy release the GIL in the large array work: scenes run in threads
            before, sw = self.piece[b, :counts[b]], sweeps[b]
            after = P.split(x[b], before, sw, cfg.spacing, bonds[b])
            field, conflicts = P.colour(x[b], after, cfg.n_grid, cfg.fields)
            return after, field, conflicts, P.cut_off_side(x[b], before, after, sw), \
                P.field_sides(x[b], field, cfg.fields, sw, reach)

        cut = [b for b in range(self.B) if not idle[b]]
        self.push_side[idle] = 0  # an idle scene cut nothing off
        side[idle] = s.field_side.to_numpy().reshape(self.B, -1)[idle]
        with ThreadPoolExecutor(max_workers=max(1, min(len(cut), os.cpu_count() or 1))) as pool:
            for b, (after, field, conflicts, cut_off, sides) in zip(cut, pool.map(one, cut)):
                c = counts[b]
                self.piece[b, :c], body[b, :c], self.push_side[b], side[b] = after, field, cut_off, sides
                self.field_conflicts += conflicts
        s.body.from_numpy(body)
        s.field_side.from_numpy(side.reshape(-1))
        s.n_fields[None] = max(int(s.n_fields[None]), int(body[:, :self.n].max()) + 1)  # only grows (see below)
        # n_fields never shrinks while the solver lives: fields past a smaller count would keep stale nodes the
        # clear no longer visits.  Empty fields cost a mass check per node.

    def cut(self, action: KnifeAction | list[KnifeAction]) -> CutInfo:
        """One cut per scene (a single action goes to every scene), all scenes in one launch sequence.

        Scene b runs its own budget, ceil(depth_b / (speed_b dt)) + dwell substeps, and is frozen
        (no phase touches it) for the rest of the batch's substeps, so its result does not depend on the
        other scenes: it equals a batch_size=1 cut with the same action from the same state.
        """
        t_wall = time.perf_counter()
        cfg, s = self.cfg, self._need()
        acts = [action] * self.B if isinstance(action, KnifeAction) else list(action)
        if len(acts) != self.B:
            raise ValueError(f"cut got {len(acts)} actions for batch_size={self.B}")
        # a None action (an episode that has ended) or a diverged scene: frozen through the cut, untouched
        idle = np.array([a is None for a in acts]) | self.dead
        acts = [KnifeAction(0.5, 0.5) if i else a for a, i in zip(acts, idle)]  # geometry only: no budget
        counts = self.counts
        x = [xb[:c] for xb, c in zip(s.x.to_numpy().astype(np.float64), counts)]  # B x (n_b,3)
        dmg0 = s.damage.to_numpy()[:, :self.n].sum(1)
        frames, o0, depth = [], [], []
        for b, a in enumerate(acts):
            a = a.canonical()
            u, w, nrm = a.blade_axis, a.travel, a.normal
            p0 = a.plane_point(cfg.board_z)
            p0 = p0 + u * float(u @ (x[b].mean(0) - p0))  # centre the blade on the object
            z_start = a.z_start if a.z_start is not None else x[b][:, 2].max() + cfg.knife_clearance + cfg.margin
            t_board = max(z_start - cfg.board_z, 0.0) / -w[2]  # travel until the edge reaches the board
            depth.append(t_board if a.depth is None else min(max(a.depth, 0.0), t_board))
            o0.append(p0 - w * t_board)
            frames.append((u, w, nrm))
        depth = np.asarray(depth)
        if cfg.cut_substeps is not None:  # each scene covers its own depth in cut_substeps substeps
            speed = np.maximum(depth, 1e-6) / (cfg.cut_substeps * self.dt)
            if (speed * self.dt > 0.5 * cfg.dx).any():
                raise ValueError(f"sim.cut_substeps={cfg.cut_substeps} moves the knife more than half a cell "
                                 f"per substep; raise it above {int(depth.max() / (0.5 * cfg.dx)) + 1}")
            osc = 2 * math.pi * cfg.osc_frequency * cfg.osc_amplitude
            bound = cfg.dx / (cfg.wave_speed() + float(speed.max()) + osc)  # the CFL bound at this knife speed
            if self.dt > bound:  # speed <= dx/dt - c - osc  <=>  cut_substeps >= depth / (dx - dt (c + osc))
                need = int(math.ceil(float(depth.max()) / (cfg.dx - self.dt * (cfg.wave_speed() + osc))))
                raise ValueError(f"sim.cut_substeps={cfg.cut_substeps} drives the knife at {speed.max():.3g} units/s, "
                                 f"so sim.dt={self.dt:.3g} exceeds the CFL bound {bound:.3g} at that speed; "
                                 f"use sim.cut_substeps >= {need} or a smaller sim.dt")
        else:
            speed = np.full(self.B, cfg.knife_speed)
        # the swept surface of each scene's blade: what _split separates before the knife moves
        sweeps = [KnifeSweep(origin=tuple(map(float, o0[b])), u=tuple(map(float, u)), w=tuple(map(float, w)),
                             n=tuple(map(float, nrm)), half_length=cfg.knife_half_length + cfg.osc_amplitude,
                             depth=float(depth[b]), half_thickness=cfg.knife_half_thickness + cfg.margin)
                  for b, (u, w, nrm) in enumerate(frames)]
        t_split = time.perf_counter()
        self._split(x, sweeps, idle)
        t_split = time.perf_counter() - t_split
        # each scene's own budget (cut_substeps exactly: ceil(depth / (speed dt)) may round up by one)
        travel = [cfg.cut_substeps if cfg.cut_substeps is not None else int(math.ceil(depth[b] / (speed[b] * self.dt)))
                  for b in range(self.B)]
        totals = np.where(idle, 0, np.asarray(travel, np.int64) + cfg.substeps(cfg.dwell_time))
        total = int(totals.max())
        half = [cfg.knife_half_length, cfg.knife_height / 2, cfg.knife_half_thickness]
        self._arm_knife(o0, [f[0] for f in frames], [f[1] for f in frames], [f[2] for f in frames],
                        [half] * self.B, depth, speed, cfg.osc_amplitude, sharp=1, on=(~idle).astype(np.int32))
        self._set_frozen(self.step_count + totals)  # scene b stops after its budget
        try:
            self.simulate(total, contact=0 if cfg.knife_mode == "wedge" else 1)
        finally:
            s.k_on.fill(0)
            self._set_frozen()  # outside a cut every scene moves (but a diverged one)
        om = 2 * math.pi * cfg.osc_frequency
        ends = [o0[b] + w * depth[b] + u * cfg.osc_amplitude * math.sin(om * depth[b] / speed[b])
                for b, (u, w, nrm) in enumerate(frames)]
        self.sweeps = [prev if i else [sw] for prev, sw, i in zip(self.sweeps, sweeps, idle)]
        sweeps = [None if i else sw for sw, i in zip(sweeps, idle)]
        duration = (totals * self.dt).astype(np.float32)  # B: each scene's own cut duration
        return CutInfo(sweeps=sweeps, force=s.k_imp.to_numpy() / np.maximum(duration, self.dt)[:, None], peak_force=s.k_peak.to_numpy(),
                       work=s.k_work.to_numpy().astype(np.float64), knife_end=np.asarray(ends),
                       newly_damaged=s.damage.to_numpy()[:, :self.n].sum(1) - dmg0, substeps=total,
                       wall_time=time.perf_counter() - t_wall, substeps_per_scene=totals, split_time=t_split)

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

import copy
import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np

from topocut.sim import pieces as P
from topocut.sim.action import KnifeAction, KnifeSweep
from topocut.sim.config import SimConfig
from topocut.sim.mpm import MPMSolver
from topocut.sim.primitives import Primitives
from topocut.sim.runtime import init_taichi, row_sums, to_device, to_host
from topocut.sim.scenes import NO_STEP, Scenes, SimState, cell_order  # noqa: F401 - SimState, cell_order: re-exported
from topocut.utils.runtime import host_map


class SimulationDiverged(RuntimeError):
    """NaN/Inf positions or a runaway J = det F; ``step`` is the first bad substep, ``scene`` its scene."""

    def __init__(self, step: int, scene: int):
        super().__init__(f"simulation diverged at substep {step} (scene {scene}): a NaN/Inf position or J = det F "
                         f"outside (sim.j_min, sim.j_max); usual causes: a large sim.gravity or sim.knife_speed, a "
                         f"time step too long for the forces (lower sim.cfl or sim.dt), or J bounds tighter than "
                         f"the motion")
        self.step, self.scene = step, scene


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
    split_time: float = 0.0  # [s] of wall_time finding the pieces the cut makes (pieces.py, or pieces_device.py)
    snapshots: list | None = None  # [CutSnapshot] during the cut, with cut(..., record_every=k) (renders); else None


@dataclass
class CutSnapshot:
    """The particles part-way through a cut (``CuttingEnv.cut(..., record_every=k)``): what a GIF of the cut shows."""

    substep: int  # substeps of the cut done
    x: np.ndarray  # B,n,3 f32 positions (rows past counts[b] are padding)
    damage: np.ndarray  # B,n bool
    knife_edge: np.ndarray  # B,3 the edge midpoint at that time (the knife's motion, knife.py)


class CuttingEnv(Scenes, Primitives):
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

    def simulate(self, substeps: int, t0: float = 0.0, contact: int = 0, on_record=None, record_every: int = 0) -> None:
        """Advance every scene by ``substeps`` substeps.

        An armed knife follows its motion from time t0; ``contact`` 0 treats it as a
        wedge, 1 as a solid body (sticky inside, sliding contact band).  Whole chunks of
        ``sim.fuse_substeps`` substeps go to one ``MPMSolver.advance`` call (a kernel graph),
        the rest to ``substep`` (same kernels, same result bit for bit); the host syncs only
        for the divergence check, every ``check_every`` substeps and at the end.  ``on_record(i)`` (with
        ``record_every`` k > 0) is called after the chunk that completes each multiple of k substeps (a host sync
        each: off by default, so nothing else pays for it).
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
            if on_record is not None and record_every > 0 and i // record_every > (i - m) // record_every:
                on_record(i)
        self._check()

    def _arm_knife(self, o, u, w, nrm, half, depth, speed, amp, direction=None, target=None, smooth=0,
                   on=None, sharp=0, hold=None) -> None:
        """Knife pose per scene (B,3 arrays); ``speed``/``target`` scalars or one per scene.  It travels ``depth``
        along ``direction`` (default w, its own edge direction), smoothly started and stopped if ``smooth``."""
        s = self.solver
        direction = w if direction is None else direction
        f = np.zeros((self.B, 22), np.float32)  # Knife.arm's columns: six (B,3) frames, then four per-scene scalars
        for c, val in enumerate((o, u, w, nrm, half, direction)):
            f[:, 3 * c:3 * c + 3] = np.asarray(val, np.float32).reshape(self.B, 3)
        for c, val in enumerate((depth, speed, amp,
                                 self.cfg.knife_wedge * np.asarray(speed) if target is None else target), start=18):
            f[:, c] = np.broadcast_to(np.asarray(val, np.float32), (self.B,))
        k = np.zeros((self.B, 4), np.int32)
        k[:, 0], k[:, 1] = int(smooth), int(sharp)  # sharp, a cut: the blade damages what it occupies (not the push)
        k[:, 2] = 0 if hold is None else np.asarray(hold, np.int32)
        k[:, 3] = 1 if on is None else np.asarray(on, np.int32)
        s.arm(to_device(f), to_device(k))  # one launch: a from_numpy per field was 14 (2-2.7 ms a cut at 128^3)
        s.reset_knife_stats()

    # -- pieces -------------------------------------------------------------------------
    def _split(self, xs: np.ndarray, sweeps: list[KnifeSweep], idle=None) -> None:
        """Before a cut: the pieces its swept surfaces make, their velocity fields and the fields' sides.

        ``xs``: the scenes' particles (B,N,3) f32 as the solver holds them (the device path reads the solver's
        own; the host path converts each scene's first counts[b] rows to f64).  Scenes holding the same particles
        (MPMSolver rollouts from one state) share one neighbour search.  ``idle`` (B,) scenes are not cut: their
        pieces stay."""
        cfg, s = self.cfg, self.solver
        bonds = {}
        reach = cfg.knife_half_thickness + cfg.margin + 2 * cfg.dx  # where the wedge acts on a node's fields
        searched = []  # scenes whose neighbour search ran; a scene holding the same particles reuses it
        idle = np.zeros(self.B, bool) if idle is None else idle
        counts = self.counts
        on_device = cfg.tuning.device_split_enabled(cfg.arch)
        if on_device:  # sim.tuning.device_split: every scene's split in one batch of kernels, the same labels
            split = self._split_on_device(sweeps, idle, reach)
            if split is None:
                return
        x = [None if idle[b] else xs[b, :counts[b]].astype(np.float64) for b in range(self.B)]  # B x (n_b,3)
        body = to_host(s.body)
        side = np.zeros((self.B, cfg.fields), np.int32)
        for b in range(self.B):
            if idle[b] or on_device:
                continue
            key = next((c for c in searched if x[c].shape == x[b].shape and np.array_equal(x[c], x[b])), None)
            if key is None:
                searched.append(b)
                bonds[b] = P.bonds(x[b], cfg.spacing)
            else:
                bonds[b] = bonds[key]

        def one(b):  # numpy / scipy release the GIL in the large array work: scenes run in threads
            before, sw = self.piece[b, :counts[b]], sweeps[b]
            after = split[b, :counts[b]] if on_device else P.split(x[b], before, sw, cfg.spacing, bonds[b])
            field, conflicts = P.colour(x[b], after, cfg.n_grid, cfg.fields, sw, reach)
            return after, field, conflicts, P.cut_off_side(x[b], before, after, sw), \
                P.field_sides(x[b], field, cfg.fields, sw, reach)

        cut = [b for b in range(self.B) if not idle[b]]
        self.push_side[idle] = 0  # an idle scene cut nothing off
        side[idle] = s.field_side.to_numpy().reshape(self.B, -1)[idle]
        for b, (after, field, conflicts, cut_off, sides) in zip(cut, host_map(one, cut)):
            c = counts[b]
            self.piece[b, :c], body[b, :c], self.push_side[b], side[b] = after, field, cut_off, sides
            self.field_conflicts += conflicts
        s.body.from_numpy(body)
        s.field_side.from_numpy(side.reshape(-1))
        s.n_fields[None] = max(int(s.n_fields[None]), int(body[:, :self.n].max()) + 1)  # only grows (see below)
        # n_fields never shrinks while the solver lives: fields past a smaller count would keep stale nodes the
        # clear no longer visits.  Empty fields cost a mass check per node.

    def _split_on_device(self, sweeps: list[KnifeSweep], idle: np.ndarray, reach: float) -> np.ndarray | None:
        """_split's device path: the pieces from the solver's positions in place (pieces_device), their fields,
        sides and cut-off side from per-piece summaries (fields_device), written into the solver.  Returns None
        when done, or the labels (B,n) when a label past 64 leaves the colouring to the host."""
        from topocut.sim.fields_device import colour_batch
        from topocut.sim.pieces_device import device_split

        cfg, s, n = self.cfg, self.solver, self.n
        ds = device_split(self.B, n)
        before = self.piece[:, :n]
        split = ds.run(s.x, self.counts, before, [None if i else sw for sw, i in zip(sweeps, idle)],
                       cfg.spacing)[:, :n]
        done = colour_batch(ds, s.body, split, before, cfg.n_grid, cfg.fields, reach)
        if done is None:
            return split
        side = s.field_side.to_numpy().reshape(self.B, -1)
        used = int(s.n_fields[None])
        self.push_side[idle] = 0  # an idle scene cut nothing off
        for b, res in enumerate(done):
            if res is None:
                continue
            conflicts, self.push_side[b], side[b], fields = res
            self.field_conflicts += conflicts
            used = max(used, fields)
        self.piece[:, :n] = split  # an idle scene's labels and the rows past a scene's count come back unchanged
        s.field_side.from_numpy(side.reshape(-1))
        s.n_fields[None] = used  # only grows (see _split)
        return None

    def _knife_speeds(self, depth: np.ndarray) -> np.ndarray:
        """Each scene's knife speed (B,): sim.knife_speed, or (sim.cut_substeps) its own depth in that many
        substeps, refused when that moves the knife more than half a cell per substep or past the CFL bound."""
        cfg = self.cfg
        if cfg.cut_substeps is None:
            return np.full(self.B, cfg.knife_speed)
        # each scene covers its own depth in cut_substeps substeps
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
        return speed

    def _recorder(self, s, snaps: list, o0, frames, depth, speed, om: float):
        """simulate()'s on_record for a cut: appends a CutSnapshot (particles, damage, knife edge) of the fields
        ``s`` to ``snaps``."""
        cfg = self.cfg

        def record(i):  # the edge as knife.py moves it: along w at speed until depth, oscillating along u
            te = np.minimum(i * self.dt, depth / np.maximum(speed, 1e-9))[:, None]  # B,1
            edge = np.asarray(o0) + np.stack([f[1] for f in frames]) * speed[:, None] * te \
                + np.stack([f[0] for f in frames]) * cfg.osc_amplitude * np.sin(om * te)  # B,3
            snaps.append(CutSnapshot(i, to_host(s.x)[:, :self.n].copy(), to_host(s.damage)[:, :self.n].astype(bool),
                                     edge))
        return record

    def cut(self, action: KnifeAction | list[KnifeAction], record_every: int = 0) -> CutInfo:
        """One cut per scene (a single action goes to every scene), all scenes in one launch sequence.

        ``record_every`` k > 0: ``CutInfo.snapshots`` holds the particles every k substeps (at the fused chunks'
        ends: ``sim.tuning.fuse_substeps``) with the knife's edge, for GIFs of the cut in motion; 0 (default) none.

        Scene b runs its own budget, ceil(depth_b / (speed_b dt)) + dwell substeps, and is frozen
        (no phase touches it) for the rest of the batch's substeps, so its result does not depend on the
        other scenes: it equals a batch_size=1 cut with the same action from the same state.
        """
        t_wall = time.perf_counter()
        cfg, s = self.cfg, self._need()
        if record_every < 0:
            raise ValueError(f"cut: record_every={record_every}; 0 records nothing, k > 0 every k substeps")
        acts = [action] * self.B if isinstance(action, KnifeAction) else list(action)
        if len(acts) != self.B:
            raise ValueError(f"cut got {len(acts)} actions for batch_size={self.B}")
        # a None action (an episode that has ended) or a diverged scene: frozen through the cut, untouched
        idle = np.array([a is None for a in acts]) | self.dead
        acts = [KnifeAction(0.5, 0.5) if i else a for a, i in zip(acts, idle)]  # geometry only: no budget
        counts = self.counts
        dmg0 = row_sums(s.damage, self.n)
        xs = to_host(s.x)  # B,N,3 f32
        frames, o0, depth, sweeps = _blade_plans(acts, xs, counts, cfg)
        speed = self._knife_speeds(depth)
        # the swept surface of each scene's blade (P.blade_sweep): what _split separates before the knife moves
        t_split = time.perf_counter()
        self._split(xs, sweeps, idle)
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
        om = 2 * math.pi * cfg.osc_frequency
        snaps = [] if record_every > 0 else None
        record = self._recorder(s, snaps, o0, frames, depth, speed, om) if snaps is not None else None
        try:
            self.simulate(total, contact=0 if cfg.knife_mode == "wedge" else 1, on_record=record,
                          record_every=record_every)
        finally:
            s.k_on.fill(0)
            self._set_frozen()  # outside a cut every scene moves (but a diverged one)
        ends = [o0[b] + w * depth[b] + u * cfg.osc_amplitude * math.sin(om * depth[b] / speed[b])
                for b, (u, w, nrm) in enumerate(frames)]
        self.sweeps = [prev if i else [sw] for prev, sw, i in zip(self.sweeps, sweeps, idle)]
        sweeps = [None if i else sw for sw, i in zip(sweeps, idle)]
        duration = (totals * self.dt).astype(np.float32)  # B: each scene's own cut duration
        return CutInfo(sweeps=sweeps, force=s.k_imp.to_numpy() / np.maximum(duration, self.dt)[:, None], peak_force=s.k_peak.to_numpy(),
                       work=s.k_work.to_numpy().astype(np.float64), knife_end=np.asarray(ends),
                       newly_damaged=row_sums(s.damage, self.n) - dmg0, substeps=total,
                       wall_time=time.perf_counter() - t_wall, substeps_per_scene=totals, split_time=t_split,
                       snapshots=snaps)


def _blade_plans(acts: list[KnifeAction], xs: np.ndarray, counts, cfg: SimConfig) -> tuple:
    """(frames [(blade axis, travel, normal)], start points, depths (B,), sweeps) of each scene's canonical action
    over its particles xs[b, :counts[b]] (the solver's float32 positions, P.blade_sweep), one scene after another:
    on an H200's host 16 scenes took 13.4 ms at 128^3 and 3.6 ms at 64^3 in turn, 14-16 and 9.5-12 ms in 16 threads
    (numpy's small passes hold the GIL; docs/benchmarks.md, "The thirty-fourth session")."""
    frames, o0, depth, sweeps = [], [], [], []
    for a, x, n in zip(acts, xs, counts):
        a = a.canonical()
        sw, d, o = P.blade_sweep(a, x[:n], cfg)
        frames.append((a.blade_axis, a.travel, a.normal))
        o0.append(o)
        depth.append(d)
        sweeps.append(sw)
    return frames, o0, np.asarray(depth), sweeps


_ENV: dict = {}  # this process's shared simulator (stage=mppi's parts): {"key": (sim config, batch size), "env": CuttingEnv}


def cached_env(sim, batch_size: int, make=None):
    """The process's CuttingEnv for ``sim`` (a SimConfig on the run's device) and ``batch_size``, built by ``make``
    (CuttingEnv) on first use.  A stage=all worker runs part after part of the same config: a new env each time
    would allocate its fields and build its kernel graphs again.  Every episode starts from env.reset, as the
    episodes of one run always did.  Another config releases the held env before building its own."""
    key = (copy.deepcopy(sim), int(batch_size))  # a copy: the caller's dataclass may be changed later
    if _ENV.get("key") != key:
        release_env()
        if make is None:  # looked up at call time (tests count the envs built through topocut.sim)
            from topocut.sim import CuttingEnv as make
        _ENV.update(key=key, env=make(sim, batch_size=int(batch_size)))
    return _ENV["env"]


def release_env() -> None:
    """Free the cached env's simulator fields: Taichi keeps a field tree until it is destroyed, not when its env
    is collected (as Scenes._ensure frees a solver it outgrows)."""
    env = _ENV.pop("env", None)
    _ENV.clear()
    if getattr(env, "solver", None) is not None:
        env.solver.destroy()
        env.solver = None

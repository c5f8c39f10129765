"""Loading and reading the scenes of a CuttingEnv (a mixin: CuttingEnv holds the solver and the host state).

Every scene may hold its own object: scenes are padded to the largest particle count ``n`` with material -1
(particles no phase visits), ``counts`` names each scene's own count, and ``SimState.scene(b)`` /
``get_state(b)`` drop the padding.  Writing goes through ``_write``: one round trip of every field for all the
scenes written.  See docs/sim.md ("Scenes of different objects").
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from topocut.sim import pieces as P
from topocut.sim.action import KnifeSweep
from topocut.sim.mpm import MPMSolver
from topocut.sim.objects import ObjectPose, sample_object
from topocut.sim.runtime import to_host

NO_STEP = 2 ** 30


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
class SavedScene:
    """A scene kept on the device by ``Scenes.save_scene``: the slot's name and token, and the host's part."""

    name: str
    token: object
    n: int
    piece: np.ndarray  # n, i32
    sweeps: list
    object: object
    n_fields: int
    push_side: int = 0  # the side the scene's last cut left for a push (save_scene_from; save_scene: none)


def cell_order(x: np.ndarray, n_grid: int) -> np.ndarray:
    """Indices that order particles (N,3) by base cell, then by sampling order (a stable sort).

    Particles of one cell become neighbours in memory, so the lanes of a GPU warp share their stencils
    (MPMSolver.scatter_warp adds them before the atomics) and their grid reads hit the same lines."""
    cell = np.floor(np.asarray(x) * n_grid - 0.5).astype(np.int64)  # N,3: the solver's base node
    return np.lexsort((cell[:, 2], cell[:, 1], cell[:, 0]))


@dataclass
class Snapshot:
    """Every scene kept on the device by ``Scenes.snapshot_scenes`` (a BatchSlot), and the host's part."""

    name: str
    token: object
    counts: np.ndarray  # B,
    piece: np.ndarray  # B,n i32
    sweeps: list
    object: object
    n_fields: int
    push_side: np.ndarray  # B,


class Scenes:
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
        :len(states[b]["x"]), padding after them.  One round trip of every field for the whole batch."""
        if len(states) != self.B:
            raise ValueError(f"load_scenes got {len(states)} states for batch_size={self.B}")
        counts = np.array([len(np.asarray(st["x"]).reshape(-1, 3)) for st in states], np.int64)
        self._ensure(int(counts.max()))
        self.scene_n = None if (counts == self.n).all() else counts
        self.piece = np.zeros((self.B, self.n), np.int32)
        self._write(dict(enumerate(states)))
        names = [st.get("object") for st in states]
        self.object = names[0] if len(set(names)) == 1 else names

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
        return SimState(x=to_host(s.x)[:, :n], v=to_host(s.v)[:, :n], material=to_host(s.material)[0, :n],
                        damage=to_host(s.damage)[:, :n].astype(bool), sweeps=[list(w) for w in self.sweeps],
                        piece=self.piece.copy(), counts=self.counts)

    def get_state(self, b: int = 0) -> dict:
        """Scene b as numpy arrays (only its rows cross to the host: copied on the device into a SceneSlot first)."""
        s = self._need()
        if not 0 <= b < self.B:
            raise ValueError(f"scene b={b} out of range [0, {self.B})")
        n = int(self.counts[b])
        obj = self.object[b] if isinstance(self.object, list) else self.object
        slot = s.slot("export")
        slot.save(b)
        a = slot.to_numpy(n)
        return {"x": a["x"], "v": a["v"], "C": a["C"], "F": a["F"], "sigma_y": a["sigma_y"],
                "damage": a["damage"].astype(bool), "material": a["material"],
                "sweeps": [w.asdict() for w in self.sweeps[b]], "object": obj,
                "piece": self.piece[b, :n].copy(), "body": a["body"]}

    def save_scene(self, b: int = 0, name: str = "saved") -> SavedScene:
        """Keep scene b on the device (the solver's SceneSlot ``name``, topocut.sim.slots) with its host-side
        labels: ``restore_scene`` puts it into every scene with one kernel, no round trip through numpy."""
        s = self._need()
        if not 0 <= b < self.B:
            raise ValueError(f"scene b={b} out of range [0, {self.B})")
        slot = s.slot(name)
        slot.save(b)
        slot.token = token = object()
        n = int(self.counts[b])
        obj = self.object[b] if isinstance(self.object, list) else self.object
        return SavedScene(name, token, n, self.piece[b, :n].copy(), list(self.sweeps[b]), obj,
                          int(s.n_fields[None]))

    def _holding(self, kept):
        """The solver's slot that still holds ``kept`` (a SavedScene or Snapshot: its name and token), or None (a
        later save under that name, or a new solver)."""
        slot = None if self.solver is None else getattr(self.solver, "_slots", {}).get(kept.name)
        return slot if slot is not None and getattr(slot, "token", None) is kept.token else None

    def snapshot_scenes(self, name: str = "snapshot") -> Snapshot:
        """Keep every scene on the device (the solver's BatchSlot ``name``) with its host-side labels:
        ``save_scene_from`` then keeps one of them as a SavedScene, as ``save_scene`` would have then."""
        s = self._need()
        slot = s.slot(name, every_scene=True)
        slot.save()
        slot.token = token = object()
        return Snapshot(name, token, self.counts, self.piece.copy(), [list(w) for w in self.sweeps], self.object,
                        int(s.n_fields[None]), self.push_side.copy())

    def save_scene_from(self, snap: Snapshot, b: int, name: str = "saved") -> SavedScene | None:
        """Scene b of ``snap`` (snapshot_scenes) as a SavedScene under ``name``, for ``restore_scene``, with the side
        its last cut left for a push (a restored cut may still be pushed); None where the snapshot's slot no longer
        holds it (a later snapshot under its name, or a new solver)."""
        src = self._holding(snap)
        if src is None:
            return None
        s = self.solver
        if not 0 <= b < len(snap.counts):
            raise ValueError(f"scene b={b} out of range [0, {len(snap.counts)})")
        slot = s.slot(name)
        slot.save_from(src, b)
        slot.token = token = object()
        n = int(snap.counts[b])
        obj = snap.object[b] if isinstance(snap.object, list) else snap.object
        return SavedScene(name, token, n, snap.piece[b, :n].copy(), list(snap.sweeps[b]), obj, snap.n_fields,
                          int(snap.push_side[b]))

    def restore_scene(self, saved: SavedScene) -> bool:
        """Load ``saved`` (save_scene) into every scene, as ``set_state(get_state(b), b=None)`` would, but J_p
        stays the solver's own; False (nothing changed) where the slot no longer holds it (a later save under
        the same name, or a new solver): then load the state through ``set_state``."""
        slot = self._holding(saved)
        if slot is None:
            return False
        slot.load()
        self.n, self.scene_n = saved.n, None
        self.piece = np.tile(saved.piece, (self.B, 1))
        self.sweeps = [list(saved.sweeps) for _ in range(self.B)]
        self.object = saved.object
        self.dead[:] = False
        self._loaded(slice(None), saved.n_fields)
        self.push_side[:] = saved.push_side  # a cut's outcome may still be pushed (save_scene_from)
        return True

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
        self._write({sb: state for sb in (range(self.B) if whole else [b])})
        if whole:
            self.object = state.get("object", self.object)
        elif "object" in state and state["object"] != self.object:  # scenes of different objects: one name each
            names = list(self.object) if isinstance(self.object, list) else [self.object] * self.B
            names[b] = state["object"]
            self.object = names

    def _write(self, states: dict) -> None:
        """Write {scene: state} into the fields (one to_numpy / from_numpy per field for all of them); rows past
        a scene's particle count become padding (material -1)."""
        s = self.solver
        prepared = {}  # id(state) -> its arrays: every scene of a set_state(b=None) shares one state
        for st in states.values():
            if id(st) in prepared:
                continue
            x = np.asarray(st["x"], np.float32).reshape(-1, 3)
            n = len(x)
            piece = np.zeros(n, np.int32) if st.get("piece") is None else np.asarray(st["piece"], np.int32)
            if st.get("body") is not None:
                body = np.asarray(st["body"], np.int32)
            else:
                body = P.colour(x, piece, self.cfg.n_grid, self.cfg.fields)[0] if piece.max(initial=0) > 0 else piece
            vals = {"x": x, "v": st.get("v", np.zeros((n, 3))), "C": st.get("C", np.zeros((n, 3, 3))),
                    "F": st.get("F", np.broadcast_to(np.eye(3), (n, 3, 3))),
                    "sigma_y": st.get("sigma_y", np.full(n, self.cfg.yield_stress)),
                    "damage": st.get("damage", np.zeros(n)), "body": body}
            sweeps = [KnifeSweep.fromdict(d) if isinstance(d, dict) else d for d in st.get("sweeps", [])]
            prepared[id(st)] = (n, vals, piece, st.get("material"), sweeps)
        scenes = list(states)
        self.dead[scenes] = False
        targets = {"x": s.x, "v": s.v, "C": s.C, "F": s.F, "sigma_y": s.sigma_y, "damage": s.damage, "body": s.body}
        for key, fld in targets.items():
            arr = to_host(fld)  # B,cap,...
            for sb, st in states.items():
                n, vals = prepared[id(st)][:2]
                arr[sb, :n] = np.asarray(vals[key])
                arr[sb, n:] = 0  # past the scene's particles: nothing (padding, or the rows no loop reaches)
            fld.from_numpy(arr)
        mat = to_host(s.material)  # B,cap
        for sb, st in states.items():
            n, _, piece, material, sweeps = prepared[id(st)]
            if material is not None:
                mat[sb, :n] = np.asarray(material, np.int32)
            else:  # keep the scene's materials; rows that were padding become core
                mat[sb, :n] = np.maximum(mat[sb, :n], 0)
            mat[sb, n:] = -1
            self.sweeps[sb] = list(sweeps)
            self.piece[sb, :n], self.piece[sb, n:] = piece, 0
        s.material.from_numpy(mat)
        s.Jp.from_numpy(np.linalg.det(to_host(s.F)).astype(np.float32))
        top = max(int(v[1]["body"].max(initial=0)) for v in prepared.values())
        self._loaded(scenes, top + 1)

    def _loaded(self, scenes, n_fields: int) -> None:
        """After particles were written into ``scenes`` (``_write``, ``restore_scene``): the scatter's visiting
        order, no pending push, at least ``n_fields`` velocity fields, no divergence flag, the knife off."""
        s = self.solver
        s.sort_by_cell(self.n, self.resort > 0)  # the scatter's order must cover exactly particles 0 .. n-1
        self.push_side[scenes] = 0
        s.n_fields[None] = max(int(s.n_fields[None]), n_fields)  # only grows: see _split
        s.bad_step.fill(NO_STEP)
        s.k_on.fill(0)
        self._set_frozen()

    def _need(self) -> MPMSolver:
        if self.solver is None:
            raise RuntimeError("no particles loaded: call reset(object) or set_state(...) first")
        return self.solver

"""Ice-cream scooping's scene and scripted episodes: block, spoon primitive per 2-D placement, chunks in the cup,
rewards (the spoon and cup colliders are physics: topocut.sim.spoon).

The block is a jittered lattice of the von Mises material (material 1, per-particle yield stress
``spoon.yield_stress``; damage and softening as for the food's skin; the chunk comes free because the
sided transfers keep material on either side of the shell apart, see topocut.sim.spoon).  Every placement in ``task.spoon.scoops`` (x, y offsets from the block centre) runs the
primitive of topocut.sim.spoon.scoop_keyframes; the tools' sided p2g, the solver's grid_op, the tools'
collider kernel and the sided g2p make one substep (the solver's own p2g / g2p once the spoon is away).

Chunk bookkeeping: when the spoon has lifted, the particles inside its bowl are chunk i (by
construction).  At the end, topology discovery labels the scene; the clusters whose centroid lies in
the cup are the scooped pieces, and each chunk should be one of them.  They are scored against one target
chunk per scoop (``chunk_targets``: the block's particles at rest inside the bowl's mid-sphere, a cap of
height ``depth + thickness / 2``) by topocut.tasks.scooping_reward (no stock or waste roles; spilled
material costs).
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from topocut.sim.spoon import SpoonPath, ToolColliders, scoop_keyframes


def block_particles(spoon, spacing: float, board_z: float, seed: int = 0, jitter: float = 0.25) -> np.ndarray:
    """Jittered lattice (N,3) filling the block spoon.block centred on spoon.block_center, on the board."""
    size = np.asarray(spoon.block, float)
    counts = np.maximum(np.round(size / spacing).astype(int), 1)
    g = np.stack(np.meshgrid(*[np.arange(c) for c in counts], indexing="ij"), -1).reshape(-1, 3)
    x = (g + 0.5) * spacing - np.array([size[0] / 2, size[1] / 2, 0.0])
    x += np.random.default_rng(seed).uniform(-jitter, jitter, x.shape) * spacing
    return (x + np.array([spoon.block_center[0], spoon.block_center[1], board_z])).astype(np.float32)


def bowl_cap(spoon) -> tuple[float, float]:
    """(radius R, height H) of the cap a scoop takes: the bowl's mid-sphere R = radius + thickness / 2, dipping
    H = depth + thickness / 2 below the top.  The shell splits the material at its mid-surface (the sided transfers
    give every particle below the rim a side of that sphere, topocut.sim.spoon), so the inner half of the rim's
    thickness pushes its material into the bowl."""
    return spoon.radius + spoon.thickness / 2, spoon.depth + spoon.thickness / 2


def cap_volume(radius: float, height: float) -> float:
    """Volume of a spherical cap, pi h^2 (3 r - h) / 3."""
    return float(np.pi * height * height * (3 * radius - height) / 3)


def chunk_targets(x0, spoon) -> list[np.ndarray]:
    """Target chunk of every scoop (list of (m_i,3)): the block's particles at rest x0 (N,3) that the bowl's
    mid-sphere encloses where scoop i starts its advance: a full bowl.

    No physics: the sphere sits where ``scoop_keyframes`` puts it (its centre ``radius - depth`` above the block's
    topmost particle, over the placement) and holds the cap ``bowl_cap``.  The advance does not enlarge it: the
    shell turns about its own centre, so its rim closes the cap under the material already inside, and the centre's
    2 cm of travel carries the closed bowl's content along rather than sweeping more in (measured, docs/tasks.md).
    The chunks are the scene's own particles, so the target has their density and jitter (a separate lattice
    would differ by its sampling alone: at n_grid 48 two samplings of one cap are up to d = 0.04 apart).  Caps of
    neighbouring placements may share a sliver (the default two share a 6 mm strip of the top): each target is
    still the full cap, the shape the bowl gives its content (the second chunk, measured, is nearer the full cap
    than the cap without the first's sliver, d 0.025 against 0.049 at n_grid 48).
    """
    x0 = np.asarray(x0, np.float32)
    return [x0[m] for m in chunk_masks(x0, spoon)]


def chunk_masks(x0, spoon) -> list[np.ndarray]:
    """(N,) bool per scoop: which particles of x0 (N,3) ``chunk_targets`` takes for it."""
    x0 = np.asarray(x0, np.float64)
    rad, _ = bowl_cap(spoon)
    top = float(x0[:, 2].max())  # as ScoopScene.scoop measures the block's top
    centres = [(spoon.block_center[0] + ox, spoon.block_center[1] + oy, top - spoon.depth + spoon.radius)
               for ox, oy in spoon.scoops]
    return [np.linalg.norm(x0 - np.asarray(c), axis=1) <= rad for c in centres]


def target_chunks(spoon, spacing: float, board_z: float, seed: int = 0) -> list[np.ndarray]:
    """``chunk_targets`` of the block ``ScoopScene`` loads with this seed (the task's goal, one chunk per scoop)."""
    return chunk_targets(block_particles(spoon, spacing, board_z, seed), spoon)


def in_cup(points, spoon, board_z: float) -> np.ndarray:
    """(N,) bool: over the cup's inner disc, below its rim plus a bowl's diameter (chunks resting in the cup heap
    above the rim: a bowlful stands ~7 cm tall and the second lands on the first)."""
    p = np.asarray(points, float)
    rho = np.linalg.norm(p[:, :2] - np.asarray(spoon.cup_center, float), axis=1)
    return (rho < spoon.cup_radius) & (p[:, 2] < board_z + spoon.cup_height + 2 * spoon.radius)


def on_block(points, spoon, board_z: float, margin: float) -> np.ndarray:
    """(N,) bool: within the block's box grown by margin (the rest of the block, dented and bulged by the scoops)."""
    p = np.asarray(points, float)
    half = np.asarray(spoon.block[:2], float) / 2 + margin
    return (np.abs(p[:, :2] - np.asarray(spoon.block_center, float)) <= half).all(1) & \
        (p[:, 2] <= board_z + spoon.block[2] + margin)


def spilled_mask(x, labels, spoon, board_z: float, margin: float) -> np.ndarray:
    """(N,) bool: particles of x (N,3) whose cluster (labels (N,), -1: none) has its centroid neither over the cup
    (``in_cup``) nor on the block (``on_block`` with margin); a particle without a cluster by its own place.

    Clusters, not particles: the advance bulges the block's face out by more than a cell (169 particles at n_grid 48,
    still the block's cluster), and a chunk in the cup may rest an edge on the rim."""
    x, lab = np.asarray(x, float), np.asarray(labels)
    ids, where = np.unique(lab, return_inverse=True)
    where = where.reshape(-1)
    cent = np.array([x[lab == c].mean(0) for c in ids]).reshape(-1, 3)  # C,3
    keep = in_cup(cent, spoon, board_z) | on_block(cent, spoon, board_z, margin)  # C,
    own = in_cup(x, spoon, board_z) | on_block(x, spoon, board_z, margin)  # N,
    return ~np.where(lab >= 0, keep[where], own)


def tool_points(spoon, c, a, board_z: float, n: int = 400) -> tuple[np.ndarray, np.ndarray]:
    """Points on the spoon's bowl and the cup wall, for pictures: (spoon (k,3), cup (m,3))."""
    rng = np.random.default_rng(0)
    d = rng.standard_normal((n * 3, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = d[d @ a <= spoon.opening][:n]
    th = np.linspace(0, 2 * np.pi, 90, endpoint=False)
    z = np.linspace(board_z, board_z + spoon.cup_height, 8)
    ring = np.stack([np.cos(th), np.sin(th)], -1) * (spoon.cup_radius + spoon.cup_wall / 2) + spoon.cup_center
    cup = np.concatenate([np.column_stack([ring, np.full(len(ring), zz)]) for zz in z])
    return c + spoon.radius * d, cup


class ScoopScene:
    """One block, the spoon and the cup in a one-scene solver."""

    def __init__(self, sim, spoon, seed: int = 0, sided: bool = True):
        from topocut.sim import CuttingEnv

        self.spoon, self.sided = spoon, sided
        self.env = CuttingEnv(dataclasses.replace(sim, yield_stress=spoon.yield_stress, fields=1), batch_size=1)
        x = block_particles(spoon, self.env.cfg.spacing, self.env.cfg.board_z, seed)
        self.env.load_particles(x, np.ones(len(x), np.int32))
        self.tools = ToolColliders(self.env.solver, spoon)
        self.chunk = np.zeros(len(x), np.int32)  # 0 = block, i + 1 = chunk of scoop i
        self.lifted: list[np.ndarray] = []  # N,3 per scoop: the particles when the spoon has lifted
        self.lifted_J: list[np.ndarray] = []  # N, per scoop: their det F then
        self.t = 0.0

    @property
    def x(self) -> np.ndarray:  # N,3
        return self.env.solver.x.to_numpy()[0, :self.env.n]

    @property
    def J(self) -> np.ndarray:  # N, det F: the material's volume change (1 at rest)
        return self.env.solver.Jp.to_numpy()[0, :self.env.n]

    def run(self, path: SpoonPath | None, until: float, on_phase=None) -> None:
        """Advance to time ``until`` with the spoon following path (None: spoon away); on_phase(name) at changes."""
        env, s = self.env, self.env.solver
        self.tools.on[None] = int(path is not None)
        phase = path.phase(self.t) if path is not None else ""
        while self.t < until:
            if path is not None:
                c, a, vc, om = path.pose(self.t)
                self.tools.set_pose(np.stack([c, a, vc, om])[None])
                p = path.phase(self.t)
                if p != phase and on_phase is not None:
                    on_phase(phase, c, a)
                phase = p
            k = env.step_count
            sided = self.sided and path is not None
            if sided:
                self.tools.p2g_sided(env.n, k)
            else:
                s.p2g(env.n, k)
            s.grid_op(self.t, 0)
            self.tools.collide_tools()
            if sided:
                self.tools.g2p_sided(env.n, k)
            else:
                s.g2p(env.n, k, self.t)
            env.step_count += 1
            self.t += env.dt
            if env.step_count % env.cfg.tuning.check_every == 0:
                env._check()
        env._check()

    def scoop(self, i: int, place_xy, on_phase=None, **primitive) -> dict:
        """Scoop i at absolute placement (x, y); chunk i = the particles in the bowl once it has lifted.
        primitive: scoop_keyframes' depth / pour_dx (a wrong scoop; the task's own uses the defaults)."""
        top = float(self.x[self.chunk == 0, 2].max())  # the block's top (earlier chunks may heap higher in the cup)
        path = scoop_keyframes(self.spoon, place_xy, top, self.env.cfg.board_z + self.spoon.cup_height, t0=self.t,
                               **primitive)
        lift_end = next(k.t for k in path.keys if k.phase == "lift")
        self.run(path, lift_end, on_phase)
        c, a, _, _ = path.pose(self.t)
        d = self.x - c
        held = (np.linalg.norm(d, axis=1) < self.spoon.radius + 0.5 * self.env.cfg.dx) & (d @ a < self.spoon.opening * self.spoon.radius)
        self.chunk[held & (self.chunk == 0)] = i + 1
        self.lifted.append(self.x)  # N,3: the scene as the bowl holds chunk i (its shape before the pour)
        self.lifted_J.append(self.J)
        self.run(path, path.duration, on_phase)
        return {"held": int(held.sum()), "keyframes": [(k.phase, k.t) for k in path.keys]}


def scoop_episode(sim, task, topology=None, frames_dir=None, seed: int = 0, reward_cfg=None, on_scoop=None,
                  primitive: dict | None = None) -> dict:
    """All scoops of task.spoon.scoops, then settle; clusters, chunks in the cup, the score, frames.

    primitive: keyword arguments of scoop_keyframes for every scoop (depth, pour_dx: a wrong scoop); the targets are
    the task's all the same (``chunk_targets`` of the block at rest)."""
    from topocut.sim.render import render_particles

    t0 = time.perf_counter()
    spoon = task.spoon
    scene = ScoopScene(sim, spoon, seed)
    bz = scene.env.cfg.board_z
    targets = chunk_targets(scene.x, spoon)  # before any physics: the goal is what the bowl's geometry holds
    frames, arrays, records = [], {"x_0": scene.x, "spacing": np.float64(scene.env.cfg.spacing)}, []
    limits = ((spoon.block_center[0] - 0.1, spoon.block_center[1] - 0.15, bz),
              (spoon.cup_center[0] + 0.1, spoon.block_center[1] + 0.15, bz + 0.25))

    def draw(name, c=None, a=None, labels=None):
        if frames_dir is None:
            return
        lab = scene.chunk if labels is None else np.asarray(labels) + 1
        pts, col = [scene.x], [lab]
        if c is not None:
            sp, cup = tool_points(spoon, c, a, bz)
            pts += [sp, cup]
            col += [np.full(len(sp), -1), np.full(len(cup), 6)]
        else:
            _, cup = tool_points(spoon, np.zeros(3), np.array([0, 0, 1.0]), bz)
            pts.append(cup)
            col.append(np.full(len(cup), 6))
        frames.append(render_particles(np.concatenate(pts), np.concatenate(col), frames_dir / f"{len(frames):02d}_{name}.png",
                                       title=name, view=(20.0, -70.0), size=3, limits=limits))

    draw("start")
    for i, off in enumerate(spoon.scoops):
        place = (spoon.block_center[0] + off[0], spoon.block_center[1] + off[1])
        rec = scene.scoop(i, place, on_phase=lambda ph, c, a, i=i: draw(f"scoop{i + 1}_{ph}", c, a)
                          if ph in ("advance", "tilt") else None, **(primitive or {}))
        rec["chunk_in_cup"] = float(in_cup(scene.x[scene.chunk == i + 1], spoon, bz).mean()) if rec["held"] else 0.0
        records.append(rec)
        arrays[f"x_{i + 1}"], arrays[f"x_lift_{i + 1}"], arrays[f"J_lift_{i + 1}"] = scene.x, scene.lifted[i], \
            scene.lifted_J[i]
        if on_scoop is not None:
            on_scoop(i, {"chunks_in_cup": i + 1, **rec})
    scene.run(None, scene.t + scene.env.cfg.settle_time)
    out = score_scene(scene, targets, topology, reward_cfg)
    draw("final (clusters)", labels=out["arrays"]["labels"])
    arrays.update(out.pop("arrays"))
    return {"scoops": records, **out, "particles": int(len(scene.chunk)), "substeps": int(scene.env.step_count),
            "seconds": time.perf_counter() - t0, "arrays": arrays, "frames": frames}


def score_scene(scene: ScoopScene, targets, topology=None, reward_cfg=None) -> dict:
    """Discovery, the cup's pieces, spilled particles and the score (topocut.tasks.scooping_reward) of a settled
    scene; which cup cluster holds each chunk (by construction against discovery)."""
    from topocut.tasks.scooping_reward import scooping_reward
    from topocut.topology import discover

    spoon, bz = scene.spoon, scene.env.cfg.board_z
    x = scene.x
    st = scene.env.state()
    topo = discover(x, st.damage[0], None, cfg=topology, device="cuda" if scene.env.cfg.arch == "cuda" else "cpu")
    lab = np.asarray(topo.labels)
    ids = [c for c in np.unique(lab) if c >= 0]
    cup_ids = [c for c in ids if in_cup(x[lab == c].mean(0, keepdims=True), spoon, bz)[0]]
    pieces = [x[lab == c] for c in cup_ids]
    spilled = spilled_mask(x, lab, spoon, bz, scene.env.cfg.dx)
    res = scooping_reward(pieces, targets, int(spilled.sum()), reward_cfg, spacing=scene.env.cfg.spacing)
    chunk_cluster = []
    for i in range(len(spoon.scoops)):
        m = (scene.chunk == i + 1) & np.isin(lab, cup_ids)
        vals, cnt = np.unique(lab[m], return_counts=True)
        chunk_cluster.append((int(vals[cnt.argmax()]), float(cnt.max() / max((scene.chunk == i + 1).sum(), 1)))
                             if len(vals) else (-1, 0.0))
    distinct = len({c for c, _ in chunk_cluster if c >= 0}) == len(spoon.scoops)
    return {"clusters": int(topo.num_clusters), "chunks_in_cup": len(cup_ids),
            "cup_piece_sizes": [int(len(p)) for p in pieces], "chunk_clusters": chunk_cluster,
            "chunks_distinct": bool(distinct), "reward": res.total, "per_chunk": res.per_chunk.tolist(),
            "distances": res.distances.tolist(), "spilled": res.spilled, "spill_weight": res.spill_weight,
            "target_points": [int(len(t)) for t in targets],
            "arrays": {"x": x, "J": scene.J, "labels": lab, "chunk": scene.chunk, "damage": st.damage[0], "spilled": spilled,
                       **{f"target_{i}": t for i, t in enumerate(targets)}}}

"""The primitives after a cut: ``push`` (slide the piece just cut off aside; docs/sim.md, "Push primitive") and
``turn`` (pick pieces up, turn them, lay them down; "Turn primitive").  Methods of CuttingEnv (env.py), which
holds the scenes, the knife's arming and the stepping they use."""
from __future__ import annotations

import math

import numpy as np

from topocut.sim import pieces as P
from topocut.sim.runtime import to_host


def turned_positions(p: np.ndarray, turn, cfg) -> np.ndarray:
    """Where ``turn`` lays particles p (n,3): x <- R (x - c) + target about their current centroid c, lowered or
    raised so that the lowest rests half a cell above the board (``Primitives.turn``; the ideal execution of a
    goal's steps, topocut.tasks.ideal, uses the same rule)."""
    p = np.asarray(p, np.float64)
    q = (p - p.mean(0)) @ turn.rotation().astype(np.float64).T + np.asarray(turn.target, np.float64)
    q[:, 2] += cfg.board_z + 0.5 * cfg.dx - q[:, 2].min()
    return q


def nearest_piece(x: np.ndarray, piece: np.ndarray, center) -> int:
    """The piece label whose centroid lies nearest ``center`` (the piece a Turn picks up)."""
    cnt = np.bincount(piece)
    cen = np.stack([np.bincount(piece, x[:, d], minlength=len(cnt)) for d in range(3)], -1) / np.maximum(cnt, 1)[:, None]
    dist = np.where(cnt > 0, np.linalg.norm(cen - np.asarray(center, np.float64), axis=1), np.inf)
    return int(np.argmin(dist))


class TurnRefused(ValueError):
    """``turn`` cannot lay the pieces where asked (they would leave the simulation box)."""


class Primitives:
    def turn(self, turn, select: np.ndarray | None = None) -> np.ndarray:
        """Pick pieces up, turn them rigidly and lay them on the board (docs/tasks.md#turn-primitive).

        ``turn`` is a topocut.tasks.Turn (rotation about a horizontal axis by an angle, a target centroid) for
        every scene, or a list of B (a Turn or None) for scenes of different episodes: a None scene is left
        alone and sits the settling out frozen, as it would alone.  ``select`` (N,) or (B,N) bool names the
        particles; by default, per scene, the piece (``piece`` label) whose centroid is nearest the turn's
        ``center``.  The selected particles move as one rigid body about their *current* centroid:
        x <- R (x - c) + target, lowered or raised so their lowest particle rests half a cell above the board;
        v <- 0, F <- R F R^T, C <- R C R^T (a rotated elastic state).  The turned scenes then settle
        sim.turn_settle_time seconds.  Piece labels stay; velocity fields are coloured anew for the new neighbours;
        the scene's sweeps are cleared (the knife has not cut since).  A turn the box cannot hold raises
        TurnRefused; with a list of turns that scene is left as it was and named in ``turn_refused`` instead,
        the others go on.  Returns the (B,N) mask of the particles turned."""
        cfg, s, n = self.cfg, self._need(), self.n
        per_scene = isinstance(turn, (list, tuple))
        turns = list(turn) if per_scene else [turn] * self.B
        if len(turns) != self.B:
            raise ValueError(f"turn got {len(turns)} turns for batch_size={self.B}")
        self.turn_refused = [None] * self.B
        counts = self.counts  # B: scene b's particles are rows :counts[b] (the rest pad)
        x = to_host(s.x)  # B,cap,3
        mask = np.zeros((self.B, n), bool)
        if select is not None:
            mask[:] = np.broadcast_to(np.asarray(select, bool), (self.B, n))
        for b in range(self.B):
            if turns[b] is None or self.dead[b]:
                mask[b] = False
            elif select is None:
                lab = self.piece[b, :counts[b]]
                mask[b, :counts[b]] = lab == nearest_piece(x[b, :counts[b]].astype(np.float64), lab, turns[b].center)
        mask &= np.arange(n)[None] < counts[:, None]  # never the padding
        F, C, v = to_host(s.F), to_host(s.C), to_host(s.v)
        body = to_host(s.body)
        lo, hi = 2.5 * cfg.dx, 1.0 - 2.5 * cfg.dx  # the solver's boundary band
        turned = np.zeros(self.B, bool)
        for b in range(self.B):
            sel = np.flatnonzero(mask[b])
            if not len(sel):
                continue
            R = turns[b].rotation().astype(np.float64)
            q = turned_positions(x[b, sel], turns[b], cfg)
            if q[:, :2].min() < lo or q.max() > hi:  # (z rests on the board, above the boundary band)
                msg = (f"turn: the turned pieces would leave the simulation box [{lo:.3f}, {hi:.3f}] "
                       f"(target {tuple(np.round(np.asarray(turns[b].target), 3))}); move turn.target")
                if not per_scene:
                    raise TurnRefused(msg)
                self.turn_refused[b] = msg
                mask[b] = False
                continue
            x[b, sel] = q
            v[b, sel] = 0
            F[b, sel] = R @ F[b, sel] @ R.T
            C[b, sel] = R @ C[b, sel] @ R.T
            c = counts[b]
            body[b, :c] = P.colour(x[b, :c].astype(np.float64), self.piece[b, :c], cfg.n_grid, cfg.fields)[0]
            self.sweeps[b] = []
            turned[b] = True
        for fld, arr in ((s.x, x), (s.v, v), (s.F, F), (s.C, C), (s.body, body)):
            fld.from_numpy(arr.astype(np.float32) if arr.dtype != np.int32 else arr)
        field_side = s.field_side.to_numpy().reshape(self.B, -1)
        field_side[turned] = 0  # the turned scenes' fields were coloured anew: no blade side
        s.field_side.from_numpy(field_side.reshape(-1))
        s.n_fields[None] = max(int(s.n_fields[None]), int(body[:, :n].max()) + 1)
        s.sort_by_cell(n, self.resort > 0)
        self.push_side[turned] = 0
        if not per_scene:
            self.simulate(cfg.substeps(cfg.turn_settle_time))
        elif turned.any():
            self._set_frozen(np.where(turned, 2 ** 30, self.step_count))  # the others sit it out
            try:
                self.simulate(cfg.substeps(cfg.turn_settle_time))
            finally:
                self._set_frozen()
        return mask

    def push(self, scenes=None) -> None:
        """After a cut, per sim.push_mode (docs/sim.md); then the pieces settle for sim.settle_time seconds.

        ``scenes`` (B,) bool: push only these (None: all); the others sit the push and its settling out frozen,
        as scenes of episodes whose task does not push would alone.

        'separate': the blade, still standing where it cut, slides sideways along its normal (horizontally)
        by sim.push_distance over sim.push_time seconds, starting and stopping smoothly, towards the material
        the cut separated from the rest (``push_side``: the smaller side of the split pieces): a cook sliding
        a slice aside with the knife's flat.  Each velocity field is pushed only from its own side, so the
        rest is not dragged along.  Scenes whose cut separated nothing are not pushed."""
        cfg, s = self.cfg, self._need()
        if cfg.push_mode == "none":
            return
        sel = np.ones(self.B, bool) if scenes is None else np.asarray(scenes, bool).reshape(self.B).copy()
        sel &= ~self.dead
        if not sel.any():
            return
        self.push_side[~sel] = 0  # an unselected scene is not pushed
        hold = np.where(sel, 2 ** 30, self.step_count)  # frozen_at: the unselected scenes from now on
        if cfg.push_mode == "separate" and self.push_side.any():
            o, u, w, nrm, d = (np.zeros((self.B, 3)) for _ in range(5))
            for b, sw in enumerate(self.sweeps):
                if sw and self.push_side[b]:
                    o_b, u[b], w[b], nrm[b] = sw[-1].as_arrays()
                    o[b] = o_b + w[b] * sw[-1].depth  # where the edge stopped
                    h = nrm[b] * [1, 1, 0]
                    d[b] = self.push_side[b] * h / max(np.linalg.norm(h), 1e-9)
            half = [cfg.knife_half_length, cfg.knife_height / 2, cfg.knife_half_thickness]
            self._arm_knife(o, u, w, nrm, [half] * self.B, cfg.push_distance, cfg.push_distance / max(cfg.push_time, 1e-9),
                            0.0, direction=d, target=0.0, smooth=1, on=self.push_side != 0, hold=self.push_side)
            # a scene with nothing to push sits the push out frozen, as it would alone (no push phase at all)
            self._set_frozen(np.where(self.push_side != 0, 2 ** 30, self.step_count))
            try:
                self.simulate(cfg.substeps(cfg.push_time))
            finally:
                s.k_on.fill(0)
                self._set_frozen()
        elif cfg.push_mode == "press":  # a flat plate (the knife box laid horizontally) pressing down lightly
            xs = [xb[:c] for xb, c in zip(to_host(s.x), self.counts)]  # B x (n_b,3)
            o = np.array([[xb[:, 0].mean(), xb[:, 1].mean(), xb[:, 2].max() + cfg.knife_clearance] for xb in xs])
            depth = np.full(self.B, cfg.knife_clearance + cfg.press_depth)
            tile = lambda v: np.tile(np.asarray(v, np.float32), (self.B, 1))  # noqa: E731
            self._arm_knife(o, tile([1, 0, 0]), tile([0, 0, -1]), tile([0, 1, 0]), tile([0.4, 0.02, 0.4]),
                            depth, cfg.press_speed, 0.0, on=sel.astype(np.int32))
            self._set_frozen(hold)
            try:
                self.simulate(int(math.ceil(depth.max() / (cfg.press_speed * self.dt))) + cfg.substeps(cfg.push_time),
                              contact=1)
            finally:
                s.k_on.fill(0)
                self._set_frozen()
        self.push_side[:] = 0
        self._set_frozen(hold)
        try:
            self.simulate(cfg.substeps(cfg.settle_time))
        finally:
            self._set_frozen()

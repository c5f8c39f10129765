"""The primitives after a cut: ``push`` (slide the piece just cut off aside; docs/sim.md, "Push primitive") and
``turn`` (pick pieces up, turn them, lay them down; "Turn primitive").  Methods of CuttingEnv (env.py), which
holds the scenes, the knife's arming and the stepping they use."""
from __future__ import annotations

import math

import numpy as np

from topocut.sim import pieces as P


class TurnRefused(ValueError):
    """``turn`` cannot lay the pieces where asked (they would leave the simulation box)."""


class Primitives:
    def turn(self, turn, select: np.ndarray | None = None) -> np.ndarray:
        """Pick pieces up, turn them rigidly and lay them on the board (docs/tasks.md#turn-primitive).

        ``turn`` is a topocut.tasks.Turn (rotation about a horizontal axis by an angle, a target centroid);
        ``select`` (N,) or (B,N) bool names the particles; by default, per scene, the piece (``piece`` label)
        whose centroid is nearest ``turn.center``.  The selected particles move as one rigid body about their
        *current* centroid: x <- R (x - c) + target, lowered or raised so their lowest particle rests half a
        cell above the board; v <- 0, F <- R F R^T, C <- R C R^T (a rotated elastic state).  Every scene then
        settles sim.settle_time seconds.  Piece labels stay; velocity fields are coloured anew for the new
        neighbours; the scene's sweeps are cleared (the knife has not cut since).  Returns the (B,N) mask."""
        cfg, s, n = self.cfg, self._need(), self.n
        x = s.x.to_numpy()  # B,cap,3
        if select is None:
            mask = np.zeros((self.B, n), bool)
            c_goal = np.asarray(turn.center, np.float64)
            for b in range(self.B):
                lab = self.piece[b]
                cnt = np.bincount(lab)
                cen = np.stack([np.bincount(lab, x[b, :n, d], minlength=len(cnt)) for d in range(3)], -1)
                cen = cen / np.maximum(cnt, 1)[:, None]
                dist = np.where(cnt > 0, np.linalg.norm(cen - c_goal, axis=1), np.inf)
                mask[b] = lab == int(np.argmin(dist))
        else:
            mask = np.broadcast_to(np.asarray(select, bool), (self.B, n)).copy()
        R = turn.rotation().astype(np.float64)
        target = np.asarray(turn.target, np.float64)
        F, C, v = s.F.to_numpy(), s.C.to_numpy(), s.v.to_numpy()
        body = s.body.to_numpy()
        lo, hi = 2.5 * cfg.dx, 1.0 - 2.5 * cfg.dx  # the solver's boundary band
        for b in range(self.B):
            sel = np.flatnonzero(mask[b])
            if not len(sel):
                continue
            p = x[b, sel].astype(np.float64)
            q = (p - p.mean(0)) @ R.T + target
            q[:, 2] += cfg.board_z + 0.5 * cfg.dx - q[:, 2].min()  # rest half a cell above the board
            if q[:, :2].min() < lo or q.max() > hi:  # (z rests on the board, above the boundary band)
                raise TurnRefused(f"turn: the turned pieces would leave the simulation box [{lo:.3f}, {hi:.3f}] "
                                 f"(target {tuple(np.round(target, 3))}); move turn.target")
            x[b, sel] = q
            v[b, sel] = 0
            F[b, sel] = R @ F[b, sel] @ R.T
            C[b, sel] = R @ C[b, sel] @ R.T
            body[b, :n] = P.colour(x[b, :n].astype(np.float64), self.piece[b], cfg.n_grid, cfg.fields)[0]
            self.sweeps[b] = []
        for fld, arr in ((s.x, x), (s.v, v), (s.F, F), (s.C, C), (s.body, body)):
            fld.from_numpy(arr.astype(np.float32) if arr.dtype != np.int32 else arr)
        s.field_side.fill(0)
        s.n_fields[None] = max(int(s.n_fields[None]), int(body[:, :n].max()) + 1)
        s.sort_by_cell(n, self.resort > 0)
        self.push_side[:] = 0
        self.simulate(cfg.substeps(cfg.settle_time))
        return mask

    def push(self) -> None:
        """After a cut, per sim.push_mode (docs/sim.md); then the pieces settle for sim.settle_time seconds.

        'separate': the blade, still standing where it cut, slides sideways along its normal (horizontally)
        by sim.push_distance over sim.push_time seconds, starting and stopping smoothly, towards the material
        the cut separated from the rest (``push_side``: the smaller side of the split pieces): a cook sliding
        a slice aside with the knife's flat.  Each velocity field is pushed only from its own side, so the
        rest is not dragged along.  Scenes whose cut separated nothing are not pushed."""
        cfg, s = self.cfg, self._need()
        if cfg.push_mode == "none":
            return
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
            try:
                self.simulate(cfg.substeps(cfg.push_time))
            finally:
                s.k_on.fill(0)
        elif cfg.push_mode == "press":  # a flat plate (the knife box laid horizontally) pressing down lightly
            x = s.x.to_numpy()[:, :self.n]
            top = x[:, :, 2].max(1)
            o = np.stack([x[:, :, 0].mean(1), x[:, :, 1].mean(1), top + cfg.knife_clearance], -1)
            depth = np.full(self.B, cfg.knife_clearance + cfg.press_depth)
            tile = lambda v: np.tile(np.asarray(v, np.float32), (self.B, 1))  # noqa: E731
            self._arm_knife(o, tile([1, 0, 0]), tile([0, 0, -1]), tile([0, 1, 0]), tile([0.4, 0.02, 0.4]),
                            depth, cfg.press_speed, 0.0)
            try:
                self.simulate(int(math.ceil(depth.max() / (cfg.press_speed * self.dt))) + cfg.substeps(cfg.push_time),
                              contact=1)
            finally:
                s.k_on.fill(0)
        self.push_side[:] = 0
        self.simulate(cfg.substeps(cfg.settle_time))

"""A goal's own steps executed on the ideal particle set, with no physics: the pieces the plan makes.

``execute(points, steps, sim_cfg)`` runs the ``Cut`` and ``Turn`` steps of ``Goal.steps`` the way the simulator
separates and moves material, without the forces: a cut splits the pieces its blade's swept surface crosses
(``topocut.sim.pieces.blade_sweep`` and ``split``, the simulator's own rule), a turn moves the piece nearest its
centre rigidly (``topocut.sim.primitives.turned_positions``, ``nearest_piece``).  No push, no settling, no
deformation.  The result is what a perfect cook's execution of the plan leaves on the board, so the goal is
defined by it (docs/tasks.md#goals-are-what-their-steps-make):

* goal pieces: the pieces lying in a goal cell (a slab, a stick, a die), one per connected piece (a donut slab
  through the hole is two);
* planned offcuts: every other piece but the largest (a die's rims, a stick's edge band);
* the rest: the largest piece that is no goal piece (the uncut stock).

``Anchor``: for each cut, particles of the piece it splits, at their initial and their planned positions just
before the cut; the oracle policy (topocut.planning.oracle) finds where that piece has moved since (pushes,
settling) and moves the plane with it.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

ANCHOR_POINTS = 256  # particles per cut the oracle tracks (those nearest the plane on the piece it splits)
MIN_GOAL_SHARE = 0.2  # a piece of a goal cell with less of the cell than this is an offcut (a corner sliver)
# a cut all of whose cut-off parts hold less than this share of a full goal cell only trims a sliver about one
# particle layer thick (a die is 7.7 layers at 128^3 with 3 cm, 6.4 at 64^3 with 5 cm): a cook would not make it,
# the simulator smears it and discovery takes one under topology.min_piece_particles for a chip of its neighbour
# (dice / steak at 128^3: chops trimming 17-36 particles off 500-particle sticks, R 0; docs/tasks.md)
MIN_CUT_SHARE = 0.15


@dataclass
class Anchor:
    """Where the pieces a cut splits were planned to be: initial positions (m,3), positions before the cut, which
    of them the cut leaves on the +n side of its plane (m,) bool, their indices in the planned particle set (m,),
    the piece each lies in before the cut (m,) and whether it ends in a goal piece (m,) bool (``Task.make_goal``
    sets ``goal`` once the roles are known)."""

    initial: np.ndarray
    planned: np.ndarray
    side: np.ndarray = None
    index: np.ndarray = None
    piece: np.ndarray = None
    goal: np.ndarray = None


@dataclass
class IdealRun:
    x: np.ndarray  # N,3 positions after the last step
    piece: np.ndarray  # N, piece labels after the last step (0..P-1)
    anchors: list = field(default_factory=list)  # one Anchor per Cut
    pieces_after_cut: list = field(default_factory=list)  # the number of pieces after each Cut
    splits: list = field(default_factory=list)  # per Cut: whether it separated anything
    cut_off: list = field(default_factory=list)  # per Cut: the largest part it cut off a piece (0: none), particles


def sim_config_for(spacing: float, board_z: float):
    """A SimConfig whose lattice spacing is ``spacing`` (half a cell) and whose board is at ``board_z``."""
    from topocut.sim.config import SimConfig

    return SimConfig(n_grid=max(8, int(round(0.5 / spacing))), particle_spacing=float(spacing), board_z=float(board_z))


def replay(x: np.ndarray, steps, sim_cfg):
    """``steps`` (Cut / Turn) on the ideal material ``x`` (N,3 float64, moved in place by the turns): yields, for
    each Cut, (the positions when it starts (N,3), the pieces before it (N,), the Cut, the pieces after it (N,))."""
    from topocut.sim import pieces as P
    from topocut.sim.primitives import nearest_piece, turned_positions

    piece = np.zeros(len(x), np.int32)
    pairs = P.bonds(x, sim_cfg.spacing)  # rigid moves keep every bond within a piece: one search serves all steps
    for step in steps:
        if getattr(step, "kind", "cut") == "turn":
            sel = piece == nearest_piece(x, piece, step.center)
            x[sel] = turned_positions(x[sel], step, sim_cfg)
            continue
        sweep, _, _ = P.blade_sweep(step.action, x, sim_cfg)
        after = P.split(x, piece, sweep, sim_cfg.spacing, pairs)
        yield x, piece, step, after
        piece = after


def execute(points: np.ndarray, steps, sim_cfg) -> IdealRun:
    """Run ``steps`` (Cut / Turn) on ``points`` (N,3) without physics (module docstring)."""
    x0 = np.asarray(points, np.float64)
    x = x0.copy()
    run = IdealRun(x, np.zeros(len(x), np.int32))
    for _, piece, step, after in replay(x, steps, sim_cfg):
        run.anchors.append(_anchor(x0, x, piece, after, step.action))
        run.splits.append(int(after.max()) > int(piece.max()))
        run.cut_off.append(_largest_cut_off(piece, after))
        run.pieces_after_cut.append(int(after.max()) + 1)
        run.piece = after
    run.x = x
    return run


def _largest_cut_off(before: np.ndarray, after: np.ndarray) -> int:
    """The largest part a cut took off a piece: of each piece it split, every part but the largest (particles)."""
    pairs, n = np.unique(np.stack([before, after]), axis=1, return_counts=True)  # (parent, part) and its size
    best = 0
    for p in np.unique(pairs[0]):
        parts = np.sort(n[pairs[0] == p])
        if len(parts) > 1:
            best = max(best, int(parts[-2]))
    return best


def effective_steps(points: np.ndarray, steps, sim_cfg, min_cut_off: int = 0) -> tuple[list, IdealRun]:
    """``steps`` without the cuts that separate nothing on the ideal material (a band edge planned past the
    material's end: a cook would not make it, and in the simulator it only presses on a piece) and without those
    that only trim a sliver (every part they cut off holds fewer than ``min_cut_off`` particles), and the ideal
    run of what is left.  Leaving a trim out leaves its sliver on its neighbour, which the goal then holds."""
    run = execute(points, steps, sim_cfg)
    useful = [s and c >= min_cut_off for s, c in zip(run.splits, run.cut_off)]
    if all(useful):
        return list(steps), run
    out, k = [], 0
    for step in steps:
        if getattr(step, "kind", "cut") != "turn":
            k += 1
            if not useful[k - 1]:
                continue
        out.append(step)
    while out and getattr(out[-1], "kind", "cut") == "turn":
        out.pop()
    return out, execute(points, out, sim_cfg)


def push_conflicts(points: np.ndarray, steps, sim_cfg, pairs=None) -> int:
    """How many of the plan's cuts split a piece that an earlier cut's push slid aside.

    After each cut the simulator's push slides the cut-off side (``topocut.sim.pieces.cut_off_side``: of the pieces
    the cut split, the side with fewer particles) a couple of centimetres along the blade's normal; a Turn lays
    its piece where the plan says, which undoes that.  A later plane that crosses pushed material finds it moved
    (and, when the plane crosses several pieces, each moved differently: no one plane cuts them all where the
    plan meant).  A push along a direction square to the later plane moves nothing across it, so only
    displacement along the later plane's normal counts."""
    from topocut.sim import pieces as P
    from topocut.sim.primitives import nearest_piece, turned_positions

    x = np.asarray(points, np.float64).copy()
    pairs = P.bonds(x, sim_cfg.spacing) if pairs is None else pairs
    piece = np.zeros(len(x), np.int32)
    moved = np.zeros((len(x), 3))  # N,3 each particle's pushes so far, in push lengths
    conflicts = 0
    for step in steps:
        if getattr(step, "kind", "cut") == "turn":
            sel = piece == nearest_piece(x, piece, step.center)
            x[sel] = turned_positions(x[sel], step, sim_cfg)
            moved[sel] = 0.0
            continue
        sweep, _, _ = P.blade_sweep(step.action, x, sim_cfg)
        after = P.split(x, piece, sweep, sim_cfg.spacing, pairs)
        parents = [p for p in np.unique(piece) if len(np.unique(after[piece == p])) > 1]
        cut = np.isin(piece, parents)
        conflicts += int(cut.any() and np.abs(moved[cut] @ step.action.normal).max() > 0.1)
        side = P.cut_off_side(x, piece, after, sweep)
        if side:
            o, _, _, n = sweep.as_arrays()
            h = np.array([n[0], n[1], 0.0]) / max(float(np.hypot(n[0], n[1])), 1e-9)  # the push is horizontal
            moved[cut & ((((x - o) @ n) >= 0) == (side > 0))] += side * h
        piece = after
    return conflicts


def push_safe(points: np.ndarray, steps, sim_cfg) -> list:
    """``steps`` with each run of parallel cuts (consecutive Cut steps, normals parallel) in the order, as planned
    or reversed, whose pushes move the least material a later cut crosses (``push_conflicts``): a cook slices
    from the end, sliding each slice away from where the knife goes next (docs/tasks.md#pushes)."""
    from topocut.sim import pieces as P

    steps = list(steps)
    runs, i = [], 0
    while i < len(steps):
        j = i
        while (j + 1 < len(steps) and all(getattr(s, "kind", "cut") == "cut" for s in steps[i:j + 2])
               and abs(float(np.dot(steps[i].action.normal, steps[j + 1].action.normal))) > 0.999):
            j += 1
        if j > i:
            runs.append((i, j + 1))
        i = j + 1
    if not runs:
        return steps
    pairs = P.bonds(np.asarray(points, np.float64), sim_cfg.spacing)
    best = push_conflicts(points, steps, sim_cfg, pairs)
    for a, b in runs:
        if best == 0:
            break
        cand = steps[:a] + steps[a:b][::-1] + steps[b:]
        c = push_conflicts(points, cand, sim_cfg, pairs)
        if c < best:
            steps, best = cand, c
    return steps


def _anchor(x0, x, before, after, action) -> Anchor:
    """The particles nearest the cut's plane on the pieces it splits (all pieces it touches if it splits none),
    half of them on each side."""
    split = [p for p in np.unique(before) if len(np.unique(after[before == p])) > 1]
    n, q = action.normal, action.plane_point()
    sd = (x - q) @ n
    cand = np.flatnonzero(np.isin(before, split)) if split else np.arange(len(x))
    keep = []
    for on_plus in (True, False):
        c = cand[(sd[cand] > 0) == on_plus]
        keep.append(c[np.argsort(np.abs(sd[c]), kind="stable")[:ANCHOR_POINTS // 2]])
    keep = np.concatenate(keep)
    return Anchor(x0[keep].astype(np.float32), x[keep].astype(np.float32), sd[keep] > 0, keep, before[keep])


def roles(piece: np.ndarray, cells: np.ndarray, min_points: int = 32, fallback: int = 8):
    """Split the executed pieces into goal pieces and the rest: (goal piece labels [p], offcut labels [p],
    rest label or None).  A piece is a goal piece when most of its particles lie in one goal cell (``cells``
    (N,), 0 = none), it holds at least MIN_GOAL_SHARE of that cell and ``min_points`` particles (the reward's
    least spectrum); where no piece has that many (a coarse smoke grid), ``fallback`` particles will do."""
    out = _roles(piece, cells, min_points)
    return out if out[0] or fallback >= min_points else _roles(piece, cells, fallback)


def _roles(piece, cells, min_points):
    counts = np.bincount(piece)
    cell_size = np.bincount(cells)
    goal, other = [], []
    for p in np.flatnonzero(counts):
        c = cells[piece == p]
        top = np.bincount(c, minlength=len(cell_size))
        top[0] = 0
        k = int(np.argmax(top))
        if k and top[k] * 2 > counts[p] and top[k] >= MIN_GOAL_SHARE * cell_size[k] and counts[p] >= min_points:
            goal.append((k, int(p)))
        else:
            other.append(int(p))
    goal = [p for _, p in sorted(goal)]  # in the order of the plan's cells
    rest = max(other, key=lambda p: counts[p]) if other else None
    return goal, [p for p in other if p != rest], rest

"""discover_batch (topocut.topology.batch): B scenes tiled in one grid give, scene by scene, what discover()
gives alone with the batch's shared voxel size and particle radius; nothing crosses from one tile to the next.

Float tolerance: the batch translates each scene onto its tile in float32 (~1e-7 of the coordinates), so SDF
values differ from discover()'s by rounding; the scenes below hold no node within that of a decision, and
labels, piece counts and next ids are compared exactly (every particle)."""
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import cKDTree
from test_topology import cut, lattice, piece_counts, vertical_sweep

from topocut.sim.action import KnifeSweep
from topocut.topology import TopologyConfig, discover

pytest.importorskip("warp")

CFG = TopologyConfig(resolution=48)


def long_knife(y0, half_length=1.0):
    """Blade plane y = y0 (normal +y), its long axis along x (the tiling axis), straight down from z = 0.2."""
    return KnifeSweep((0.5, y0, 0.2), (1.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), half_length, 0.2, 0.0015)


def cut_y(x, y0):
    """`cut` across the plane y = y0."""
    xs, dmg = cut(x[:, [1, 0, 2]], [y0])
    return xs[:, [1, 0, 2]], dmg


def scenes():
    """(positions, damage, sweeps, previous labels, next id, side (N,): the part each particle must end in)."""
    out = []
    # 0: a box cut once
    x0 = lattice((0.40, 0.45, 0.055), (0.60, 0.55, 0.145))
    x, dmg = cut(x0, [0.503])
    out.append((x, dmg, vertical_sweep(0.503), None, None, (x0[:, 0] >= 0.503).astype(int)))
    # 1: no particles
    out.append((np.zeros((0, 3)), np.zeros(0, bool), None, np.zeros(0, int), 4, np.zeros(0, int)))
    # 2: a wider, flatter box cut twice: the earlier cut's two pieces are previous labels (walls), the last
    # sweep alone is carved, particles back on the lattice (as test_third_cut_keeps_other_ids_and_gets_a_fresh_id)
    x2 = lattice((0.36, 0.43, 0.055), (0.62, 0.57, 0.125), seed=3)
    _, d1 = cut(x2, [0.453])
    _, d2 = cut(x2, [0.533])
    out.append((x2, d1 | d2, vertical_sweep(0.533), (x2[:, 0] >= 0.453).astype(int), 5,
                np.searchsorted([0.453, 0.533], x2[:, 0])))
    # 3: an uncut ball
    g = lattice((0.44, 0.44, 0.06), (0.56, 0.56, 0.18), seed=4)
    x3 = g[np.linalg.norm(g - [0.5, 0.5, 0.12], axis=1) < 0.06]
    out.append((x3, None, None, None, None, np.zeros(len(x3), int)))
    # 4: a box cut across y by a knife 2 m long along x: its box spans the neighbouring tiles
    x4 = lattice((0.42, 0.40, 0.055), (0.58, 0.60, 0.125), seed=5)
    x, dmg = cut_y(x4, 0.503)
    out.append((x, dmg, long_knife(0.503), None, None, (x4[:, 1] >= 0.503).astype(int)))
    # 5: damaged throughout but not cut here: scene 4's knife must not carve it
    x5 = lattice((0.40, 0.42, 0.055), (0.56, 0.58, 0.135), seed=6)
    out.append((x5, np.ones(len(x5), bool), None, np.zeros(len(x5), int), 2, np.zeros(len(x5), int)))
    return out


def run_batch(sc, cfg=CFG):
    from topocut.topology.batch import batch_scale, discover_batch

    xs, dmgs, sweeps, prevs, nids, _ = zip(*sc)
    res = discover_batch(list(xs), list(dmgs), list(sweeps), list(prevs), cfg, "cpu", list(nids))
    h, r = batch_scale(list(xs), cfg)
    return res, replace(cfg, voxel_size=h, particle_radius=r)


def test_each_scene_of_a_batch_is_discover_alone_with_the_shared_scale():
    from topocut.topology.discover import scene_grid

    sc = scenes()
    res, cfg_b = run_batch(sc)
    assert len(res) == len(sc)
    live = [s[0] for s in sc if len(s[0])]
    # the radius: radius_factor x the median 3rd-neighbour distance, every particle among its own scene's
    d3 = np.concatenate([cKDTree(x).query(x, k=4)[0][:, 3] for x in live])
    assert cfg_b.particle_radius == pytest.approx(CFG.radius_factor * np.median(d3), rel=1e-5)
    # the voxel size: the coarsest any scene alone gets at that radius
    lohi = [(x.min(0), x.max(0)) for x in live]
    assert cfg_b.voxel_size == max(scene_grid(lo, hi, cfg_b.particle_radius, CFG).h for lo, hi in lohi)
    expect_pieces = [2, 0, 3, 1, 2, 1]
    for b, ((x, dmg, sweep, prev, nid, side), got) in enumerate(zip(sc, res)):
        alone = discover(x, dmg, sweep, previous_labels=prev, cfg=cfg_b, next_id=nid)
        assert np.array_equal(got.labels, alone.labels), b
        assert (got.num_clusters, got.next_id) == (alone.num_clusters, alone.next_id), b
        assert got.num_clusters == expect_pieces[b], b
        # the pieces are the parts the cut planes leave (each part one id, different parts different ids)
        if len(x):
            parts = [np.unique(got.labels[side == s]) for s in np.unique(side)]
            assert all(len(p) == 1 and p[0] >= 0 for p in parts), b
            assert len({int(p[0]) for p in parts}) == len(parts), b
            assert piece_counts(got.labels) == sorted(np.bincount(side).tolist()), b
    # earlier ids kept, fresh ids from each scene's own next id
    assert set(np.unique(res[2].labels)) == {0, 1, 5} and res[2].next_id == 6
    assert (res[5].labels == 0).all() and res[5].next_id == 2
    assert res[1].labels.shape == (0,) and res[1].next_id == 4


def test_a_chip_at_a_tile_boundary_joins_its_own_scene():
    """Scene A: a box and a chip 30 cm away at A's +x end; scene B, the next tile, starts a few cm past it.
    Alone the chip joins A's box; B's nearer box is another scene."""
    a = lattice((0.30, 0.45, 0.055), (0.40, 0.55, 0.145))
    chip = lattice((0.70, 0.49, 0.09), (0.72, 0.51, 0.10), seed=2)
    xa = np.concatenate([a, chip])
    xb = lattice((0.30, 0.45, 0.055), (0.45, 0.55, 0.145), seed=7)
    sc = [(xa, None, None, None, None, None), (xb, None, None, None, 7, None)]  # B's ids from 7: A's never
    (ra, rb), cfg_b = run_batch(sc)
    assert ra.num_clusters == 1 and (ra.labels == 0).all()
    assert rb.num_clusters == 1 and (rb.labels == 7).all()
    for (x, _, _, _, nid, _), got in zip(sc, (ra, rb)):
        alone = discover(x, None, None, cfg=cfg_b, next_id=nid)
        assert np.array_equal(got.labels, alone.labels) and got.num_clusters == alone.num_clusters
    # the chip is an own piece when chips are kept: it is not merged into a piece by the tiling either
    (ra, _), _ = run_batch(sc, replace(CFG, min_piece_particles=1))
    assert ra.num_clusters == 2 and len(np.unique(ra.labels[-len(chip):])) == 1
    assert ra.labels[-1] != ra.labels[0]


# ---- MPPI's rollouts: one batched discovery per simulated cut ------------------------------------------------

def test_sim_rollout_costs_are_the_same_batched_or_scene_by_scene(monkeypatch):
    from test_mppi import _cube_slice

    from topocut.planning import rollout as R

    env, goal, state = _cube_slice(3)
    p0, p1 = goal.planes[0].to_vector(), goal.planes[1].to_vector()
    # two cuts each (the second discovers with the first's labels: walls); the last sequence misses twice
    seqs = np.array([[p0, p1], [[0.46, 0.5, 0.0, 0.0], p0], [p1, [0.50, 0.5, 0.3, 0.0]],
                     [[0.95, 0.5, 0.0, 0.0]] * 2], np.float32)
    calls = []
    monkeypatch.setattr(R.Scorer, "labels_batch",
                        lambda self, *a, f=R.Scorer.labels_batch: calls.append(len(a[0])) or f(self, *a))
    costs = {}
    for batched in (True, False):
        topo = TopologyConfig(resolution=48, batch_scenes=batched)
        costs[batched] = R.make_sim_rollout(env, state, goal, topo_cfg=topo, board_z=env.cfg.board_z)(seqs)
    assert calls == [3, 3]  # chunk 1: its three scenes in one call per cut; chunk 2 (a miss) none
    assert np.isfinite(costs[True]).all() and costs[True][0] < costs[True][3]  # the goal's planes beat two misses
    # the batch shares one voxel size and radius where each scene alone picks its own: the pieces here are the
    # same either way (equal costs on this machine); the tolerance is the simulator's run-to-run CPU-atomics
    # noise, as in test_mppi.test_sim_rollout_batched_matches_sequential_and_restores_state
    np.testing.assert_allclose(costs[True], costs[False], rtol=2e-3, atol=1e-4)


def test_discover_scenes_batches_only_where_the_scorer_and_its_config_allow():
    """One labels_batch call for a cut's scenes (and after a turn), else labels scene by scene: a scorer without
    labels_batch, or topology.batch_scenes = False."""
    from types import SimpleNamespace

    from topocut.planning.rollout import discover_scenes, execute_turns

    class PerScene:  # a scorer of the older kind: labels only
        def __init__(self, cfg=None):
            self.topo_cfg, self.calls = cfg, []

        def labels(self, x, damage, sweeps, previous):
            self.calls.append(("one", len(x)))
            return np.full(len(x), len(self.calls), np.int32)

    class Batched(PerScene):
        def labels_batch(self, xs, damages, sweeps, previous):
            self.calls.append(("batch", len(xs)))
            return [np.full(len(x), 9, np.int32) for x in xs]

    xs = [np.zeros((n, 3)) for n in (3, 5)]
    args = (xs, [np.zeros(len(x), bool) for x in xs], [None, None], [None, None])
    for scorer, want in ((PerScene(), [("one", 3), ("one", 5)]), (Batched(), [("batch", 2)]),
                         (Batched(TopologyConfig(batch_scenes=False)), [("one", 3), ("one", 5)])):
        out = discover_scenes(scorer, *args)
        assert scorer.calls == want and [len(o) for o in out] == [3, 5]
    assert discover_scenes(Batched(), [], [], [], []) == []
    # a turn re-discovers every scene in one call, with its previous labels
    env = SimpleNamespace(turn=lambda t: None, state=lambda: SimpleNamespace(x=xs, damage=args[1], sweeps=[[], []]))
    scorer, labels, pts = Batched(), [np.zeros(3, np.int32), np.zeros(5, np.int32)], [None, None]
    assert execute_turns(env, ["turn"], scorer, labels, pts) == 1
    assert scorer.calls == [("batch", 2)] and all((lab == 9).all() for lab in labels) and pts[1].shape == (5, 3)

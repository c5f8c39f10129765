"""Topology discovery on hand-built particle clouds; expected piece counts come from the cut planes."""
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from topocut.sim.action import KnifeSweep
from topocut.topology import TopologyConfig, discover, match_labels
from topocut.topology.discover import as_sweeps

S = 0.01  # lattice spacing
CFG = TopologyConfig(resolution=64)


def lattice(lo, hi, s=S, seed=0, jitter=0.15):
    rng = np.random.default_rng(seed)
    axes = [np.arange(a, b + 1e-9, s) for a, b in zip(lo, hi)]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return g + rng.uniform(-jitter * s, jitter * s, g.shape)  # N,3


def box():
    return lattice((0.40, 0.45, 0.055), (0.60, 0.55, 0.145))


def vertical_sweep(x0, depth=0.2, top=0.2, ht=0.0015):
    """Blade plane x = x0 (normal +x) moving straight down from z = top by `depth`."""
    return KnifeSweep((x0, 0.5, top), (0.0, 1.0, 0.0), (0.0, 0.0, -1.0), (1.0, 0.0, 0.0), 0.2, depth, ht)


def cut(x, planes, band=0.012, push=0.002, below=-1.0):
    """Damage the particles within `band` of each plane x = p (and above z = below); push them off the plane."""
    x = x.copy()
    dmg = np.zeros(len(x), bool)
    for p in planes:
        d = (np.abs(x[:, 0] - p) < band) & (x[:, 2] > below)
        dmg |= d
        x[d, 0] += np.sign(x[d, 0] - p) * push
    return x, dmg


def piece_counts(labels):
    ids = np.unique(labels[labels >= 0])
    return sorted(int((labels == i).sum()) for i in ids)


def test_uncut_box_is_one_watertight_piece():
    x = box()
    res = discover(x, np.zeros(len(x), bool), None, cfg=CFG)
    assert res.num_clusters == 1 and (res.labels == 0).all()
    (mesh,) = res.meshes.values()
    assert mesh.is_watertight
    # the surface wraps the particle box grown by about one particle radius (= spacing)
    lo, hi = x.min(0), x.max(0)
    assert np.all(mesh.bounds[0] > lo - 2 * S) and np.all(mesh.bounds[0] < lo)
    assert np.all(mesh.bounds[1] < hi + 2 * S) and np.all(mesh.bounds[1] > hi)
    for step in ("sdf", "carve", "marching_cubes", "smoothing", "components", "assignment"):
        assert res.timings[step] >= 0.0


def test_plane_cut_gives_two_pieces_with_plane_counts():
    x0 = box()
    x, dmg = cut(x0, [0.503])
    res = discover(x, dmg, vertical_sweep(0.503), cfg=CFG)
    assert res.num_clusters == 2 and (res.labels >= 0).all()
    left = x0[:, 0] < 0.503
    assert len(np.unique(res.labels[left])) == 1 and len(np.unique(res.labels[~left])) == 1
    assert res.labels[left][0] != res.labels[~left][0]
    assert piece_counts(res.labels) == sorted([int(left.sum()), int((~left).sum())])
    # mesh volumes split in the ratio of the particle counts (both pieces have the same cross-section)
    vols = {i: m.volume for i, m in res.meshes.items()}
    li, ri = res.labels[left][0], res.labels[~left][0]
    assert vols[li] / vols[ri] == pytest.approx(left.sum() / (~left).sum(), rel=0.15)


def test_cut_without_displacement_still_separates():
    x0 = box()
    _, dmg = cut(x0, [0.503])
    res = discover(x0, dmg, vertical_sweep(0.503), cfg=CFG)
    assert res.num_clusters == 2
    assert piece_counts(res.labels) == sorted([int((x0[:, 0] < 0.503).sum()), int((x0[:, 0] >= 0.503).sum())])


def test_four_parallel_cuts_give_five_slabs():
    x0 = box()
    planes = [0.443, 0.483, 0.523, 0.563]
    x, dmg = cut(x0, planes)
    res = discover(x, dmg, [vertical_sweep(p) for p in planes], cfg=CFG)
    assert res.num_clusters == 5
    slab = np.searchsorted(planes, x0[:, 0])  # 0..4: which side of each plane
    for k in range(5):
        assert len(np.unique(res.labels[slab == k])) == 1
    assert piece_counts(res.labels) == sorted(np.bincount(slab).tolist())


def test_half_way_cut_leaves_one_piece():
    x0 = box()
    # the blade stops at z = 0.10, half-way down a box spanning z in [0.05, 0.15]
    x, dmg = cut(x0, [0.503], below=0.10)
    res = discover(x, dmg, vertical_sweep(0.503, depth=0.10), cfg=CFG)
    assert res.num_clusters == 1 and (res.labels == res.labels[0]).all()


def test_sweep_without_damage_carves_nothing_in_the_damage_driven_mode():
    import dataclasses

    cfg = dataclasses.replace(CFG, carve_through="damaged")
    x = box()
    res = discover(x, np.zeros(len(x), bool), vertical_sweep(0.503), cfg=cfg)
    assert res.num_clusters == 1
    # damage far from the sweep does not license a carve either
    far = x[:, 0] < 0.42
    res = discover(x, far, vertical_sweep(0.503), cfg=cfg)
    assert res.num_clusters == 1


def test_a_sweep_through_undamaged_material_separates_it_as_the_simulator_does():
    """carve_through="swept" (the default): the pieces are what the blade's swept surface separates, damaged or
    not (topocut.sim.pieces.split's rule); the two sides of the plane at x = 0.503 are the two pieces."""
    x = box()
    res = discover(x, np.zeros(len(x), bool), vertical_sweep(0.503), cfg=CFG)
    assert res.num_clusters == 2
    side = x[:, 0] > 0.503
    assert len(np.unique(res.labels[side])) == 1 and len(np.unique(res.labels[~side])) == 1
    assert res.labels[side][0] != res.labels[~side][0]


def test_torus_is_one_piece_of_genus_one():
    R, a, s = 0.08, 0.03, 0.006
    g = lattice((0.5 - R - a,) * 2 + (0.1 - a,), (0.5 + R + a,) * 2 + (0.1 + a,), s=s)
    rho = np.hypot(g[:, 0] - 0.5, g[:, 1] - 0.5)
    x = g[(rho - R) ** 2 + (g[:, 2] - 0.1) ** 2 < a * a]
    res = discover(x, np.zeros(len(x), bool), None, cfg=CFG)
    assert res.num_clusters == 1 and (res.labels == 0).all()
    (mesh,) = res.meshes.values()
    assert mesh.is_watertight and mesh.euler_number == 0  # a torus, the hole survived


def test_hollow_sphere_cavity_shell_joins_its_piece():
    g = lattice((0.38,) * 3, (0.62,) * 3, s=0.008)
    d = np.linalg.norm(g - 0.5, axis=1)
    x = g[(d < 0.12) & (d > 0.07)]
    res = discover(x, np.zeros(len(x), bool), None, cfg=CFG)
    assert res.num_clusters == 1
    (mesh,) = res.meshes.values()
    assert mesh.body_count == 2  # outer surface + inner cavity shell, one piece
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * (0.12 ** 3 - 0.07 ** 3), rel=0.25)


def test_two_separate_objects():
    a = lattice((0.30, 0.45, 0.055), (0.40, 0.55, 0.145))
    b = lattice((0.55, 0.45, 0.055), (0.65, 0.55, 0.145), seed=1)
    x = np.concatenate([a, b])
    res = discover(x, np.zeros(len(x), bool), None, cfg=CFG)
    assert res.num_clusters == 2
    la, lb = np.unique(res.labels[: len(a)]), np.unique(res.labels[len(a):])
    assert len(la) == 1 and len(lb) == 1 and la[0] != lb[0]


def test_third_cut_keeps_other_ids_and_gets_a_fresh_id():
    x0 = box()
    x, dmg = cut(x0, [0.463, 0.543])
    first = discover(x, dmg, [vertical_sweep(0.463), vertical_sweep(0.543)], cfg=CFG)
    assert first.num_clusters == 3 and first.next_id == 3
    # third cut splits the middle piece only; earlier gaps are not re-carved (only the last sweep is passed)
    # and the particles are put back on the lattice: previous labels keep the earlier pieces apart
    _, dmg3 = cut(x0, [0.503])
    res = discover(x0, dmg | dmg3, vertical_sweep(0.503), previous_labels=first.labels, cfg=CFG, next_id=7)
    assert res.num_clusters == 4
    outer = (x0[:, 0] < 0.463) | (x0[:, 0] >= 0.543)
    assert np.array_equal(res.labels[outer], first.labels[outer])
    mid = ~outer
    mid_id = first.labels[mid][0]
    new = set(np.unique(res.labels[mid]).tolist())
    assert len(new) == 2 and mid_id in new and (new - {mid_id}) == {7}  # fresh id, never a reused one
    assert res.next_id == 8 and set(res.meshes) == set(np.unique(res.labels).tolist())


def test_match_labels_hungarian_and_fresh_ids():
    prev = np.array([0, 0, 0, 0, 0, 0, 1, 1, 1, -1])
    raw = np.array([1, 1, 1, 1, 2, 2, 0, 0, 0, -1])  # old 0 splits 4/2; old 1 unchanged
    labels, id_of, nxt = match_labels(raw, prev)
    assert labels.tolist() == [0, 0, 0, 0, 2, 2, 1, 1, 1, -1] and nxt == 3
    # P: 450 of old 0 + 550 of old 1 (merged); Q: 300 of old 0 alone; S: 500 of old 1 alone. Maximum overlap
    # over all pairs gives P old 0 (450) and S old 1 (950 > 850): P then fails the half share (45%) and Q,
    # wholly old 0, lost id 0 too. Among eligible pairs (P-1 55%, Q-0, S-1) the most overlap is P-1 + Q-0.
    prev = np.r_[np.zeros(450), np.ones(550), np.zeros(300), np.ones(500)].astype(int)
    raw = np.r_[np.zeros(1000), np.ones(300), np.full(500, 2)].astype(int)
    labels, id_of, nxt = match_labels(raw, prev)
    assert id_of.tolist() == [1, 0, 2] and nxt == 3  # Q keeps 0; S, the smaller claim on 1, is new
    # no previous labels: ids by decreasing size
    labels, _, nxt = match_labels(np.array([1, 0, 0, 1, 1]))
    assert labels.tolist() == [0, 1, 1, 0, 0] and nxt == 2


def test_mesh_export_round_trip(tmp_path):
    x, dmg = cut(box(), [0.503])
    res = discover(x, dmg, vertical_sweep(0.503), cfg=CFG)
    paths = res.export(tmp_path, "ply") + res.export(tmp_path, "obj")
    assert len(paths) == 4
    for p in paths:
        cid = int(p.stem.split("_")[1])
        back = trimesh.load(p, process=False)
        assert len(back.faces) == len(res.meshes[cid].faces)
        assert back.volume == pytest.approx(res.meshes[cid].volume, rel=1e-4)
    with pytest.raises(ValueError, match="ply"):
        res.export(tmp_path, "fbx")


def test_bad_inputs_name_the_problem():
    with pytest.raises(ValueError, match="knife_sweep"):
        as_sweeps(42)
    assert len(as_sweeps([[vertical_sweep(0.5).asdict()], None])) == 1
    with pytest.raises(ValueError, match="smoothing_alpha"):
        TopologyConfig(smoothing_alpha=2.0).validate()
    with pytest.raises(ValueError, match="damage"):
        discover(box(), np.zeros(3, bool), None, cfg=CFG)


def test_package_import_does_not_load_warp():
    code = "import sys, topocut.topology, topocut.topology.observation; assert 'warp' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_marching_cubes_adapter_and_smoothing_on_an_analytic_sphere():
    from topocut.topology.mesh import laplacian_smooth, marching_cubes, mesh_components
    from topocut.topology.sdf import Grid

    n, R = 48, 0.3
    grid = Grid(np.full(3, -0.5), 1.0 / (n - 1), (n, n, n))
    ax = np.linspace(-0.5, 0.5, n)
    field = np.sqrt(sum(a ** 2 for a in np.meshgrid(ax, ax, ax, indexing="ij"))) - R
    v, f = marching_cubes(field.astype(np.float32), grid)
    mesh = trimesh.Trimesh(v, f, process=False)
    assert mesh.is_watertight and mesh.volume == pytest.approx(4 / 3 * np.pi * R ** 3, rel=0.02)  # outward normals
    assert np.abs(np.linalg.norm(v, axis=1) - R).max() < 0.2 * grid.h
    assert mesh_components(f, len(v))[0] == 1
    noisy = v + np.random.default_rng(0).normal(0, 0.3 * grid.h, v.shape)
    smooth = laplacian_smooth(noisy, f, iterations=5, alpha=0.5)
    err = lambda p: np.std(np.linalg.norm(p, axis=1) - R)  # noqa: E731
    assert err(smooth) < 0.5 * err(noisy)


def test_cut_down_to_the_board_separates_and_the_board_clips_the_bottom():
    x0 = box()  # bottom particles at z = 0.055, their balls reach below the board at z = 0.05
    x, dmg = cut(x0, [0.503])
    sweep = vertical_sweep(0.503, depth=0.15)  # the blade stops exactly on the board
    res = discover(x, dmg, sweep, cfg=CFG)
    assert res.num_clusters == 2
    assert all(m.bounds[0][2] >= 0.05 - 1e-6 for m in res.meshes.values())  # flat on the board
    # without the board the material under the blade's last position keeps the halves together
    res = discover(x, dmg, sweep, cfg=TopologyConfig(resolution=64, board_z=None))
    assert res.num_clusters == 1


def test_device_names():
    from topocut.topology.sdf import resolve_device

    assert resolve_device("cpu") == "cpu" and resolve_device("auto") in ("cpu", "cuda")
    with pytest.raises(ValueError, match="cpu, cuda"):
        resolve_device("tpu")


def test_chips_of_debris_join_the_nearest_piece():
    # two boxes, and a chip of 18 particles 5 cm from box b: pieces, not chips, are counted
    a = lattice((0.30, 0.45, 0.055), (0.40, 0.55, 0.145))
    b = lattice((0.55, 0.45, 0.055), (0.65, 0.55, 0.145), seed=1)
    chip = lattice((0.70, 0.49, 0.09), (0.72, 0.51, 0.10), seed=2)
    assert len(chip) == 18
    x = np.concatenate([a, b, chip])
    res = discover(x, np.zeros(len(x), bool), None, cfg=CFG)
    assert res.num_clusters == 2
    assert (res.labels[-len(chip):] == res.labels[len(a)]).all()  # the chip is counted with box b
    alone = discover(x, np.zeros(len(x), bool), None, cfg=TopologyConfig(resolution=64, min_piece_particles=1))
    assert alone.num_clusters == 3  # without the rule the chip is a piece of its own


def test_an_unlabelled_particle_between_two_pieces_does_not_join_them():
    """Two earlier pieces 3 spacings apart with one particle in the gap: labelled either way it is walled off;
    unlabelled (-1: it was debris) it takes its nearest piece's side of the wall instead of bridging both pieces
    into one fresh id."""
    g = np.stack(np.meshgrid(np.arange(10), np.arange(8), np.arange(6), indexing="ij"), -1).reshape(-1, 3) * S
    a, b = g + [0.40, 0.45, 0.055], g + [0.40 + 9 * S + 0.03, 0.45, 0.055]
    stray = np.array([[0.40 + 9 * S + 0.012, 0.45 + 3.5 * S, 0.055 + 2 * S]])  # nearer a's face
    x = np.concatenate([a, b, stray])
    for stray_label in (0, -1):
        prev = np.r_[np.zeros(len(a), int), np.ones(len(b), int), [stray_label]]
        res = discover(x, None, None, previous_labels=prev, cfg=TopologyConfig(resolution=48))
        assert np.array_equal(res.labels[: len(a)], np.zeros(len(a))), stray_label  # ids kept, pieces apart
        assert np.array_equal(res.labels[len(a): -1], np.ones(len(b))), stray_label
        assert res.num_clusters == 2


@pytest.mark.parametrize("moved, stray", [(0.025, 0.001), (0.018, 0.0005)])
def test_a_kerf_particle_keeps_its_side_of_the_blade(moved, stray):
    """The simulator's split cuts every bond across the blade's plane, so a particle left in the carved kerf
    belongs to its own side's piece even where the other side's surface is nearer (docs/topology.md, step 9):
    here the + side has moved ``moved`` off the plane but a layer of its particles stayed ``stray`` past it,
    a few mm from the - side's surface and ~2 cm from its own.  The rule before sent them to the - side."""
    x0 = box()
    plane = 0.503
    minus = x0[:, 0] < plane
    prev = np.where(x0[:, 0] < 0.443, 1, 0).astype(np.int32)  # an earlier slab: this cut splits cluster 0
    x = x0.copy()
    x[~minus, 0] += moved
    layer = np.flatnonzero(~minus & (x0[:, 0] < plane + S))[::3]  # every third particle of the + face
    x[layer, 0] = plane + stray
    dmg = np.abs(x0[:, 0] - plane) < 0.012
    res = discover(x, dmg, vertical_sweep(plane), previous_labels=prev, cfg=CFG)
    # the batched discovery (several scenes in one grid) applies the same rule, here beside an uncut scene
    from topocut.topology.batch import discover_batch

    both = discover_batch([box(), x], [np.zeros(len(x0), bool), dmg], [None, vertical_sweep(plane)], [None, prev],
                          cfg=CFG)
    np.testing.assert_array_equal(both[1].labels, res.labels)
    plus = np.setdiff1d(np.flatnonzero(~minus), layer)
    assert res.num_clusters == 3
    assert len(np.unique(res.labels[plus])) == 1 and len(np.unique(res.labels[minus & (prev == 0)])) == 1
    assert res.labels[plus][0] != res.labels[minus & (prev == 0)][0]
    assert (res.labels[layer] == res.labels[plus][0]).all()


def test_a_particle_the_blade_dragged_across_its_plane_keeps_the_side_it_started_on():
    """The simulator splits by where the particles were when the blade started; the oscillating blade can drag a
    few across its plane (slice / burger at 128^3: 931 particles of the + side ended 3-4 mm on the - side).
    Given the positions before the cut, discovery keeps them on their starting side; without, the side of where
    they ended, as the simulator does not."""
    x0 = box()
    plane = 0.503
    minus = x0[:, 0] < plane
    prev = np.where(x0[:, 0] < 0.443, 1, 0).astype(np.int32)
    layer = np.flatnonzero(~minus & (x0[:, 0] < plane + S))[::3]  # every third particle of the + face...
    start = x0.copy()
    start[layer, 0] = plane + 0.0005  # ...just past the plane when the blade started
    x = x0.copy()
    x[~minus, 0] += 0.02  # the + side moved off the plane
    x[layer, 0] = plane - 0.002  # and the blade dragged the layer 2 mm onto the - side
    dmg = np.abs(x0[:, 0] - plane) < 0.012
    plus = np.setdiff1d(np.flatnonzero(~minus), layer)
    kept = discover(x, dmg, vertical_sweep(plane), previous_labels=prev, cfg=CFG, start_positions=start)
    assert (kept.labels[layer] == kept.labels[plus][0]).all()
    from topocut.topology.batch import discover_batch

    both = discover_batch([box(), x], [np.zeros(len(x0), bool), dmg], [None, vertical_sweep(plane)], [None, prev],
                          cfg=CFG, start_positions=[None, start])
    np.testing.assert_array_equal(both[1].labels, kept.labels)
    ended = discover(x, dmg, vertical_sweep(plane), previous_labels=prev, cfg=CFG)
    assert (ended.labels[layer] == ended.labels[minus & (prev == 0)][0]).all()
    with pytest.raises(ValueError, match="start_positions must be"):
        discover(x, dmg, vertical_sweep(plane), previous_labels=prev, cfg=CFG, start_positions=start[:-1])


@pytest.mark.parametrize("batched", [False, True])
def test_a_cut_never_joins_pieces_even_where_the_walls_fail(monkeypatch, batched):
    """Two earlier pieces touching (the particles back on the lattice, no gap, no sweep): the SDF's walls keep them
    apart.  With the walls taken away (as a failed wall did on the H200: a last cut's discovery joined two earlier
    pieces that the CPU, from the same inputs, kept apart), the check on the result (``keep_earlier_splits``) still
    returns the two pieces with their ids; without the check as well they merge, so the check is what holds."""
    from topocut.topology import assign as A
    from topocut.topology import sdf as S
    from topocut.topology.batch import discover_batch

    x = box()
    prev = (x[:, 0] >= 0.503).astype(int)  # N, two earlier pieces, touching at x = 0.503

    def run():
        if batched:
            return discover_batch([x, x + [0.0, 0.0, 0.0]], [None, None], [None, None], [prev, prev], cfg=CFG)[1]
        return discover(x, None, None, previous_labels=prev, cfg=CFG)

    assert np.array_equal(run().labels, prev)  # the walls
    walls = S.particle_sdf
    monkeypatch.setattr(S, "particle_sdf", lambda x, r, grid, band, device="cpu", owner_labels=None:
                        walls(x, r, grid, band, device))  # no owners: no walls
    held = run()
    assert np.array_equal(held.labels, prev) and held.num_clusters == 2  # the check
    monkeypatch.setattr(A, "keep_earlier_splits", lambda raw, overlap, *a, **k: (raw, len(overlap), np.zeros(0, int)))
    assert run().num_clusters == 1  # neither: they join

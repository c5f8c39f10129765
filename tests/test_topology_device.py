"""The device routines of topology discovery (Warp, run here on the CPU) against independent references:
scipy's connected components, a hand-computed Laplacian step, cKDTree nearest neighbours, numpy carving."""
import numpy as np
import pytest
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from topocut.sim.action import KnifeSweep
from topocut.topology import TopologyConfig, discover

wp = pytest.importorskip("warp")


@pytest.fixture(scope="module", autouse=True)
def _warp():
    """Warp's default device is CUDA where there is a GPU: the arrays these tests make without a device, and the
    routines they call with device="cpu", must meet on the CPU (else a launch reads device memory on the host)."""
    from topocut.topology.sdf import init_warp

    init_warp()
    before = wp.get_device()
    wp.set_device("cpu")
    yield
    wp.set_device(before)


def scipy_components(edges, n):
    e = np.asarray(edges).reshape(-1, 2)
    g = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    return connected_components(g, directed=False)


def warp_devices():
    """Warp's CPU, and CUDA where there is a GPU (the union-find's races only show there: run by benchmarks/gpu.sh)."""
    from topocut.topology.sdf import init_warp

    init_warp()
    return ["cpu"] + (["cuda"] if wp.get_cuda_device_count() else [])


@pytest.mark.parametrize("device", warp_devices())
@pytest.mark.parametrize("case", ["chain", "random", "isolated", "self_loops"])
def test_graph_components_match_scipy(case, device):
    from topocut.topology.components import graph_components

    rng = np.random.default_rng(1)
    n = 400
    if case == "chain":  # one long path given backwards: the deepest trees a union-find can build
        edges = np.stack([np.arange(n - 1, 0, -1), np.arange(n - 2, -1, -1)], 1)
    elif case == "random":
        edges = rng.integers(0, n, (300, 2))
    elif case == "isolated":
        edges = np.array([[0, 399], [5, 7], [7, 9]])
    else:
        edges = np.array([[3, 3], [4, 4], [3, 4], [10, 10]])
    k_ref, lab_ref = scipy_components(edges, n)
    for _ in range(3 if device == "cuda" else 1):  # a race would not show every time
        k, lab = graph_components(edges, n, device)
        assert k == k_ref
        assert np.array_equal(lab, lab_ref)  # same numbering too: by each component's smallest node


def serpentine(n=24):
    """A 6-connected corridor winding along every other row of every other layer (long and thin)."""
    m = np.zeros((n, n, n), bool)
    for i in range(0, n, 2):
        for j in range(0, n, 2):
            m[i, j, :] = True
            if j + 2 < n:  # to the next row, at alternating ends
                m[i, j + 1, n - 1 if (j // 2) % 2 == 0 else 0] = True
        if i + 2 < n:  # to the next layer
            m[i + 1, 0, 0] = True
    return m


@pytest.mark.parametrize("device", warp_devices())
@pytest.mark.parametrize("case", ["random30", "random60", "serpentine", "shells"])
def test_grid_components_match_ndimage_label(case, device):
    from topocut.topology.components import grid_components

    rng = np.random.default_rng(2)
    if case.startswith("random"):
        mask = rng.random((21, 17, 19)) < int(case[6:]) / 100
    elif case == "serpentine":
        mask = serpentine()
    else:  # nested spherical shells: several components, one inside the other
        ax = np.linspace(-1, 1, 31)
        r = np.sqrt(sum(a ** 2 for a in np.meshgrid(ax, ax, ax, indexing="ij")))
        mask = ((r > 0.2) & (r < 0.4)) | ((r > 0.6) & (r < 0.8)) | (r < 0.05)
    lab_ref, k_ref = ndimage.label(mask)  # default structure: 6-connectivity
    for _ in range(3 if device == "cuda" else 1):
        lab, k = grid_components(mask, device)
        assert k == k_ref and np.array_equal(lab, lab_ref)


@pytest.mark.parametrize("device", warp_devices())
def test_fill_voids_fills_small_enclosed_cavities_only(device):
    from topocut.topology.components import fill_voids

    f = np.ones((20, 20, 20), np.float32)  # outside everywhere ...
    f[3:17, 3:17, 3:17] = -1.0  # ... but a solid block
    f[5:7, 5:7, 5:7] = 1.0  # an enclosed cavity of 8 nodes
    f[9:12, 9:12, 9:12] = 1.0  # an enclosed cavity of 27 nodes
    f[3:17, 14, 14] = 1.0  # a tunnel open to the outside: not a cavity
    for _ in range(3 if device == "cuda" else 1):  # on CUDA the last pass once left air nodes under a non-root
        field = wp.array(f, dtype=float, device=device)
        fill_voids(field, 10, -0.25, device)
        out = field.numpy()
        assert np.count_nonzero(out != f) == 8
    assert np.all(out[5:7, 5:7, 5:7] == -0.25)  # small cavity filled
    assert np.all(out[9:12, 9:12, 9:12] == 1.0)  # large cavity kept (a hollow object)
    assert np.all(out[3:17, 14, 14] == 1.0) and out[0, 0, 0] == 1.0  # connected to the border: kept
    assert np.count_nonzero(out != f) == 8


@pytest.mark.parametrize("device", warp_devices())
def test_label_pieces_drops_pieces_below_min_voxels_and_numbers_the_rest_by_first_node(device):
    """Inside nodes only (no mesh): blocks of 1, 7, 8, 9 and 512 nodes with min_voxels 8 keep the last three, numbered
    in the order of their smallest node index, as scipy's labelling says; the dropped blocks' nodes are -1."""
    from topocut.topology.components import label_pieces

    f = np.ones((24, 24, 24), np.float32)
    f[20:22, 20:22, 20:22] = -1.0  # 8 nodes
    f[1, 1, 1] = -1.0  # 1 node
    f[1, 5, 1:8] = -1.0  # 7 nodes
    f[10:18, 10:18, 10:18] = -1.0  # 512 nodes
    f[5, 20, 1:10] = -1.0  # 9 nodes
    ref, n = ndimage.label(f < 0)
    sizes = np.bincount(ref.ravel())[1:]
    kept = [c + 1 for c in range(n) if sizes[c] >= 8]  # scipy numbers in raster order: by first node, as ours
    empty = wp.zeros(0, dtype=wp.int32, device=device)
    pieces = label_pieces(wp.array(f, dtype=float, device=device), empty, empty, 0, min_voxels=8, device=device)
    labels = pieces.labels.numpy().reshape(f.shape)
    assert pieces.count == 3 == len(kept) and sorted(sizes[np.array(kept) - 1]) == [8, 9, 512]
    want = np.full(f.shape, -1)
    for i, c in enumerate(kept):
        want[ref == c] = i
    np.testing.assert_array_equal(labels, want)


def octahedron():
    v = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)
    f = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    return v, f


def test_smoothing_step_by_hand_on_an_octahedron():
    from topocut.topology.mesh import laplacian_smooth

    v, f = octahedron()
    # each vertex's 4 neighbours are the other axis directions: their mean is 0, so a step with alpha maps
    # v -> v + alpha (0 - v) = (1 - alpha) v, and n steps give (1 - alpha)^n v
    assert np.allclose(laplacian_smooth(v, f, iterations=1, alpha=0.5), 0.5 * v, atol=1e-6)
    assert np.allclose(laplacian_smooth(v, f, iterations=3, alpha=0.25), 0.75 ** 3 * v, atol=1e-6)
    # move the top vertex up: its neighbours' mean moves by 1/4 of that, its own mean stays 0
    v2 = v.copy()
    v2[4, 2] = 3.0
    s = laplacian_smooth(v2, f, iterations=1, alpha=0.5)
    assert s[4] == pytest.approx([0.0, 0.0, 1.5])  # 3 + 0.5 (0 - 3)
    assert s[0] == pytest.approx([0.5, 0.0, 0.5 * (3.0 - 1.0) / 4])  # mean of (0,1,0),(0,-1,0),(0,0,3),(0,0,-1)


def test_smoothing_matches_a_dense_umbrella_operator_on_an_irregular_mesh():
    from topocut.topology.mesh import laplacian_smooth

    rng = np.random.default_rng(3)
    v = rng.normal(size=(30, 3))
    f = np.array([rng.choice(30, 3, replace=False) for _ in range(60)])
    f = np.concatenate([f, f[:10]])  # repeated faces: every edge counts once
    nbr = [set() for _ in range(len(v))]
    for a, b, c in f:
        nbr[a] |= {b, c}
        nbr[b] |= {a, c}
        nbr[c] |= {a, b}
    ref = v.copy()
    for _ in range(2):
        mean = np.array([ref[sorted(s)].mean(0) if s else ref[i] for i, s in enumerate(nbr)])
        ref = ref + 0.3 * (mean - ref)  # vertices in no face keep their place
    assert np.allclose(laplacian_smooth(v, f, iterations=2, alpha=0.3), ref, atol=1e-5)


def test_vertex_adjacency_rows_are_the_distinct_neighbours():
    from topocut.topology.mesh import vertex_adjacency

    v, f = octahedron()
    fa = wp.array(f.astype(np.int32).ravel(), dtype=wp.int32)
    adj = vertex_adjacency(fa, len(v))
    off, cnt, nbr = adj.offset.numpy(), adj.count.numpy(), adj.nbr.numpy()
    for i in range(len(v)):
        opposite = i ^ 1  # vertices come in +/- pairs: 0/1, 2/3, 4/5
        assert nbr[off[i]:off[i] + cnt[i]].tolist() == sorted(set(range(6)) - {i, opposite})


def test_vertex_inside_nodes_lie_on_each_vertex_grid_edge():
    from topocut.topology.mesh import extract_surface, vertex_inside_nodes
    from topocut.topology.sdf import Grid

    n, R = 24, 0.3
    grid = Grid(np.full(3, -0.5), 1.0 / (n - 1), (n, n, n))
    ax = np.linspace(-0.5, 0.5, n)
    f = (np.sqrt(sum(a ** 2 for a in np.meshgrid(ax, ax, ax, indexing="ij"))) - R).astype(np.float32)
    field = wp.array(f, dtype=float)
    verts, _ = extract_surface(field, grid)
    node = vertex_inside_nodes(verts, field, grid).numpy()
    v = verts.numpy()
    assert (node >= 0).all()
    idx = np.stack(np.unravel_index(node, f.shape), 1)
    assert (f.ravel()[node] < 0).all()
    d = np.abs((v - grid.lower) / grid.h - idx)  # vertex minus node, in voxels: along one axis only, < 1
    assert (np.sort(d, 1)[:, :2] < 1e-3).all() and (d.max(1) <= 1 + 1e-4).all()


@pytest.mark.parametrize("cloud", ["lattice", "plane", "line"])
def test_particle_spacing_is_the_median_third_neighbour_distance(cloud):
    from topocut.topology.sdf import particle_spacing

    rng = np.random.default_rng(4)
    if cloud == "lattice":
        ax = np.arange(0, 0.2, 0.01)
        x = np.stack(np.meshgrid(ax, ax, ax[:8], indexing="ij"), -1).reshape(-1, 3)
        x = x + rng.uniform(-0.002, 0.002, x.shape)
    elif cloud == "plane":  # no volume: the first search radius is too small and has to grow
        ax = np.arange(0, 0.3, 0.01)
        x = np.stack(np.meshgrid(ax, ax, [0.1], indexing="ij"), -1).reshape(-1, 3)
    else:
        x = np.stack([np.linspace(0, 1, 50), np.zeros(50), np.zeros(50)], 1)
    d, _ = cKDTree(x).query(x, k=4)
    xd = wp.array(x.astype(np.float32), dtype=wp.vec3)
    got = particle_spacing(xd, x.min(0), x.max(0), "cpu")
    assert got == pytest.approx(np.median(d[:, 3]), rel=1e-5)


def test_carving_matches_a_numpy_reference():
    from topocut.topology.carve import carve_and_clip
    from topocut.topology.sdf import Grid

    rng = np.random.default_rng(5)
    grid = Grid(np.zeros(3), 0.01, (20, 20, 20))
    f0 = rng.uniform(-0.02, 0.02, grid.shape).astype(np.float32)
    x = rng.uniform(0.0, 0.19, (400, 3))
    dmg = x[:, 1] < 0.08  # damage only in one half of the sweep
    sweep = KnifeSweep((0.1, 0.1, 0.2), (0.0, 1.0, 0.0), (0.0, 0.0, -1.0), (1.0, 0.0, 0.0), 0.2, 0.15, 0.004)
    radius, min_half, board = 0.015, 0.006, 0.03
    field = wp.array(f0, dtype=float)
    n_carvers, _ = carve_and_clip(field, grid, wp.array(x.astype(np.float32), dtype=wp.vec3),
                                  wp.array(dmg.astype(np.int32), dtype=wp.int32), [sweep], [sweep], radius,
                                  min_half, board)
    carvers = x[dmg & (sweep.sdf(x) <= radius)]
    assert n_carvers == len(carvers)
    nodes = np.stack(np.meshgrid(*[np.arange(s) * grid.h for s in grid.shape], indexing="ij"), -1).reshape(-1, 3)
    thick = KnifeSweep(sweep.origin, sweep.u, sweep.w, sweep.n, sweep.half_length, sweep.depth, min_half)
    box = thick.sdf(nodes)
    near = cKDTree(carvers).query(nodes, distance_upper_bound=radius)[0] <= radius
    ref = np.maximum(f0.ravel(), board - nodes[:, 2])
    ref = np.where((box < 0) & near, np.maximum(ref, -box), ref)
    assert np.allclose(field.numpy().ravel(), ref, atol=1e-6)
    assert ((box < 0) & near).any() and ((box < 0) & ~near).any()  # both cases occur


def test_chips_join_the_nearest_particle_of_a_larger_piece():
    from topocut.topology.assign import absorb_chips

    rng = np.random.default_rng(6)
    x = rng.uniform(0, 1, (300, 3))
    raw = rng.integers(0, 4, 300)
    raw[:5] = -1
    small = np.array([0, 1, 0, 1])  # pieces 1 and 3 are chips
    out = absorb_chips(wp.array(x.astype(np.float32), dtype=wp.vec3), wp.array(raw.astype(np.int32), dtype=wp.int32),
                       small).numpy()
    big = np.flatnonzero((raw >= 0) & (small[np.maximum(raw, 0)] == 0))
    move = np.flatnonzero((raw >= 0) & (small[np.maximum(raw, 0)] == 1))
    _, j = cKDTree(x[big]).query(x[move])
    ref = raw.copy()
    ref[move] = raw[big[j]]
    assert np.array_equal(out, ref)


def box(lo, hi, s=0.01, seed=0):
    axes = [np.arange(a, b + 1e-9, s) for a, b in zip(lo, hi)]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return g + np.random.default_rng(seed).uniform(-0.0015, 0.0015, g.shape)


def test_meshes_are_built_only_when_asked_for():
    x = np.concatenate([box((0.30, 0.45, 0.055), (0.40, 0.55, 0.145)),
                        box((0.55, 0.45, 0.055), (0.65, 0.55, 0.145), seed=1)])
    res = discover(x, np.zeros(len(x), bool), None, cfg=TopologyConfig(resolution=48))
    assert res._meshes is None  # labels only: no host mesh yet
    meshes = res.meshes
    assert sorted(meshes) == [0, 1] and all(m.is_watertight for m in meshes.values())
    assert res.meshes is meshes  # built once
    for cid, m in meshes.items():  # each mesh wraps its own piece's particles
        p = x[res.labels == cid]
        assert np.all(m.bounds[0] < p.min(0)) and np.all(m.bounds[1] > p.max(0))


def test_large_previous_ids_are_kept():
    a = box((0.30, 0.45, 0.055), (0.40, 0.55, 0.145))
    b = box((0.55, 0.45, 0.055), (0.65, 0.55, 0.145), seed=1)
    x = np.concatenate([a, b])
    prev = np.r_[np.full(len(a), 200_000), np.full(len(b), 100_000)]  # ids beyond the direct overlap table
    res = discover(x, np.zeros(len(x), bool), None, previous_labels=prev, cfg=TopologyConfig(resolution=48))
    assert np.array_equal(res.labels, prev) and res.next_id == 200_001

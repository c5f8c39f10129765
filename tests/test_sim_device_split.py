"""The device split (topocut/sim/pieces_device.py, sim.tuning.device_split; docs/sim.md, "Pieces and contact")
gives exactly the labels of the host's pieces.split for every particle, on the CPU backend.

Scenes: the separation tests' cuts (cube and cake, vertical planes spread over a cell at 48³ and 64³ spacings),
random planes (yaw, tilt, offset; some stop short) after an earlier cut (so bonds between pieces are refused),
flakes and far debris (the nearest-large-piece rule, and its whole-scene search), a batch of different scenes with
an idle one against each alone.  CuttingEnv with the switch on against off (its pieces, and their fields):
tests/test_sim_device_fields.py.
"""
import numpy as np
import pytest

from topocut.sim import pieces as P
from topocut.sim.action import KnifeAction
from topocut.sim.config import SimConfig, TuningConfig
from topocut.sim.objects import ObjectPose, sample_object

POSE = ObjectPose(x=0.5, y=0.5, yaw=0.0, scale=1.0)
CAP = 24000  # rows of every call (counts below it): one set of device fields, compiled once


pytestmark = pytest.mark.usefixtures("taichi_two_threads")  # the union-find's atomics race as on a GPU


def device(x, piece, sweep, spacing):
    from topocut.sim.pieces_device import split_batch

    n = len(x)
    xs, ps = np.zeros((1, CAP, 3)), np.zeros((1, CAP), np.int32)
    xs[0, :n], ps[0, :n] = x, piece
    return split_batch(xs, [n], ps, [sweep], spacing)[0, :n]


def scene(name, n_grid, seed=0):
    cfg = SimConfig(n_grid=n_grid)
    x, _ = sample_object(name, POSE, spacing=cfg.spacing, seed=seed)
    assert len(x) < CAP
    return cfg, x.astype(np.float64)


def flake_particles(x, piece, sweep, spacing):
    """Particles in components under MIN_PIECE before the flake rule (scipy's components of the kept bonds)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    pairs = P.bonds(x, spacing)
    e = pairs[(piece[pairs[:, 0]] == piece[pairs[:, 1]]) & ~P.crosses(x, pairs, sweep)]
    lab = connected_components(coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(len(x),) * 2))[1]
    return int((np.bincount(lab)[lab] < P.MIN_PIECE).sum())


def check(x, piece, sweep, spacing):
    host = P.split(x, piece, sweep, spacing)
    dev = device(x, piece, sweep, spacing)
    assert dev.dtype == np.int32
    np.testing.assert_array_equal(dev, host)
    return host


@pytest.mark.parametrize("name", ["cube", "cake"])
@pytest.mark.parametrize("n_grid,positions", [(48, 8), (64, 4)])
def test_separation_cuts_match_the_host(name, n_grid, positions):
    cfg, x = scene(name, n_grid)
    piece = np.zeros(len(x), np.int32)
    for c in 0.5 + cfg.dx * np.arange(positions) / positions:
        sweep = P.blade_sweep(KnifeAction(x=float(c), y=0.5).canonical(), x, cfg)[0]
        assert check(x, piece, sweep, cfg.spacing).max() == 1  # two pieces
    # a second, crossing cut of the halves (labels from the first): four pieces
    first = P.split(x, piece, P.blade_sweep(KnifeAction(x=0.5, y=0.5), x, cfg)[0], cfg.spacing)
    assert check(x, first, P.blade_sweep(KnifeAction(x=0.5, y=0.52, yaw=np.pi / 2), x, cfg)[0], cfg.spacing).max() == 3


def test_random_planes_after_an_earlier_cut_match_the_host():
    rng = np.random.default_rng(49)
    splits = whole = 0
    for k in range(20):
        name, n_grid = ("cube", "cake")[k % 2], (48, 64)[(k // 2) % 2]
        cfg, x = scene(name, n_grid, seed=k)
        centre = x.mean(0)
        earlier = KnifeAction(x=float(centre[0] + rng.uniform(-0.04, 0.04)), y=float(centre[1]),
                              yaw=float(rng.uniform(-1.5, 1.5)))
        piece = P.split(x, np.zeros(len(x), np.int32), P.blade_sweep(earlier, x, cfg)[0], cfg.spacing)
        depth = None if k % 3 else float(rng.uniform(0.0, 0.12))  # a third stop short (or barely start)
        a = KnifeAction(x=float(centre[0] + rng.uniform(-0.06, 0.06)), y=float(centre[1] + rng.uniform(-0.06, 0.06)),
                        yaw=float(rng.uniform(-np.pi, np.pi)), tilt=float(rng.uniform(-0.6, 0.6)), depth=depth)
        after = check(x, piece, P.blade_sweep(a.canonical(), x, cfg)[0], cfg.spacing)
        splits += after.max() > piece.max()
        whole += after.max() == piece.max()
    assert splits >= 5 and whole >= 2, (splits, whole)  # both outcomes exercised


def test_flakes_and_far_debris_join_the_nearest_large_piece():
    cfg, x = scene("cube", 48)
    lo, hi = x.min(0), x.max(0)
    # debris: 3 particles bonded to each other far from the cube (the whole-scene search), 1 alone nearer
    debris = np.array([[hi[0] + 0.05, 0.5, 0.1], [hi[0] + 0.05 + cfg.spacing, 0.5, 0.1], [hi[0] + 0.05, 0.5, 0.1 + cfg.spacing],
                       [lo[0] - 0.02, 0.45, 0.12]])
    x = np.concatenate([debris[:2], x, debris[2:]])  # low and high indices: the renumbering sees them
    piece, flakes = np.zeros(len(x), np.int32), 0
    # a corner shaved off: a few particles cut loose (flakes), and a shallow cut
    for a in (KnifeAction(x=float(hi[0] - 0.3 * cfg.spacing), y=0.5), KnifeAction(x=0.5, y=0.5, yaw=0.7, depth=0.03),
              KnifeAction(x=float(lo[0] + 0.01), y=float(lo[1] + 0.01), yaw=-np.pi / 4, tilt=0.3)):
        sweep = P.blade_sweep(a.canonical(), x, cfg)[0]
        after = check(x, piece, sweep, cfg.spacing)
        assert np.bincount(after).min() >= P.MIN_PIECE
        flakes += flake_particles(x, piece, sweep, cfg.spacing)
    assert flakes > 3 * len(debris), flakes  # flakes beside the cube too, not only the debris
    # no large piece at all: flakes keep their own labels
    tiny = x[2:7]
    check(tiny, np.zeros(5, np.int32), P.blade_sweep(KnifeAction(x=0.5, y=0.5), x, cfg)[0], cfg.spacing)


def test_a_batch_equals_each_scene_alone():
    from topocut.sim.pieces_device import split_batch

    # different objects, poses and counts at one spacing (a batch is one SimConfig), one scene idle
    cfg = SimConfig(n_grid=64)
    poses = [POSE, ObjectPose(0.45, 0.52, yaw=0.3, scale=0.8), POSE, ObjectPose(0.55, 0.5, yaw=-0.5, scale=1.1)]
    xs0 = [sample_object(name, pose, spacing=cfg.spacing, seed=b)[0].astype(np.float64)
           for b, (name, pose) in enumerate(zip(("cube", "cake", "cake", "cube"), poses))]
    acts = [KnifeAction(x=0.5, y=0.5), KnifeAction(x=0.45, y=0.52, yaw=0.4, tilt=0.2), None,
            KnifeAction(x=0.56, y=0.49, yaw=-1.1, depth=0.08)]
    n = max(map(len, xs0))
    xs, ps = np.zeros((4, n, 3)), np.full((4, n), 7, np.int32)  # padding rows come back unchanged
    sweeps, alone = [], []
    for b, (x, a) in enumerate(zip(xs0, acts)):
        c = len(x)
        xs[b, :c], ps[b, :c] = x, x[:, 0] > x[:, 0].mean() + 0.02  # previous labels: two pieces
        sweeps.append(None if a is None else P.blade_sweep(a.canonical(), x, cfg)[0])
        alone.append(ps[b, :c] if a is None else P.split(x, ps[b, :c], sweeps[b], cfg.spacing))
    assert len({len(x) for x in xs0}) == 4 and max(a.max() for a in alone) >= 2
    out = split_batch(xs, list(map(len, xs0)), ps, sweeps, cfg.spacing)
    for b, x in enumerate(xs0):
        np.testing.assert_array_equal(out[b, :len(x)], alone[b], err_msg=f"scene {b}")
        np.testing.assert_array_equal(out[b, len(x):], 7)
        if sweeps[b] is not None:  # the same scene alone through the single-scene path
            np.testing.assert_array_equal(device(x, ps[b, :len(x)], sweeps[b], cfg.spacing), alone[b])


def test_switch_values_are_checked():
    assert TuningConfig().device_split_enabled("cuda") and not TuningConfig().device_split_enabled("cpu")  # auto
    assert TuningConfig(device_split="on").device_split_enabled("cpu")
    with pytest.raises(ValueError, match=r"^sim\.tuning\.device_split: 'yes'; valid: auto, on, off$"):
        TuningConfig(device_split="yes").validate("cpu", 1, 64, 8)


def test_row_counts_that_change_between_calls_reuse_the_fields_while_they_fit():
    """The env's rows are its largest scene's count, which changes every episode: the device fields only grow
    (a new field tree recompiles the kernels), and every call still equals the host split."""
    from topocut.sim import pieces_device as D

    cfg, x = scene("cube", 32)
    sweep, _, _ = P.blade_sweep(KnifeAction(x=0.5, y=0.5), x, cfg)
    host = P.split(x, np.zeros(len(x), np.int32), sweep, cfg.spacing)
    trees = []
    for n in (len(x) + 100, len(x) + 40, len(x) + 3000, len(x) + 10):  # rows of padding past the scene's count
        xs, ps = np.zeros((2, n, 3)), np.zeros((2, n), np.int32)
        xs[:, :len(x)] = x
        out = D.split_batch(xs, [len(x), len(x)], ps, [sweep, None], cfg.spacing)
        assert out.shape == (2, n)
        np.testing.assert_array_equal(out[0, :len(x)], host)
        np.testing.assert_array_equal(out[1], 0)  # the idle scene keeps its labels
        trees.append(id(D._CACHE[2]))
    assert trees[0] == trees[1] and trees[2] == trees[3]  # fits: reused; grown past its capacity: one new tree
    assert D._CACHE[2].n >= len(x) + 3000


def test_two_batch_sizes_keep_their_own_fields():
    """Two envs of different batch sizes in one process (MPPI's rollouts beside an evaluation's scenes) each keep
    their fields: alternating between them builds no new tree (which would recompile the kernels)."""
    from topocut.sim import pieces_device as D

    cfg, x = scene("cube", 32)
    sweep, _, _ = P.blade_sweep(KnifeAction(x=0.5, y=0.5), x, cfg)
    host = P.split(x, np.zeros(len(x), np.int32), sweep, cfg.spacing)
    seen = {}
    for B in (1, 3, 1, 3):
        xs, ps = np.repeat(x[None], B, 0), np.zeros((B, len(x)), np.int32)
        out = D.split_batch(xs, [len(x)] * B, ps, [sweep] * B, cfg.spacing)
        for b in range(B):
            np.testing.assert_array_equal(out[b], host)
        assert seen.setdefault(B, id(D._CACHE[B])) == id(D._CACHE[B])

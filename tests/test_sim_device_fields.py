"""The pieces' velocity fields on the device (topocut/sim/fields_device.py, with sim.tuning.device_split) give the
host's pieces.colour field for every particle, its conflicts, pieces.cut_off_side and pieces.field_sides, on the
CPU backend.

Scenes: the separation tests' cuts (cube and cake at 48³ and 64³ spacings), random planes after earlier cuts,
a cube diced into a dozen pieces with too few fields (conflicts), labels past a mask's 64 (the host path), and
CuttingEnv with the switch on against off (pieces, fields, sides, the push's side, the field count).  The
adjacency the masks give is checked against a brute-force search over the pieces' cells, written here.
"""
import numpy as np
import pytest
import taichi as ti
from scipy.spatial import cKDTree

from topocut.sim import pieces as P
from topocut.sim.action import KnifeAction
from topocut.sim.config import SimConfig, TuningConfig
from topocut.sim.objects import ObjectPose, sample_object
from topocut.sim.runtime import _ON_RESET

POSE = ObjectPose(x=0.5, y=0.5, yaw=0.0, scale=1.0)
CAP = 24000  # rows of every call: one set of split fields, compiled once
pytestmark = pytest.mark.usefixtures("taichi_two_threads")  # the masks' atomic ORs race as on a GPU
_BODY = {}  # the solver's body field stand-in (1, CAP), made once per Taichi runtime


def body_field():
    if "f" not in _BODY:
        fb = ti.FieldsBuilder()
        _BODY["f"] = ti.field(ti.i32)
        fb.dense(ti.ij, (1, CAP)).place(_BODY["f"])
        _BODY["tree"] = fb.finalize()
        if _BODY.clear not in _ON_RESET:
            _ON_RESET.append(_BODY.clear)  # reset_taichi frees it
    return _BODY["f"]


def reach_of(cfg):
    return cfg.knife_half_thickness + cfg.margin + 2 * cfg.dx  # CuttingEnv._split's


def on_device(x, before, sweep, cfg, fields):
    """(labels, field per particle, conflicts, cut-off side, field sides) from the device, or None."""
    from topocut.sim.fields_device import colour_batch
    from topocut.sim.pieces_device import device_split

    n, body = len(x), body_field()
    ds = device_split(1, CAP)
    xs, ps = np.zeros((1, ds.n, 3)), np.zeros((1, ds.n), np.int32)
    xs[0, :n], ps[0, :n] = x, before
    labels = ds.run(xs, [n], ps, [sweep], cfg.spacing)[:, :n]
    body.fill(-1)
    out = colour_batch(ds, body, labels, ps[:, :n], cfg.n_grid, fields, reach_of(cfg))
    if out is None:
        return None
    conflicts, cut_off, sides, used = out[0]
    field = body.to_numpy()[0, :n]
    assert used == field.max() + 1
    return labels[0], field, conflicts, cut_off, sides


def check(x, before, sweep, cfg, fields=None):
    """The device's fields equal the host's; returns the labels after the cut."""
    fields = cfg.fields if fields is None else fields
    got = on_device(x, before, sweep, cfg, fields)
    after = P.split(x, before, sweep, cfg.spacing)
    field, conflicts = P.colour(x, after, cfg.n_grid, fields, sweep, reach_of(cfg))
    np.testing.assert_array_equal(got[0], after)
    np.testing.assert_array_equal(got[1], field)
    assert got[2] == conflicts
    assert got[3] == P.cut_off_side(x, before, after, sweep)
    np.testing.assert_array_equal(got[4], P.field_sides(x, field, fields, sweep, reach_of(cfg)))
    return after, got


def scene(name, n_grid, seed=0):
    cfg = SimConfig(n_grid=n_grid)
    x, _ = sample_object(name, POSE, spacing=cfg.spacing, seed=seed)
    assert len(x) < CAP
    return cfg, x.astype(np.float64)


def brute_adjacency(x, piece, n_grid, reach=P.REACH):
    """Pairs of pieces with some two base cells within ``reach`` (Chebyshev): every cell pair, by a KD-tree."""
    cell = np.floor(x * n_grid - 0.5)
    out = set()
    for p in range(piece.max() + 1):
        for q in range(p + 1, piece.max() + 1):
            a, b = np.unique(cell[piece == p], axis=0), np.unique(cell[piece == q], axis=0)
            if cKDTree(a).query(b, p=np.inf, distance_upper_bound=reach + 0.5)[0].min() <= reach:
                out.add((p, q))
    return out


@pytest.mark.parametrize("name", ["cube", "cake"])
@pytest.mark.parametrize("n_grid", [48, 64])
def test_separation_cuts_match_the_host(name, n_grid):
    cfg, x = scene(name, n_grid)
    first, got = check(x, np.zeros(len(x), np.int32), P.blade_sweep(KnifeAction(x=0.5, y=0.5), x, cfg)[0], cfg)
    assert first.max() == 1 and len(set(got[1][first == 0]) & set(got[1][first == 1])) == 0  # apart
    assert set(np.abs(got[4][:2])) == {1} and got[3] != 0  # each field on its own side; something cut off
    second, got = check(x, first, P.blade_sweep(KnifeAction(x=0.5, y=0.52, yaw=np.pi / 2), x, cfg)[0], cfg)
    assert second.max() == 3
    # the masks' adjacency is the brute force's: all four quarters touch (diagonals within REACH cells too)
    from topocut.sim.fields_device import _CACHE, _bits

    df = _CACHE[(1, n_grid)]
    adj = df.adj.to_numpy()[0]
    mask_pairs = {(p, q) for q in range(4) for p in _bits(adj[q]) if p < q}
    assert mask_pairs == brute_adjacency(x, second, n_grid) == P.adjacency(x, second, n_grid)


def test_random_planes_after_earlier_cuts_match_the_host():
    rng = np.random.default_rng(4949)
    for k in range(8):
        name, n_grid = ("cube", "cake")[k % 2], (48, 64)[(k // 2) % 2]
        cfg, x = scene(name, n_grid, seed=k)
        centre, piece = x.mean(0), np.zeros(len(x), np.int32)
        for _ in range(3):
            a = KnifeAction(x=float(centre[0] + rng.uniform(-0.05, 0.05)), y=float(centre[1] + rng.uniform(-0.05, 0.05)),
                            yaw=float(rng.uniform(-np.pi, np.pi)), tilt=float(rng.uniform(-0.5, 0.5)),
                            depth=None if rng.random() < 0.7 else float(rng.uniform(0.0, 0.1)))
            piece, _ = check(x, piece, P.blade_sweep(a.canonical(), x, cfg)[0], cfg)


def test_dice_with_too_few_fields_conflict_as_on_the_host():
    cfg, x = scene("cube", 48)
    piece = np.zeros(len(x), np.int32)
    lo, hi = x.min(0), x.max(0)
    for t in (0.3, 0.55, 0.8):  # three cuts along x, then three along y: a 4 x 4 grid of sticks
        piece, _ = check(x, piece, P.blade_sweep(KnifeAction(x=float(lo[0] + t * (hi[0] - lo[0])), y=0.5), x, cfg)[0], cfg)
    for t in (0.3, 0.55, 0.8):
        sweep = P.blade_sweep(KnifeAction(x=0.5, y=float(lo[1] + t * (hi[1] - lo[1])), yaw=np.pi / 2), x, cfg)[0]
        before = piece
        piece, got = check(x, before, sweep, cfg)
    assert piece.max() + 1 == 16
    conflicts = {cfg.fields: got[2]}
    for fields in (1, 2, 3, 16):  # a piece's neighbours within REACH cells reach past the next stick
        _, got = check(x, before, sweep, cfg, fields=fields)
        conflicts[fields] = got[2]
        assert got[1].max() < fields
    # one field: pieces - 1 (pieces.colour's count there); fewer fields, more neighbours sharing one; 16: none
    assert conflicts[1] == 15 and conflicts[2] > conflicts[3] >= conflicts[cfg.fields] > conflicts[16] == 0, conflicts


def test_labels_past_a_mask_leave_the_colouring_to_the_host():
    from topocut.sim.fields_device import MAX_PIECES, colour_batch
    from topocut.sim.pieces_device import device_split

    cfg, x = scene("cube", 48)
    ds = device_split(1, CAP)
    xs, ps = np.zeros((1, ds.n, 3)), np.zeros((1, ds.n), np.int32)
    xs[0, :len(x)] = x
    ps[0, :len(x)] = np.arange(len(x)) % (MAX_PIECES + 1)  # 65 labels before the cut (every one a flake)
    sweep = P.blade_sweep(KnifeAction(x=0.5, y=0.5), x, cfg)[0]
    labels = ds.run(xs, [len(x)], ps, [sweep], cfg.spacing)[:, :len(x)]
    body = body_field()
    body.fill(-7)
    assert colour_batch(ds, body, labels, ps[:, :len(x)], cfg.n_grid, cfg.fields, reach_of(cfg)) is None
    assert (body.to_numpy() == -7).all()  # nothing written


def test_env_cuts_with_the_device_fields_equal_the_host_path(taichi_one_thread, monkeypatch):
    """Three scenes, three rounds of cuts (one scene idle in one round): the blade plans, pieces, every particle's
    field, the fields' sides, the push's side, the field count and the conflicts are the host path's; so they are where
    labels outgrow the masks (MAX_PIECES lowered to 3 here) and the env falls back to colouring on the host."""
    from topocut.sim import fields_device
    from topocut.sim.env import CuttingEnv

    rounds = ([KnifeAction(x=0.5, y=0.5), KnifeAction(x=0.47, y=0.5, yaw=0.3), KnifeAction(x=0.45, y=0.5)],
              [None, KnifeAction(x=0.5, y=0.52, yaw=np.pi / 2), KnifeAction(x=0.55, y=0.5)],
              [KnifeAction(x=0.5, y=0.45, yaw=np.pi / 2), KnifeAction(x=0.5, y=0.47, yaw=np.pi / 2),
               KnifeAction(x=0.5, y=0.5, yaw=np.pi / 2)])
    seen, summaries = {}, {}
    for mode in ("off", "on", "on, masks of 3"):
        monkeypatch.setattr(fields_device, "MAX_PIECES", 3 if mode.endswith("3") else 64)
        calls = []
        monkeypatch.setattr(fields_device.DeviceFields, "summarise",
                            lambda self, *a, _f=fields_device.DeviceFields.summarise, _c=calls: _c.append(1) or _f(self, *a))
        env = CuttingEnv(SimConfig(n_grid=32, tuning=TuningConfig(device_split=mode.split(",")[0])), batch_size=3)
        env.reset("cube", POSE)
        seen[mode] = []
        for acts in rounds:
            env.cut(acts)
            s = env.solver
            seen[mode].append((env.piece.copy(), s.body.to_numpy()[:, :env.n].copy(), s.field_side.to_numpy().copy(),
                               env.push_side.copy(), int(s.n_fields[None]), env.field_conflicts,
                               [list(w) for w in env.sweeps]))  # the blade plans (plans_device when on)
        env.solver.destroy()
        summaries[mode] = len(calls)
    assert [r[0].max(1).tolist() for r in seen["off"]] == [[1, 1, 1], [1, 3, 2], [3, 5, 5]]
    # on the device every round; with masks of 3 only the first (labels before and after below 3)
    assert summaries == {"off": 0, "on": 3, "on, masks of 3": 1}, summaries
    for mode in ("on", "on, masks of 3"):
        for k, (host, dev) in enumerate(zip(seen["off"], seen[mode])):
            for name, h, d in zip(("piece", "body", "field_side", "push_side", "n_fields", "conflicts"), host, dev):
                np.testing.assert_array_equal(d, h, err_msg=f"{mode}, round {k}: {name}")
            assert dev[-1] == host[-1], f"{mode}, round {k}: sweeps"

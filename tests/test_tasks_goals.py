"""Task registry and goal shapes (issue #29): stick and dice differ, dice are dice, sticks have one long axis,
slices have the asked thickness; the oracle sequence is data (Cut / Turn).  Expectations are computed here
with numpy (principal extents of each piece from its own covariance), not with the reward's size code."""
import numpy as np
import pytest

from topocut.sim.objects import ObjectPose
from topocut.tasks import TASKS, Cut, Turn, get_task, make_goal, task_config

H = 1 / 128  # particle spacing of the 64^3 grid (half a cell)
OBJECTS = ("cube", "cake", "donut", "steak")
POSE = ObjectPose(yaw=0.3)  # cut planes oblique to the world-aligned particle lattice


def principal_extents(p, h=H):
    """Box-equivalent extents sqrt(12 var + h^2) along the principal axes, ascending (n layers -> n h)."""
    c = np.linalg.eigvalsh(np.cov(np.asarray(p, float).T, bias=True))
    return np.sqrt(12 * c + h * h)


def test_registry_names_every_task_and_its_module_docstring():
    for name in TASKS:
        t = get_task(name)
        assert t.name == name
        mod = __import__(type(t).__module__, fromlist=["x"])
        for word in ("Task.", "Randomisations.", "Success."):
            assert word in mod.__doc__, (name, word)
    with pytest.raises(ValueError, match="julienne.*valid: slice"):
        get_task("julienne")


@pytest.mark.parametrize("obj", OBJECTS)
def test_stick_and_dice_goals_differ_and_have_their_shapes(obj):
    st = make_goal(task_config("stick"), obj, POSE, H)
    di = make_goal(task_config("dice"), obj, POSE, H)
    size = task_config("dice").size
    assert len(di.fragments) >= 1 and len(st.fragments) >= 1
    same = len(st.fragments) == len(di.fragments) and all(
        a.shape == b.shape and np.array_equal(a, b) for a, b in zip(st.fragments, di.fragments))
    assert not same
    for f in di.fragments:  # every die: all three extents within 30% of the size (a flake of < 8 particles a chop
        e = principal_extents(f)  # cuts off joins its die, as in the simulator: the steak's die is 0.038 along one)
        assert np.all(np.abs(e / size - 1) <= 0.3), (obj, e)
    for f in st.fragments:  # every stick: one long axis
        e = principal_extents(f)
        assert e[2] >= 2 * e[0], (obj, e)
    # dice are cut after the slab is laid flat; the first step is always the slab cut
    assert isinstance(di.steps[0], Cut) and isinstance(di.steps[1], Turn)
    assert di.planes == [s.action for s in di.steps if isinstance(s, Cut)]


@pytest.mark.parametrize("obj", OBJECTS)
def test_every_slice_has_the_asked_thickness(obj):
    t = task_config("slice").thickness
    g = make_goal(task_config("slice", max_cuts=2), obj, POSE, H)
    for f in g.fragments:
        e = principal_extents(f)
        # the thinnest extent: along a1, the slab's normal (a ring's edge slab of the donut is curved: its
        # particles span the planes' distance exactly, so measure along a1 directly)
        s = f.astype(float) @ g.axes[0]
        assert abs((s.max() - s.min()) + H - t) <= H, (obj, s.max() - s.min())
        assert e[0] <= t + H


def test_turn_lays_the_slab_flat_on_the_board():
    """The dice oracle's turn: the slab's thickness (a1) becomes vertical, its lowest particle on the board."""
    g = make_goal(task_config("dice"), "cube", POSE, H)
    turn = g.turns[0]
    first = g.steps[0].action
    from topocut.sim.objects import sample_object

    pts, _ = sample_object("cube", POSE, H, board_z=0.05)
    p = pts.astype(float)
    slab = (p - first.plane_point(0.05)) @ first.normal
    slab = p[slab * np.sign(first.normal @ g.axes[0]) > 0]
    q = turn.transform(slab)
    assert np.ptp(q[:, 2]) == pytest.approx(np.ptp(slab @ g.axes[0]), abs=1e-9)  # thickness now vertical
    assert q[:, 2].min() == pytest.approx(0.05 + (slab @ g.axes[0]).min() - (slab @ g.axes[0]).mean()
                                          + np.ptp(slab @ g.axes[0]) / 2, abs=H)
    assert np.ptp(q @ g.axes[0]) == pytest.approx(np.ptp(slab[:, 2]), abs=1e-9)  # former height along a1
    assert (q @ g.axes[0]).min() > (p @ g.axes[0]).max()  # laid beyond the object
    assert (q @ g.axes[1]).min() > (p @ g.axes[1]).max()  # and beside it: stick cuts (normal to a2) miss the rest
    # after the turn, every cut plane crosses the laid slab
    for s in g.steps[2:]:
        d = (q - s.action.plane_point(0.05)) @ s.action.normal
        assert d.min() < 0 < d.max()


def test_success_asks_the_task():
    class R:
        total, cut_count, per_goal = 0.5, 2, np.zeros(2)

    cfg = task_config("slice")
    assert get_task("slice").success(R(), cfg)  # N_C = G
    R.cut_count = 1
    assert not get_task("slice").success(R(), cfg)

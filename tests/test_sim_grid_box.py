"""sim.grid_box: the grid clear and update visit only the box of nodes the last scatter wrote.

A node outside the box has no mass, so grid_op skips it either way: the box changes which nodes are
visited, never a value.  With the session's single CPU thread a batched cut, push and settle must
therefore agree bit for bit with the whole-grid path, and the box must be the particles' stencil
bounds worked out in numpy.
"""
import numpy as np
import pytest

from topocut.sim.action import KnifeAction
from topocut.sim.config import SimConfig

ACTIONS = [KnifeAction(0.5, 0.5, depth=5.0), KnifeAction(0.45, 0.5, yaw=0.3)]
SMALL = dict(n_grid=32, batch_size=2, push_substeps=40, settle_substeps=37)


def _run(grid_box: str):
    from topocut.sim.env import CuttingEnv

    env = CuttingEnv(SimConfig(**SMALL, grid_box=grid_box))
    assert env.solver is None or env.solver.use_box == (grid_box == "on")
    env.reset("cube")
    info = env.cut(ACTIONS)
    env.push()
    out = {f"{k}{b}": np.asarray(v) for b in range(env.B) for k, v in env.get_state(b).items()
           if k not in ("sweeps", "object")}
    out.update(force=info.force, work=info.work, newly=info.newly_damaged, Jp=env.solver.Jp.to_numpy())
    return env, out


@pytest.fixture(scope="module")
def runs():
    return _run("on"), _run("off")


def test_box_changes_no_value(runs):
    (env_on, on), (env_off, off) = runs
    assert env_on.solver.use_box and not env_off.solver.use_box
    assert on["newly"].min() > 0  # the knife cut both scenes
    for k in off:
        np.testing.assert_array_equal(on[k], off[k], err_msg=k)


def test_box_is_the_stencil_bounds_of_the_last_scatter(runs):
    (env, _), _ = runs
    s = env.solver
    x = s.x.to_numpy()[:, : env.n]  # B,N,3 after the last g2p
    env.simulate(1)  # one more substep: its scatter reads these positions
    base = np.clip(np.floor(x * s.n_grid - 0.5).astype(int), 0, s.n_grid - 3).reshape(-1, 3)
    expected = np.concatenate([base.min(0), base.max(0) + 3])
    np.testing.assert_array_equal(s.box.to_numpy(), expected)
    m = s.grid_m.to_numpy()  # B,n,n,n: every node with mass lies inside the box
    idx = np.argwhere(m > 0)[:, 1:]
    assert (idx >= expected[:3]).all() and (idx < expected[3:]).all()
    assert (expected[3:] - expected[:3] < s.n_grid).all()  # the cube fills a fraction of the grid


def test_grid_box_validation():
    with pytest.raises(ValueError, match=r"sim\.grid_box.*auto, on, off"):
        SimConfig(grid_box="maybe").validate()
    assert SimConfig().grid_box_enabled() and not SimConfig(arch="cuda").grid_box_enabled()
    assert SimConfig(arch="cuda", grid_box="on").grid_box_enabled()

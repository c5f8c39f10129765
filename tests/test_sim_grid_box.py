"""sim.tuning.grid_box: the grid clear and update visit only the box of nodes the last scatter wrote.

A node outside the box has no mass, so grid_op skips it either way: the box changes which nodes are
visited, never a value.  With the session's single CPU thread a batched cut, push and settle must
therefore agree bit for bit with the whole-grid path (the scatter's atomic loop: ``atomic_scatter``), and the box
must be the particles' stencil bounds worked out in numpy.  The spoon's sided scatter grows the same box.
"""
from contextlib import contextmanager

import numpy as np
import pytest

from topocut.sim.action import KnifeAction
from topocut.sim.config import SimConfig, TuningConfig

ACTIONS = [KnifeAction(0.5, 0.5, depth=5.0), KnifeAction(0.45, 0.5, yaw=0.3)]
SMALL = dict(n_grid=32, batch_size=2, push_time=0.008, settle_time=0.0074)


@contextmanager
def atomic_scatter():
    """Solvers built inside scatter in the threaded loop with atomic adds, even on one CPU thread: the box must leave
    its adds bit for bit unchanged.  One thread's serial loop (MPMSolver.serial_scatter) adds plainly, and the
    compiler may fuse those adds with their multiplies differently in the box's kernels and the whole grid's:
    float32 round-off (tests/test_sim_fused.py compares the two loops)."""
    import topocut.sim.mpm as mpm

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(mpm, "cpu_threads", lambda: 0)
        yield


def _run(grid_box: str):
    from topocut.sim.env import CuttingEnv

    env = CuttingEnv(SimConfig(**SMALL, tuning=TuningConfig(grid_box=grid_box)))
    assert env.solver is None or env.solver.use_box == (grid_box == "on")
    with atomic_scatter():
        env.reset("cube")
    assert not env.solver.serial_scatter
    info = env.cut(ACTIONS)
    env.push()
    out = {f"{k}{b}": np.asarray(v) for b in range(env.B) for k, v in env.get_state(b).items()
           if k not in ("sweeps", "object")}
    out.update(force=info.force, work=info.work, newly=info.newly_damaged, Jp=env.solver.Jp.to_numpy())
    return env, out


@pytest.fixture(scope="module")
def runs():
    return _run("on"), _run("off")


def test_the_gpus_box_loops_visit_the_same_nodes(runs):
    """The box's clear and update as CUDA runs them (a fixed number of threads, each reading the box's bounds and
    striding over the flattened (scene, field, node) index), here on the CPU with 97 threads so that each thread
    takes many nodes: the same cut and push as the ranged loops.  The update's float contraction may differ between
    the two loops, so positions agree to float32 rounding and the damage flags exactly."""
    import topocut.sim.mpm as mpm

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(mpm, "box_loop_threads", lambda arch: 97)
        env, strided = _run("on")
    assert env.solver.box_threads == 97 and env.solver.use_box
    (_, ranged), _ = runs
    assert strided["newly"].min() > 0
    for b in range(env.B):
        np.testing.assert_array_equal(strided[f"damage{b}"], ranged[f"damage{b}"])
        np.testing.assert_allclose(strided[f"x{b}"], ranged[f"x{b}"], rtol=0, atol=1e-5)
    np.testing.assert_allclose(strided["force"], ranged["force"], rtol=1e-3, atol=1e-6)


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
    with pytest.raises(ValueError, match=r"sim\.tuning\.grid_box: 'maybe'; valid: auto, on, off"):
        SimConfig(tuning=TuningConfig(grid_box="maybe")).validate()
    auto = TuningConfig()
    assert auto.grid_box_enabled("cpu", 1) and auto.grid_box_enabled("cuda", 16)
    assert not auto.grid_box_enabled("cuda", 1)  # a single GPU scene (measured when the box still had serial tasks)
    assert not TuningConfig(grid_box="off").grid_box_enabled("cuda", 16)
    # on CUDA the box's loops flatten (scene, field, node) into one 32-bit index: refused where it would overflow
    big = dict(arch="cuda", n_grid=256, batch_size=64, fields=2, tuning=TuningConfig(warp_scatter="off"))
    with pytest.raises(ValueError, match=r"sim\.tuning\.grid_box: the box loops' node indices .* overflow 32 bits"):
        SimConfig(**big).validate()
    SimConfig(**{**big, "batch_size": 63}).validate()  # 63 * 2 * 256^3 < 2^31
    SimConfig(**{**big, "tuning": TuningConfig(warp_scatter="off", grid_box="off")}).validate()


def _spoon_run(grid_box: str):
    """A sided (spoon) substep, then solver substeps, then sided ones with the spoon pressing into a block."""
    from topocut.sim.env import CuttingEnv
    from topocut.sim.spoon import ToolColliders, bowl_axis
    from topocut.tasks.config import SpoonConfig
    from topocut.tasks.scooping_scene import block_particles

    sim = SimConfig(n_grid=32, tuning=TuningConfig(grid_box=grid_box))
    sp = SpoonConfig()
    env = CuttingEnv(sim)
    x = block_particles(sp, sim.spacing, sim.board_z, seed=0)
    with atomic_scatter():
        env.load_particles(x, np.zeros(len(x), np.int32))
    s = env.solver
    assert not s.serial_scatter
    tools = ToolColliders(s, sp)
    top = float(x[:, 2].max())
    centre = np.array([*sp.block_center, top + sp.radius * 0.3])  # the bowl half sunk in the block
    tools.set_pose(np.stack([centre, bowl_axis(0.6), [0.0, 0.0, -0.05], [0.0, 0.0, 0.0]])[None])
    for k in range(24):
        sided = k < 8 or k >= 16  # switch to the solver's p2g and back: the box must follow both scatters
        if sided:
            tools.p2g_sided(env.n, k)
        else:
            s.p2g(env.n, k)
        s.grid_op(k * env.dt, 0)
        tools.collide_tools()
        if sided:
            tools.g2p_sided(env.n, k)
        else:
            s.g2p(env.n, k, k * env.dt)
    return s.x.to_numpy()[0, :env.n], s.v.to_numpy()[0, :env.n]


def test_spoon_sided_scatter_with_box_equals_whole_grid():
    (x_on, v_on), (x_off, v_off) = _spoon_run("on"), _spoon_run("off")
    assert np.abs(v_on).max() > 1e-3  # the spoon moved material
    np.testing.assert_array_equal(x_on, x_off)
    np.testing.assert_array_equal(v_on, v_off)

"""Graph stepping (MPMSolver.advance: k substeps per Python call) against per-phase calls, and the SVD rotation.

``sim.tuning.fuse_substeps`` only changes who launches the kernels (a ti.graph from C++
instead of three Python calls per substep): the same kernels get the same
arguments, so with the session's single CPU thread the two paths must agree bit
for bit, over a batched cut with the knife, a push and the settling.
"""
import numpy as np
import pytest

from topocut.sim.action import KnifeAction
from topocut.sim.config import SimConfig, TuningConfig

ACTIONS = [KnifeAction(0.5, 0.5, depth=5.0), KnifeAction(0.45, 0.5, yaw=0.3)]
SMALL = dict(n_grid=32, batch_size=2, push_time=0.008, settle_time=0.0074)  # 37: a chunk of 16 and a rest


def _env(**kw):
    from topocut.sim.env import CuttingEnv

    return CuttingEnv(SimConfig(**{**SMALL, **kw}))


@pytest.fixture(scope="module")
def env():
    return _env()


def _run(env, fuse, knife_mode="wedge"):
    """Cut both scenes, push, settle; every array the env exposes afterwards."""
    env.fuse, env.cfg.knife_mode = fuse, knife_mode  # both are read per call: one compiled env serves all runs
    env.reset("cube")
    info = env.cut(ACTIONS)
    env.push()
    out = {f"{k}{b}": np.asarray(v) for b in range(env.B) for k, v in env.get_state(b).items()
           if k not in ("sweeps", "object")}
    out.update(force=info.force, peak=info.peak_force, work=info.work, newly=info.newly_damaged,
               Jp=env.solver.Jp.to_numpy())
    return out, info.substeps


@pytest.mark.parametrize("knife_mode", ["wedge", "sticky"])  # contact 0 and 1 in grid_op
def test_graph_stepping_matches_per_phase_calls_bit_for_bit(env, knife_mode):
    fused, steps = _run(env, 16, knife_mode)
    plain, _ = _run(env, 1, knife_mode)
    assert steps % 16 != 0  # the cut ran whole graph chunks and a per-phase rest
    assert fused["newly"].min() > 0 and fused["work"].min() > 0  # the knife really cut both scenes
    for k in plain:
        np.testing.assert_array_equal(fused[k], plain[k], err_msg=k)


def test_divergence_inside_a_graph_chunk_names_the_step(env):
    from topocut.sim.env import SimulationDiverged

    env.fuse, env.cfg.knife_mode = 16, "wedge"
    env.reset("cube")
    env.simulate(20)  # step_count is no longer a multiple of 16
    state = env.get_state(0)
    state["F"] = np.broadcast_to(np.eye(3) * 4.0, state["F"].shape).copy()  # J = 64 > j_max from the first step
    env.set_state(state, b=1)
    first = env.step_count
    with pytest.raises(SimulationDiverged, match=rf"substep {first} \(scene 1\)"):
        env.simulate(32)  # two whole chunks, no per-phase call


def test_advance_falls_back_to_python_calls_without_kernel_graphs(env, monkeypatch):
    import taichi as ti

    env.fuse = 16
    env.reset("cube")
    env.simulate(40)
    graphs, expected = env.solver._graphs, env.get_state(1)

    def no_graphs():
        raise RuntimeError("not on this backend")

    monkeypatch.setattr(ti.graph, "GraphBuilder", no_graphs)
    env.solver._graphs = {}
    env.reset("cube")
    with pytest.warns(RuntimeWarning, match="ti.graph unavailable.*not on this backend"):
        env.simulate(40)
    for k in ("x", "v", "C", "F"):
        np.testing.assert_array_equal(env.get_state(1)[k], expected[k])
    env.solver._graphs = graphs


def test_svd_rotation_matches_polar_iteration(env):
    """sim.tuning.core_rotation=svd (the GPU default) takes R = U V^T for the healthy core instead of Newton's polar
    iteration: the same rotation, so the same cut up to float rounding."""
    polar, _ = _run(env, 16)
    svd_env = _env(tuning=TuningConfig(core_rotation="svd"))
    svd, _ = _run(svd_env, 16)
    assert svd_env.solver.rotation == "svd" and env.solver.rotation == "polar"
    dx = env.cfg.dx
    for b in range(2):
        assert np.abs(svd[f"x{b}"] - polar[f"x{b}"]).max() < 0.05 * dx
        assert (svd[f"damage{b}"] == polar[f"damage{b}"]).mean() > 0.98
    np.testing.assert_allclose(svd["work"], polar["work"], rtol=0.01)
    svd_env.solver.destroy()


def test_stepping_options_are_validated():
    with pytest.raises(ValueError, match=r"sim\.tuning\.core_rotation: 'qr'; valid: auto, polar, svd"):
        SimConfig(tuning=TuningConfig(core_rotation="qr")).validate()
    with pytest.raises(ValueError, match=r"sim\.tuning\.fuse_substeps: 0 must lie in \[1, 256\]"):
        SimConfig(tuning=TuningConfig(fuse_substeps=0)).validate()
    assert TuningConfig().core_rotation_method("cuda") == "svd"
    assert TuningConfig().core_rotation_method("cpu") == "polar"


def test_one_cpu_thread_scatters_in_a_serial_loop_with_the_parallel_loops_result(env, monkeypatch):
    """With one CPU thread (this session's) the scatter runs as a serial loop, whose atomic adds Taichi compiles as
    plain ones (Scatter.scatter); the parallel loop it replaces gives the same pieces, damage and masses, and the
    particles within float32 round-off (fused multiply-adds) as the push and settling amplify it: positions within
    1% of a cell (8.1e-5 = 0.26% of a cell on CI's machine and on 2026-12-02's, where 1e-5 had held on the
    machine that wrote the test), velocities within 10% of the fastest particle's speed (measured 5.1%:
    scene 0's pieces still slide after the push).  A loop that drops or doubles a particle's share moves the pieces
    by cells."""
    import topocut.sim.mpm as mpm

    serial, _ = _run(env, 16)
    assert env.solver.serial_scatter  # the session's Taichi runs one thread
    monkeypatch.setattr(mpm, "cpu_threads", lambda: 2)  # a solver that takes the runtime for a threaded one
    threaded_env = _env()
    threaded, _ = _run(threaded_env, 16)
    assert not threaded_env.solver.serial_scatter
    assert serial["newly"].min() > 0  # the knife cut both scenes
    for k in ("piece0", "piece1", "damage0", "damage1", "body0", "body1", "newly"):
        np.testing.assert_array_equal(serial[k], threaded[k], err_msg=k)
    dx = env.cfg.dx
    for b in range(2):
        np.testing.assert_allclose(serial[f"x{b}"], threaded[f"x{b}"], rtol=0, atol=0.01 * dx, err_msg=f"x{b}")
        speed = np.abs(threaded[f"v{b}"]).max()
        np.testing.assert_allclose(serial[f"v{b}"], threaded[f"v{b}"], rtol=0, atol=0.1 * speed, err_msg=f"v{b}")

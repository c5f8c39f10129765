"""sim.tuning.resort_every: the scatter visits each scene's particles in base-cell order, re-sorted as they move.

Only the visiting order changes (MPMSolver.order): every particle is scattered exactly once, the grid
gets the same sums up to float summation order, and the particles keep their indices for every API.
Checked on the CPU (one thread: ranks in a cell follow memory order) against numpy's stable sort of
cell keys, grid mass sums worked out by hand, and the
same cut without re-sorting.  (The CUDA warp scatter uses it by default; its check is in
tests/test_sim_warp_scatter.py.)
"""
import numpy as np
import pytest

from topocut.sim import CuttingEnv, KnifeAction, SimConfig, TuningConfig

N_GRID = 32


def cell_keys(x: np.ndarray, n: int = N_GRID) -> np.ndarray:
    cell = np.floor(x * n - 0.5).astype(np.int64)  # the solver's base node
    return (cell[:, 0] * n + cell[:, 1]) * n + cell[:, 2]


def shuffled_block(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (0.35 + 0.3 * rng.random((n, 3))).astype(np.float32)


def test_resort_interval_config():
    assert TuningConfig().resort_interval("cuda") == 64  # auto: with the warp scatter
    assert TuningConfig(warp_scatter="off").resort_interval("cuda") == 0
    assert TuningConfig().resort_interval("cpu") == 0 and TuningConfig(resort_every=8).resort_interval("cpu") == 8
    with pytest.raises(ValueError, match=r"sim\.tuning\.resort_every: -2; valid: -1 \(auto\), 0"):
        SimConfig(tuning=TuningConfig(resort_every=-2)).validate()
    with pytest.raises(ValueError, match=r"sim\.tuning\.resort_every: cell indices overflow 32 bits"):
        SimConfig(n_grid=128, batch_size=1024, tuning=TuningConfig(resort_every=16)).validate()


def test_order_is_each_scenes_stable_cell_sort():
    env = CuttingEnv(SimConfig(n_grid=N_GRID, batch_size=2, tuning=TuningConfig(resort_every=16)))
    x0 = shuffled_block(700, 0)
    env.load_particles(x0, np.zeros(len(x0), np.int32))
    x1 = x0[::-1].copy()  # scene 1: the same points in reverse memory order, so its visiting order differs
    env.set_state({"x": x1, "material": np.zeros(len(x1), np.int32)}, b=1)
    s = env.solver
    order = s.order.to_numpy()  # B,lanes
    for b, x in enumerate((x0, x1)):
        np.testing.assert_array_equal(order[b, :700], np.argsort(cell_keys(x), kind="stable"))
        np.testing.assert_array_equal(order[b, 700:], np.arange(700, s.lanes))  # appended particles: in place
    assert not np.array_equal(order[0, :700], order[1, :700])
    # without re-sorting the scatter visits memory order
    plain = CuttingEnv(SimConfig(n_grid=N_GRID, tuning=TuningConfig(resort_every=0)))
    plain.load_particles(x0, np.zeros(len(x0), np.int32))
    np.testing.assert_array_equal(plain.solver.order.to_numpy()[0], np.arange(plain.solver.lanes))


def test_every_particle_scattered_once_when_the_count_shrinks():
    env = CuttingEnv(SimConfig(n_grid=N_GRID, tuning=TuningConfig(resort_every=16)))
    x = shuffled_block(900, 1)
    mat = (np.arange(900) % 3 == 0).astype(np.int32)  # a third skin (rho 1), the rest core (rho 4)
    env.load_particles(x, mat)
    vol = env.cfg.spacing ** 3
    for n in (900, 451):  # 451: the old order held particles >= 451 in slots < 451
        env.set_state({"x": x[:n], "material": mat[:n]}, b=None)
        s = env.solver
        s.p2g(env.n, 0)
        want = vol * (env.cfg.rho_skin * mat[:n].sum() + env.cfg.rho_core * (n - mat[:n].sum()))
        assert abs(s.grid_m.to_numpy().sum() - want) < 1e-5 * want, n


def _cut(resort_every: int):
    env = CuttingEnv(SimConfig(n_grid=N_GRID, batch_size=2, push_time=0.008, settle_time=0.008,
                               tuning=TuningConfig(resort_every=resort_every)))
    env.reset("cube")
    env.cut([KnifeAction(0.5, 0.5, depth=5.0), KnifeAction(0.45, 0.5, yaw=0.3)])
    env.push()
    return env


def test_resorted_cut_matches_memory_order_cut():
    a, b = _cut(0), _cut(16)
    sa, sb = a.state(), b.state()
    assert sb.damage.sum(axis=1).min() > 50  # the knife cut both scenes
    assert np.abs(sa.x - sb.x).max() < 0.01 / N_GRID  # float summation order alone (5.5e-6 measured)
    assert (sa.damage == sb.damage).mean() > 0.999
    # the last re-sort followed the particles: its order is the stable cell sort of where they were then
    b.simulate(16 - b.step_count % 16)  # up to the next multiple of 16: a re-sort at the end
    x, order = b.state().x, b.solver.order.to_numpy()
    for k in range(2):
        np.testing.assert_array_equal(order[k, :b.n], np.argsort(cell_keys(x[k]), kind="stable"))
    assert not np.array_equal(order[0, :b.n], np.arange(b.n))  # the cut moved particles across cells

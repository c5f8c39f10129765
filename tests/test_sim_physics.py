"""MLS-MPM physics against analytic numbers: free fall, rest on the board, momentum, cuts, push, divergence.

Small on purpose (n_grid 32, ~1.5k particles); two envs = two kernel compilations.
CPU atomics make runs reproducible only up to float rounding order, so the
same-seed test compares with a tolerance.
"""
import numpy as np
import pytest

from topocut.sim.action import KnifeAction
from topocut.sim.config import SimConfig
from topocut.sim.objects import sample_sdf

HALF = np.array([0.15, 0.08, 0.06])  # test block half sizes


def block(cfg, z0=None):
    """Jittered particles of a box centred at (0.5, 0.5), bottom at z0 (default: on the board)."""
    z0 = cfg.board_z if z0 is None else z0
    c = np.array([0.5, 0.5, z0 + HALF[2]])
    sdf = lambda p: (np.abs(p - c) - HALF).max(-1)  # noqa: E731 (Chebyshev box distance, exact inside)
    return sample_sdf(sdf, c - HALF, c + HALF, cfg.spacing, cfg.skin_thickness, seed=0)


@pytest.fixture(scope="module")
def env():
    from topocut.sim.env import CuttingEnv

    return CuttingEnv(SimConfig(n_grid=32, batch_size=2))


@pytest.fixture(scope="module")
def free_env():
    from topocut.sim.env import CuttingEnv

    return CuttingEnv(SimConfig(n_grid=32, gravity=0.0, board=False, walls=False), batch_size=1)


def test_cfl_violation_names_key_and_bound():
    cfg = SimConfig(n_grid=64, dt=1e-3)
    bound = cfg.dx / (np.sqrt((cfg.lam + 2 * cfg.mu) / cfg.rho_skin) + cfg.knife_speed
                      + 2 * np.pi * cfg.osc_frequency * cfg.osc_amplitude)
    with pytest.raises(ValueError, match=rf"sim\.dt.*{bound:.3g}"):
        cfg.validate()
    SimConfig(n_grid=64, dt=0.99 * bound).validate()
    with pytest.raises(ValueError, match="push_mode.*separate"):
        SimConfig(push_mode="shove").validate()


def test_free_fall_matches_half_g_t_squared(env):
    cfg = env.cfg
    x, mat = block(cfg, z0=0.5)
    env.load_particles(x, mat)
    k = 500
    env.simulate(k)
    st = env.state()
    t = k * env.dt
    drop = x[:, 2].mean() - st.x[:, :, 2].mean(1)  # B,
    np.testing.assert_allclose(drop, 0.5 * cfg.gravity * t ** 2, rtol=0.01)
    np.testing.assert_allclose(st.v[:, :, 2].mean(1), -cfg.gravity * t, rtol=0.01)
    assert np.abs(np.linalg.det(env.solver.F.to_numpy()[:, :env.n]) - 1).max() < 1e-3  # falls undeformed
    assert not st.damage.any()


def test_block_rests_on_board_without_drift(env):
    cfg = env.cfg
    x, mat = block(cfg)
    env.load_particles(x, mat)
    env.simulate(2000)
    st = env.state()
    J = env.solver.Jp.to_numpy()[:, :env.n]
    assert np.abs(J - 1).max() < 0.01  # static strain rho g h / E ~ 5e-4
    drift = st.x.mean(1) - x.mean(0)  # B,3
    assert np.abs(drift[:, :2]).max() < 0.05 * cfg.dx
    assert np.abs(drift[:, 2]).max() < 0.5 * cfg.dx
    assert np.abs(st.v).max() < 0.05 and not st.damage.any()


def test_linear_momentum_is_conserved_without_boundaries(free_env):
    env = free_env
    x, mat = block(env.cfg, z0=0.4)
    rng = np.random.default_rng(0)
    c = x.mean(0)
    v = np.array([0.2, -0.1, 0.05]) + np.cross([0.0, 0.0, 2.0], x - c) + rng.normal(0, 0.05, x.shape)
    env.load_particles(x, mat, v=v.astype(np.float32))
    mass = np.where(mat == 1, env.cfg.rho_skin, env.cfg.rho_core) * env.cfg.spacing ** 3  # N,
    p0 = (mass[:, None] * v).sum(0)
    env.simulate(300)
    p1 = (mass[:, None] * env.state().v[0]).sum(0)
    np.testing.assert_allclose(p1, p0, atol=1e-4 * np.abs(p0).max())


ACTIONS = [KnifeAction(0.5, 0.5, depth=5.0), KnifeAction(0.45, 0.5, yaw=0.3)]


@pytest.fixture(scope="module")
def cut(env):
    x, mat = block(env.cfg)
    env.load_particles(x, mat)
    info = env.cut(ACTIONS)
    return x, info, env.state()


def _signed(x, a, board_z):
    return (x - a.plane_point(board_z)) @ a.normal


def test_cut_damages_a_band_around_each_blade_plane(env, cut):
    """The blade damages its kerf (docs/sim.md, "Contact"): the particles within ``kerf`` of its plane, half a
    particle spacing at this grid (wider than the 2 mm blade), and next to nothing a few spacings away."""
    x0, info, st = cut
    kerf, h = env.cfg.kerf, env.cfg.spacing
    assert kerf == max(env.cfg.knife_half_thickness, 0.5 * h)
    for b, a in enumerate(ACTIONS):  # each scene around its own plane
        d = np.abs(_signed(x0, a, env.cfg.board_z))
        assert (d <= 0.9 * kerf).sum() > 20
        assert st.damage[b][d <= 0.9 * kerf].mean() > 0.9
        # not the contact's inflated box (half a cell more on each side): that made 40% of a 3 cm slab mush
        assert st.damage[b][(d > kerf + 0.25 * h) & (d <= kerf + 2 * h)].mean() < 0.05
        assert st.damage[b][d > kerf + 3 * h].mean() < 0.05
        assert info.newly_damaged[b] == st.damage[b].sum()
        assert info.work[b] > 0 and info.peak_force[b] > 0


def test_knife_stops_at_the_board(env, cut):
    x0, info, st = cut
    bz = env.cfg.board_z
    np.testing.assert_allclose(info.knife_end[:, 2], bz, atol=1e-6)  # scene 0 asked for depth 5
    for sw in info.sweeps:
        o, u, w, n = sw.as_arrays()
        assert abs(o[2] + w[2] * sw.depth - bz) < 1e-6 and o[2] > x0[:, 2].max()
        assert abs(n @ u) < 1e-9 and abs(n @ w) < 1e-9
    assert st.sweeps[0][0] == info.sweeps[0]
    assert st.x[:, :, 2].min() > bz - 0.5 * env.cfg.dx  # nothing pushed through the board


def test_same_seed_gives_the_same_cut_and_push_opens_a_gap(env, cut):
    x0, info, st = cut
    x, mat = block(env.cfg)
    env.load_particles(x, mat)
    info2 = env.cut(ACTIONS)
    st2 = env.state()
    assert np.abs(st2.x - st.x).max() < 0.1 * env.cfg.dx  # same up to the order of CPU atomic adds
    assert (st2.damage == st.damage).mean() > 0.98
    np.testing.assert_allclose(info2.work, info.work, rtol=0.05)
    env.push()
    st3 = env.state()
    for b, a in enumerate(ACTIONS):
        d0 = _signed(x0, a, env.cfg.board_z)
        keep = np.abs(d0) > 1.5 * env.cfg.dx  # particles the blade itself did not reach
        d3 = _signed(st3.x[b], a, env.cfg.board_z)
        gap = d3[keep & (d0 > 0)].min() - d3[keep & (d0 < 0)].max()
        assert gap > 0.5 * env.cfg.spacing, f"scene {b}: gap {gap:.4f}"


def test_get_set_state_round_trip(env):
    x, mat = block(env.cfg)
    env.load_particles(x, mat)
    env.simulate(20)
    s1 = env.get_state(1)
    env.load_particles(x + 0.01, mat)
    env.set_state(s1, b=0)
    s0 = env.get_state(0)
    for k in ("x", "v", "C", "F", "sigma_y", "damage", "material"):
        np.testing.assert_array_equal(s0[k], s1[k])
    assert np.abs(env.get_state(1)["x"] - (x + 0.01)).max() < 1e-6  # scene 1 untouched


def test_divergence_names_the_step(env):
    from topocut.sim.env import SimulationDiverged

    x, mat = block(env.cfg)
    env.load_particles(x, mat)
    state = env.get_state(0)
    state["F"] = np.broadcast_to(np.eye(3) * 4.0, state["F"].shape).copy()  # J = 64 > j_max
    env.set_state(state, b=1)
    first = env.step_count
    with pytest.raises(SimulationDiverged, match=rf"substep {first} \(scene 1\)") as e:
        env.simulate(5)
    assert e.value.step == first and e.value.scene == 1


def test_damaged_skin_holds_no_shear(free_env):
    """Skin under a shear below its yield strain: healthy skin keeps it (elastic), damaged skin (docs/sim.md:
    zero yield stress) is returned to the von Mises surface of radius 0, i.e. to equal principal stretches."""
    from topocut.sim.objects import SKIN

    x, mat = block(free_env.cfg, z0=0.4)
    free_env.load_particles(x, mat)
    n, gamma = len(x), 0.01  # Hencky deviatoric norm ~0.0041 (principal stretches 1 ± gamma/2) < 0.0144 yield
    shear = np.eye(3)
    shear[0, 1] = gamma
    state = free_env.get_state(0)
    state.update(material=np.full(n, SKIN, np.int32), F=np.broadcast_to(shear, (n, 3, 3)).copy(),
                 damage=np.arange(n) < n // 2, v=np.zeros((n, 3)), C=np.zeros((n, 3, 3)))
    free_env.set_state(state, b=None)
    free_env.simulate(1)
    s = np.linalg.svd(free_env.get_state(0)["F"], compute_uv=False)  # N,3 principal stretches
    spread = s[:, 0] / s[:, 2]
    np.testing.assert_allclose(spread[: n // 2], 1.0, atol=1e-4)  # damaged: no deviatoric strain left
    np.testing.assert_allclose(spread[n // 2:], (1 + gamma / 2) / (1 - gamma / 2), rtol=2e-3)  # healthy: elastic


def test_cut_substeps_that_outrun_the_cfl_bound_are_refused(env, monkeypatch):
    """cut_substeps sets the knife speed; at cfl=1 (dt = dx / (c + v_knife + osc)) any faster knife breaks the
    CFL condition although it moves less than half a cell per substep."""
    cfg = env.cfg
    env.load_particles(*block(cfg))
    monkeypatch.setattr(env, "dt", cfg.cfl_bound())  # as sim.cfl=1
    monkeypatch.setattr(cfg, "cut_substeps", 13)
    depth = block(cfg)[0][:, 2].max() + cfg.knife_clearance + cfg.margin - cfg.board_z
    speed = depth / (13 * env.dt)
    assert speed * env.dt < 0.5 * cfg.dx and speed > cfg.knife_speed  # the half-cell rule alone lets it pass
    with pytest.raises(ValueError, match=r"sim\.cut_substeps=13 drives the knife at .* CFL bound"):
        env.cut(KnifeAction(0.5, 0.5))


def test_config_ranges_and_gif_timing(tmp_path):
    for kw, key in ((dict(tuning=dict(check_every=0)), "tuning.check_every"), (dict(dwell_time=-1.0), "dwell_time"),
                    (dict(j_min=1.2), "j_min"), (dict(friction=-0.1), "friction")):
        with pytest.raises(ValueError, match=rf"sim\.{key}"):
            SimConfig(**kw).validate()
    from topocut.sim.env import CuttingEnv

    # the batch the env is built with, not the config's default, decides the warp-scatter key range
    with pytest.raises(ValueError, match=r"sim\.tuning\.warp_scatter: run keys .* batch_size=16"):
        CuttingEnv(SimConfig(arch="cuda", n_grid=512), batch_size=16)
    from PIL import Image

    from topocut.sim.render import write_gif

    frames = [np.full((8, 8, 3), v, np.uint8) for v in (0, 120, 250)]
    with Image.open(write_gif(frames, tmp_path / "a.gif", fps=2)) as im:
        assert im.n_frames == 3 and im.info["duration"] == 500  # ms per frame at 2 frames/s

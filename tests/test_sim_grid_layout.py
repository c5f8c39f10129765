"""sim.tuning.grid_layout: grid mass and momentum in one struct per node (aos) or one array per component (soa).

The layout moves where a node's four floats live, never what is added to them: with the session's single
CPU thread (atomics in a fixed order) one p2g must give the same grid bit for bit, and a batched cut and
push the same damage with positions equal up to float contraction (the compiler fuses multiply-adds
differently around other address arithmetic; ~1e-3 dx after a cut).  The soa grid must really be four
separate arrays (the GPU default; its timings and GPU p2g check are in docs/benchmarks.md).
"""
import numpy as np
import pytest
from taichi.lang.field import ScalarField

from topocut.sim.action import KnifeAction
from topocut.sim.config import SimConfig, TuningConfig
from topocut.sim.objects import sample_object


def _run(layout: str):
    from topocut.sim.env import CuttingEnv

    env = CuttingEnv(SimConfig(n_grid=32, batch_size=2, push_time=0.006, tuning=TuningConfig(grid_layout=layout)))
    env.reset("cube")
    info = env.cut([KnifeAction(0.5, 0.5, depth=5.0), KnifeAction(0.45, 0.5, yaw=0.3)])
    env.push()
    st = env.state()
    return env, dict(x=st.x, damage=st.damage, force=info.force, work=info.work)


@pytest.fixture(scope="module")
def runs():
    return _run("aos"), _run("soa")


def test_one_p2g_is_bit_identical(runs):
    x = sample_object("ham", seed=1, spacing=0.5 / 32)[0][:3000]  # fewer than the cube's: the same kernels
    v = np.random.default_rng(0).normal(size=x.shape).astype(np.float32)
    grids = []
    for env, _ in runs:
        env.load_particles(x.astype(np.float32), np.zeros(len(x), np.int32), v=v)
        env.solver.p2g(env.n, 0)
        grids.append((env.solver.grid_m.to_numpy(), env.solver.grid_v.to_numpy()))
    (m0, v0), (m1, v1) = grids
    assert abs(m0.sum() - 2 * len(x) * env.solver.vol * env.cfg.rho_core) < 1e-4 * m0.sum()  # all mass landed
    np.testing.assert_array_equal(m0, m1)
    np.testing.assert_array_equal(v0, v1)


def test_layouts_give_the_same_cut(runs):
    (env, aos), (_, soa) = runs
    assert aos["damage"].sum() > 0  # the knife cut
    np.testing.assert_array_equal(aos["damage"], soa["damage"])
    assert np.abs(aos["x"] - soa["x"]).max() < 0.01 * env.cfg.dx
    # summation order differs between layouts; the contact between piece fields amplifies it in small components
    np.testing.assert_allclose(aos["force"], soa["force"], atol=3e-2 * np.abs(aos["force"]).max())
    np.testing.assert_allclose(aos["work"], soa["work"], rtol=5e-3)


def test_soa_places_each_component_in_its_own_array(runs):
    (env_aos, _), (env_soa, _) = runs

    def parents(s):  # the dense SNode holding each of m, v_x, v_y, v_z
        return [f.snode.parent() for f in (s.grid_m, *(ScalarField(e) for e in s.grid_v._get_field_members()))]

    a, s = parents(env_aos.solver), parents(env_soa.solver)
    assert len({p.ptr.id for p in a}) == 1  # one struct per node
    assert len({p.ptr.id for p in s}) == 4
    assert all(p.shape == (2 * env_soa.cfg.fields, 32, 32, 32) for p in s)  # slot b * K + f


def test_grid_layout_config():
    assert TuningConfig().grid_layout_method("cpu") == "aos" and TuningConfig().grid_layout_method("cuda") == "soa"
    assert TuningConfig(grid_layout="aos").grid_layout_method("cuda") == "aos"
    with pytest.raises(ValueError, match=r"sim\.tuning\.grid_layout: 'rows'; valid: auto, aos, soa"):
        SimConfig(tuning=TuningConfig(grid_layout="rows")).validate()

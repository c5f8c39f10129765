"""pieces.blade_sweep on the simulator's float32 positions (CuttingEnv.cut's blade plans) equals it on their
float64 conversion to the last bit: the sweep (origin, frame, depth), the depth and the start point, for random
planes (yaw, tilt, offset; some with a stopping depth or a start height) over four scenes.  Its band of particles
(``_in_band``: a cheap candidate pass, then the exact test) equals the exact test on every particle, for particles
spread over objects and for particles within a few float32 ulps of the band's edges on tilted planes.
"""
import numpy as np
import pytest

from topocut.sim import pieces as P
from topocut.sim.action import KnifeAction
from topocut.sim.config import SimConfig
from topocut.sim.objects import ObjectPose, sample_object

CFG = SimConfig(n_grid=64)


def scenes():
    """Four scenes (cake, cube, ditto, a jittered cake moved aside), float32 (n_b,3) each."""
    rng = np.random.default_rng(3)
    xs = [sample_object(name, ObjectPose(x=0.5, y=0.5, yaw=yaw, scale=1.0), spacing=CFG.spacing, seed=1)[0]
          for name, yaw in (("cake", 0.1), ("cube", 0.0), ("ditto", 0.7))]
    xs.append(xs[0] + np.array([0.03, -0.02, 0.0]) + rng.normal(0, 1e-3, xs[0].shape))
    return [x.astype(np.float32) for x in xs]


def actions(rng, k):
    return [KnifeAction(x=0.5 + rng.uniform(-0.05, 0.05), y=0.5 + rng.uniform(-0.05, 0.05), yaw=rng.uniform(-3.2, 3.2),
                        tilt=rng.uniform(-0.5, 0.5), depth=None if rng.random() < 0.7 else rng.uniform(0.01, 0.08),
                        z_start=None if rng.random() < 0.8 else rng.uniform(0.1, 0.2)) for _ in range(k)]


def exact(x, p0, n, band):
    """Every particle's band test, term by term in float64: the reference _in_band's candidates must not change."""
    q = x.astype(np.float64)
    r = q - p0
    return q[np.abs(r[:, 0] * n[0] + r[:, 1] * n[1] + r[:, 2] * n[2]) <= band]


def test_float32_positions_plan_as_their_float64_conversion():
    rng = np.random.default_rng(0)
    compared = 0
    for x in scenes():
        for a in actions(rng, 12):
            got, want = P.blade_sweep(a, x, CFG), P.blade_sweep(a, x.astype(np.float64), CFG)
            assert got[0] == want[0] and got[1] == want[1] and np.array_equal(got[2], want[2]), a
            compared += 1
    assert compared == 48


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_band_equals_the_exact_test_on_every_particle(dtype):
    rng = np.random.default_rng(1)
    for x in scenes():
        x = x.astype(dtype)
        for a in actions(rng, 8):
            a = a.canonical()
            p0, n = a.plane_point(CFG.board_z), a.normal
            got, want = P._in_band(x, p0, n, P.CENTRE_BAND), exact(x, p0, n, P.CENTRE_BAND)
            assert got.dtype == np.float64 and np.array_equal(got, want), (a, len(got), len(want))
    half = scenes()[0].astype(np.float16)  # a dtype without its own slack: planned as its float64 copy
    a = KnifeAction(x=0.5, y=0.5, yaw=0.3)
    assert P.blade_sweep(a, half, CFG)[0] == P.blade_sweep(a, half.astype(np.float64), CFG)[0]


def test_particles_on_the_band_edge():
    """Particles within a few float32 ulps of |(q - p0) . n| = band on tilted planes, about half of them inside:
    the float32 candidate pass keeps every one the exact test accepts, in their order."""
    rng = np.random.default_rng(5)
    band, N = P.CENTRE_BAND, 4000
    for _ in range(6):
        a = KnifeAction(x=0.5, y=0.5, yaw=rng.uniform(-1.5, 1.5), tilt=rng.uniform(-0.5, 0.5)).canonical()
        n, u, p0 = a.normal, a.blade_axis, a.plane_point(CFG.board_z)
        side = rng.choice([-1.0, 1.0], N)[:, None]
        q = p0 + side * band * n + rng.uniform(-0.03, 0.03, (N, 1)) * u + np.array([0, 0, 0.02])
        x = (q + rng.integers(-4, 5, (N, 3)) * 6e-8 * np.abs(q)).astype(np.float32)  # a few ulps about the edge
        want = exact(x, p0, n, band)
        assert 0.3 * N < len(want) < 0.7 * N
        assert np.array_equal(P._in_band(x, p0, n, band), want)

"""The Taichi runtime's life (topocut.sim.runtime: init_taichi, reset_taichi, offline_cache_size, memoize_source_positions).

Taichi's kernel cache on disk is keyed by each kernel's IR, which names its fields' SNode ids; the tests reset the
runtime before every file (tests/conftest.py) so that a file's fields get the same ids whatever ran before it.
"""
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
import taichi as ti

from topocut.sim.runtime import KERNEL_CACHE_BYTES, init_taichi, offline_cache_size, reset_taichi


def _ids_of_two_fields() -> list[int]:
    a, b = ti.field(ti.f32, shape=8), ti.Vector.field(3, ti.i32, shape=(2, 4))
    a.fill(1.0)  # materialise the tree
    return [a.snode._id, b.snode._id, a.snode._snode_tree_id, b.snode._snode_tree_id]


def test_a_reset_runtime_gives_new_fields_the_same_snode_ids():
    reset_taichi()
    init_taichi("cpu", cpu_threads=1)
    first = _ids_of_two_fields()
    later = _ids_of_two_fields()  # the same runtime: the ids count on
    assert later != first
    reset_taichi()
    init_taichi("cpu", cpu_threads=1)
    assert _ids_of_two_fields() == first


def test_reset_drops_the_device_splits_cached_fields_and_a_split_still_runs():
    from topocut.sim import pieces as P
    from topocut.sim import pieces_device as D
    from topocut.sim.action import KnifeAction
    from topocut.sim.config import SimConfig
    from topocut.sim.objects import ObjectPose, sample_object

    cfg = SimConfig(n_grid=32)
    x, _ = sample_object("cube", ObjectPose(x=0.5, y=0.5, yaw=0.0, scale=1.0), spacing=cfg.spacing, seed=0)
    x = x.astype(np.float64)
    sweep = P.blade_sweep(KnifeAction(x=0.5, y=0.5).canonical(), x, cfg)[0]
    piece = np.zeros(len(x), np.int32)
    host = P.split(x, piece, sweep, cfg.spacing)
    assert host.max() == 1  # two pieces

    def device():
        return D.split_batch(x[None], [len(x)], piece[None], [sweep], cfg.spacing)[0]

    np.testing.assert_array_equal(device(), host)
    assert D._CACHE
    reset_taichi()
    assert not D._CACHE  # its fields were freed with the runtime: a new tree is built
    init_taichi("cpu", cpu_threads=1)
    np.testing.assert_array_equal(device(), host)


def test_the_kernel_cache_is_capped_at_a_gibibyte_unless_the_environment_says():
    from taichi.lang import impl

    if "TI_OFFLINE_CACHE_MAX_SIZE_OF_FILES" in os.environ:
        assert offline_cache_size() == {}
    else:
        assert offline_cache_size() == {"offline_cache_max_size_of_files": KERNEL_CACHE_BYTES}
        assert impl.current_cfg().offline_cache_max_size_of_files == KERNEL_CACHE_BYTES


def test_source_excerpts_are_taichis_own_and_made_once_per_place(monkeypatch):
    """memoize_source_positions: every excerpt a kernel's transform asks for equals Taichi's own text for that
    node, and Taichi makes each place's once although a @ti.func inlined three times asks for its nodes thrice."""
    import taichi as ti
    from taichi.lang.ast import ast_transformer_utils as utils

    from topocut.sim import runtime

    init_taichi("cpu")
    memo = utils.ASTTransformerContext.get_pos_info
    assert memo.memoized
    original, made, asked, wrong = runtime._TAICHI_POS_INFO, [], [], []
    monkeypatch.setattr(runtime, "_EXCERPTS", {})
    monkeypatch.setattr(runtime, "_TAICHI_POS_INFO",
                        lambda ctx, node: made.append(ctx.func.func.__name__) or original(ctx, node))

    def spy(ctx, node):
        text = memo(ctx, node)
        asked.append(ctx.func.func.__name__)
        if text != original(ctx, node):
            wrong.append((node.lineno, text))
        return text

    monkeypatch.setattr(utils.ASTTransformerContext, "get_pos_info", spy)

    @ti.func
    def affine(x):
        return 2.0 * x + 1.0

    @ti.kernel
    def three(a: ti.f32) -> ti.f32:
        return affine(a) + affine(a + 1.0) + affine(a + 2.0)

    assert three(1.0) == 3.0 + 5.0 + 7.0
    assert not wrong
    assert len(made) == len(runtime._EXCERPTS) < len(asked)
    assert asked.count("affine") >= 3 * made.count("affine") > 0  # inlined thrice, each place made once


TO_HOST_CHECK = """
import numpy as np, taichi as ti
from topocut.sim import runtime
runtime.init_taichi("cuda")
vec, mat = ti.Vector.field(3, ti.f32, shape=(4, 1000)), ti.Matrix.field(3, 3, ti.f32, shape=(4, 1000))
ints = ti.field(ti.i32, shape=(4, 1000))
rng = np.random.default_rng(0)
vec.from_numpy(rng.random((4, 1000, 3)).astype(np.float32))
mat.from_numpy(rng.random((4, 1000, 3, 3)).astype(np.float32))
ints.from_numpy(rng.integers(-5, 5, (4, 1000)).astype(np.int32))
for f in (vec, mat, ints):
    a, b = f.to_numpy(), runtime.to_host(f)
    assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b), f
    b[0] += 1  # the host copy is the caller's: writable, and the field does not change
    assert np.array_equal(f.to_numpy(), a)
COPIES_CHECK
print("TO_HOST_OK")
"""
TO_HOST_CHECK = TO_HOST_CHECK.replace("COPIES_CHECK", f"import sys; sys.path.insert(0, {os.path.dirname(os.path.abspath(__file__))!r})\n"
                                      "from test_sim_runtime import copies_check; copies_check(ints)")


@pytest.mark.skipif(shutil.which("nvidia-smi") is None, reason="needs an NVIDIA GPU (to_host's CUDA path)")
def test_to_host_equals_to_numpy_on_cuda():
    """topocut.sim.runtime.to_host reads a field through a device tensor and pinned memory on CUDA (on the CPU it is
    to_numpy itself): the same arrays, dtypes and shapes, for vector, matrix and integer fields."""
    r = subprocess.run([sys.executable, "-c", TO_HOST_CHECK], capture_output=True, text=True, timeout=600)
    assert "TO_HOST_OK" in r.stdout, r.stdout[-3000:] + r.stderr[-3000:]


def copies_check(ints) -> None:
    """to_device's tensor as a kernel's ndarray argument fills the first rows of the (4, 1000) i32 field ``ints``,
    the rest unchanged; row_sums of its first 650 columns equals numpy's."""
    import taichi as ti

    from topocut.sim import runtime

    @ti.kernel
    def put(f: ti.template(), a: ti.types.ndarray(dtype=ti.i32, ndim=2)):
        for b, i in ti.ndrange(a.shape[0], a.shape[1]):
            f[b, i] = a[b, i]

    src = np.random.default_rng(1).integers(-9, 9, (4, 700)).astype(np.int32)
    before = ints.to_numpy()
    put(ints, runtime.to_device(src))  # a device tensor on CUDA, the array itself on the CPU
    after = ints.to_numpy()
    assert np.array_equal(after[:, :700], src) and np.array_equal(after[:, 700:], before[:, 700:])
    sums = runtime.row_sums(ints, 650)
    assert sums.dtype == np.int64 and np.array_equal(sums, src[:, :650].sum(1)), (sums, src[:, :650].sum(1))


def test_row_sums_and_to_device_on_the_cpu():
    """row_sums (a cut's damaged particles per scene, summed on the device on CUDA) and to_device (a kernel's
    ndarray argument, a device tensor on CUDA) on the CPU backend: the check the CUDA test also runs."""
    import taichi as ti

    from topocut.sim import runtime

    runtime.init_taichi("cpu")
    ints = ti.field(ti.i32, shape=(4, 1000))
    ints.from_numpy(np.random.default_rng(0).integers(-5, 5, (4, 1000)).astype(np.int32))
    copies_check(ints)

"""sim.scatter_block_dim / sim.gather_block_dim: CUDA threads per block of the scatter and the gather.

Taichi marks each GPU task with launch bounds (maxntid = block_dim, minctasm = 2), so a bigger block caps
the task's registers (65536 / (2 block_dim)) and lets more warps share an SM.  auto gives a batch's (warp)
scatter 384 threads (H100: 4.6-8.9% off a batched substep, docs/benchmarks.md) and keeps 128 elsewhere; the CPU keeps
Taichi's own chunking.  The GPU check in tests/test_sim_warp_scatter.py compares 128 against 384 on a cut.
"""
import pytest

from topocut.sim import SimConfig


@pytest.mark.parametrize("kw, dims", [
    (dict(arch="cpu", batch_size=16), (None, None)),  # no launch bounds on the CPU
    (dict(arch="cuda", batch_size=1), (128, 128)),  # a single scene: one partial wave of blocks
    (dict(arch="cuda", batch_size=2), (384, 128)),
    (dict(arch="cuda", batch_size=16), (384, 128)),
    (dict(arch="cuda", batch_size=16, warp_scatter="off"), (128, 128)),  # the plain scatter: not timed at 384
    (dict(arch="cuda", batch_size=16, scatter_block_dim=512, gather_block_dim=256), (512, 256)),
    (dict(arch="cuda", batch_size=1, scatter_block_dim=96), (96, 128)),
])
def test_block_dims(kw, dims):
    cfg = SimConfig(**kw).validate()
    assert cfg.block_dims() == dims


@pytest.mark.parametrize("key, value", [("scatter_block_dim", 100), ("scatter_block_dim", 2048),
                                        ("gather_block_dim", -32), ("gather_block_dim", 16)])
def test_bad_block_dim_names_the_key(key, value):
    with pytest.raises(ValueError, match=rf"sim\.{key}: {value}; valid: 0 \(auto\) or a multiple of 32 in \[32, 1024\]"):
        SimConfig(arch="cuda", **{key: value}).validate()

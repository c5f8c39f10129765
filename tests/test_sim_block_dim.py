"""sim.tuning.scatter_block_dim / sim.tuning.gather_block_dim: CUDA threads per block of the scatter and the gather.

Taichi marks each GPU task with launch bounds (maxntid = block_dim, minctasm = 2), so a bigger block caps
the task's registers (65536 / (2 block_dim)) and lets more warps share an SM.  auto gives a batch's (warp)
scatter 512 threads (H200: 5-7% off a batched substep at 128^3 against 384, docs/benchmarks.md) and keeps 128
elsewhere; the CPU keeps Taichi's own chunking.  The GPU check in tests/test_sim_warp_scatter.py compares 128 against
512 on a cut.
"""
import pytest

from topocut.sim import SimConfig, TuningConfig


@pytest.mark.parametrize("arch, batch_size, kw, dims", [
    ("cpu", 16, {}, (None, None)),  # no launch bounds on the CPU
    ("cuda", 1, {}, (128, 128)),  # a single scene: one partial wave of blocks
    ("cuda", 2, {}, (512, 128)),
    ("cuda", 16, {}, (512, 128)),
    ("cuda", 16, dict(warp_scatter="off"), (128, 128)),  # the plain scatter: not timed above 128
    ("cuda", 16, dict(scatter_block_dim=384, gather_block_dim=256), (384, 256)),
    ("cuda", 1, dict(scatter_block_dim=96), (96, 128)),
])
def test_block_dims(arch, batch_size, kw, dims):
    cfg = SimConfig(arch=arch, batch_size=batch_size, tuning=TuningConfig(**kw)).validate()
    assert cfg.tuning.block_dims(cfg.arch, cfg.batch_size) == dims


@pytest.mark.parametrize("key, value", [("scatter_block_dim", 100), ("scatter_block_dim", 2048),
                                        ("gather_block_dim", -32), ("gather_block_dim", 16)])
def test_bad_block_dim_names_the_key(key, value):
    with pytest.raises(ValueError, match=rf"sim\.tuning\.{key}: {value}; valid: 0 \(auto\) or a multiple of 32 in "
                                         r"\[32, 1024\]"):
        SimConfig(arch="cuda", tuning=TuningConfig(**{key: value})).validate()

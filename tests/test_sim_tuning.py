"""sim.tuning: the GPU/performance switches in a group of their own (conf/sim/tuning/, docs/sim.md).

Composing ``sim.tuning.<key>=...`` reaches SimConfig.tuning (a TuningConfig, not a dict); a bad value, an
unknown key under sim.tuning, or an old flat key (sim.warp_scatter) is refused naming the full key.  What each
switch does is checked in tests/test_sim_{fused,grid_box,warp_scatter,resort,grid_layout,block_dim}.py.
"""
import os
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from tests.stage_runner import run as run_stage
from topocut.config import ConfigError, check_known_keys, register_configs, validate
from topocut.sim.config import SimConfig, TuningConfig

REPO = Path(__file__).resolve().parents[1]
register_configs()


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def test_override_reaches_the_tuning_dataclass():
    cfg = _compose("sim.tuning.warp_scatter=off", "sim.tuning.fuse_substeps=4")
    validate(cfg)
    sim = OmegaConf.to_object(cfg.sim)
    assert isinstance(sim, SimConfig) and isinstance(sim.tuning, TuningConfig)
    assert sim.tuning.warp_scatter == "off" and sim.tuning.fuse_substeps == 4
    assert sim.tuning.grid_box == "auto"  # the rest keep their defaults


def test_gpu_sim_composes_the_auto_switches():
    sim = OmegaConf.to_object(_compose("sim=gpu").sim)
    assert sim.arch == "cuda" and sim.tuning == TuningConfig()
    assert sim.tuning.warp_scatter_enabled(sim.arch) and sim.tuning.grid_layout_method(sim.arch) == "soa"


def test_bad_value_names_the_full_key():
    with pytest.raises(ConfigError, match=r"^sim\.tuning\.warp_scatter: 'maybe'; valid: auto, on, off$"):
        validate(_compose("sim.tuning.warp_scatter=maybe"))


def test_unknown_keys_under_tuning_are_refused():
    with pytest.raises(ConfigError, match=r"sim\.tuning\.warp_scater: unknown key \(did you mean "
                                          r"sim\.tuning\.warp_scatter\?\); valid keys of sim\.tuning: fuse_substeps"):
        check_known_keys(_compose("+sim.tuning.warp_scater=on"))
    with pytest.raises(ValueError, match=r"sim\.tuning\.warp_scater: unknown key; valid keys of sim\.tuning"):
        SimConfig(tuning={"warp_scater": "on"})
    assert SimConfig(tuning={"warp_scatter": "off"}).tuning == TuningConfig(warp_scatter="off")


def _topocut(tmp_path, *overrides):
    env = dict(os.environ, WANDB_MODE="disabled", TOPOCUT_OUTPUTS=str(tmp_path), HYDRA_FULL_ERROR="0")
    cmd = [sys.executable, "-m", "topocut.run", "logger=none", "progress=false", *overrides,
           f"outputs_root={tmp_path}"]
    proc = run_stage(cmd, cwd=REPO, env=env, timeout=120)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 2 and "Traceback" not in out, f"exit {proc.returncode}\n{out[-3000:]}"
    return out


def test_cli_refuses_a_bad_switch_and_an_old_flat_key(tmp_path):
    out = _topocut(tmp_path, "sim.tuning.warp_scatter=maybe")
    assert "sim.tuning.warp_scatter: 'maybe'; valid: auto, on, off" in out
    out = _topocut(tmp_path, "sim.warp_scatter=off")  # the key before it moved into sim.tuning
    assert "sim.warp_scatter: unknown key (did you mean sim.tuning.warp_scatter?)" in out

"""stage=bc refuses the policy.train keys each policy's training sets itself, instead of overwriting them."""
import sys
from pathlib import Path

import pytest

from pipelines.bc import SET_PER_POLICY, check_train_keys
from tests.stage_runner import run as run_stage
from topocut.policies.config import PolicyTrainConfig

ROOT = Path(__file__).resolve().parent.parent


def test_defaults_pass_and_each_overridden_key_is_named():
    check_train_keys(PolicyTrainConfig())
    for key, value in {"encoder": "none", "encoder_ckpt": "/x/model.ckpt", "seed": 3}.items():
        train = PolicyTrainConfig(**{key: value})
        with pytest.raises(ValueError, match=f"policy.train.{key}="):
            check_train_keys(train)
    assert set(SET_PER_POLICY) == {"encoder", "encoder_ckpt", "seed"}


def test_the_command_line_override_exits_2_before_any_data_is_read(tmp_path):
    proc = run_stage([sys.executable, "-m", "topocut.run", "stage=bc", "policy.train.encoder=none",
                      f"outputs_root={tmp_path}", "logger=none"], cwd=ROOT, timeout=300)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 2, out[-2000:]
    assert "policy.train.encoder='none': stage=bc takes it from each policy's own encoder" in out, out[-2000:]
    assert "Traceback" not in out

"""`stage=teleop` without a display: the shipped sample log replays headlessly; a log without a cut is refused."""
import json

from tests.test_stages import REPO, _ok, _output, _summary, topocut

SAMPLE = REPO / "examples" / "teleop_slice_cake.json"


def test_the_sample_log_replays_headlessly_into_a_dataset(tmp_path):
    proc = _ok(topocut(tmp_path, "stage=teleop", "task=slice", f"stage.run.replay={SAMPLE}", "logger=none",
                       "progress=false", timeout=600))
    summary = _summary(proc)
    assert summary["cuts"] == 2 and summary["final_reward"] > 0.9, summary  # the cake's two 5 cm slabs


def test_a_log_without_a_cut_is_refused_and_commits_nothing(tmp_path):
    log = json.loads(SAMPLE.read_text())
    empty = tmp_path / "empty.json"
    empty.write_text(json.dumps({**log, "actions": []}))
    proc = topocut(tmp_path, "stage=teleop", "task=slice", f"stage.run.replay={empty}", "logger=none", timeout=300)
    out = _output(proc)
    assert proc.returncode == 2 and "holds no cut" in out and "Traceback" not in out, out[-2000:]
    assert not list(tmp_path.glob("dataset/*/v*"))  # no version committed

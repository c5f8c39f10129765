"""Run records: status.json from the start, SIGTERM handled like Ctrl-C, one directory per process."""
import json
import signal
import subprocess
import time

from tests.test_stages import FAST, REPO, _cmd, _env


def _statuses(root):
    return [json.loads(p.read_text()) for p in sorted((root / "runs").rglob("status.json"))]


def test_sigterm_marks_the_run_failed_in_one_line(tmp_path):
    """A stage under SIGTERM (Slurm's cancel, docker stop): status.json goes from running to failed, the log says
    so in one line, no traceback, exit 143; a SIGKILLed run would still leave the running record."""
    proc = subprocess.Popen(_cmd(tmp_path, "stage=mppi", "task=slice", "object=cube", "data.episodes=20", *FAST),
                            cwd=REPO, env=_env(tmp_path), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.time() + 120
    while time.time() < deadline and not any(s["status"] == "running" for s in _statuses(tmp_path)):
        time.sleep(0.2)
    running = _statuses(tmp_path)
    assert running and running[0]["status"] == "running" and running[0]["pid"] == proc.pid
    time.sleep(2.0)  # into the stage
    proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 143, out[-2000:]
    assert "terminated (SIGTERM)" in out and "Traceback" not in out, out[-2000:]
    (status,) = _statuses(tmp_path)
    assert status["status"] == "failed" and status["error"].startswith("Terminated")


def test_two_runs_started_together_keep_their_own_records(tmp_path):
    procs = [subprocess.Popen(_cmd(tmp_path, "seed=-3", "logger=none"), cwd=REPO, env=_env(tmp_path),
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) for _ in range(2)]
    for p in procs:
        p.communicate(timeout=120)
        assert p.returncode == 2
    statuses = _statuses(tmp_path)
    assert len(statuses) == 2 and {s["pid"] for s in statuses} == {p.pid for p in procs}
    assert all(s["status"] == "failed" for s in statuses)

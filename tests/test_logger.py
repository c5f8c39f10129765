"""RunLogger: csv metrics land in the run directory; a picture that does not exist is refused for every kind."""
import csv

import pytest

from tests.stage_runner import run as run_stage
from topocut.utils.logger import RunLogger


def test_csv_metrics_and_missing_picture(tmp_path):
    log = RunLogger("csv", tmp_path, "t")
    log.log({"train/loss": 0.5}, step=3)
    rows = list(csv.reader(open(tmp_path / "metrics.csv")))
    assert rows == [["step", "key", "value"], ["3", "train/loss", "0.5"]]
    png = tmp_path / "a.png"
    png.write_bytes(b"\x89PNG")
    for kind in ("csv", "none"):
        RunLogger(kind, tmp_path, "t").log_image("sim/frame", png)  # exists: fine
        with pytest.raises(FileNotFoundError, match="sim/frame.*nope.png"):
            RunLogger(kind, tmp_path, "t").log_image("sim/frame", tmp_path / "nope.png")


def test_progress_logs_a_line_per_step_when_output_is_not_a_terminal(caplog):
    """Redirected to a file (as here: pytest captures stdout), a redrawn bar would stay blank until the end."""
    import logging

    from topocut.utils.progress import progress_bar

    with caplog.at_level(logging.INFO, logger="topocut.progress"):
        with progress_bar("eval", total=3) as advance:
            advance(1, info="cube R=0.5")
            advance(2)
        with progress_bar("quiet", total=1, enabled=False) as advance:
            advance(1, info="not shown")
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2 and lines[0].startswith("eval 1/3 (") and lines[0].endswith(": cube R=0.5")
    assert lines[1].startswith("eval 3/3 (") and "not shown" not in " ".join(lines)


def test_tables_printed_to_a_log_do_not_wrap(capsys):
    """A stage's summary in a log file or a CI log (stdout not a terminal): one row a line, not folded at 80
    columns as rich does by default."""
    from topocut.utils.progress import print_summary

    key = "eval/a_rather_long_metric_name_that_would_not_fit"
    value = "/some/outputs/eval/table1/v001/results.md and more words to pass eighty columns"
    print_summary("summary", {key: value})
    out = capsys.readouterr().out
    assert any(key in line and value in line for line in out.splitlines()), out


def test_summary_keys_are_never_cut_short_on_a_narrow_terminal(monkeypatch, capsys):
    """pretrain's summary on an 80-column terminal printed `val/cluster_err_re…` beside a long checkpoint path: a
    name no doc can be searched for.  The key stays whole on its line; the value folds.  Narrower still, the key
    folds too, every character kept."""
    from rich.console import Console

    import topocut.utils.progress as progress

    key = "val/cluster_err_reduction_unseen"
    path = "/home/someone/projects/topocut/outputs/checkpoint/perception/v001"
    for width in (80, 40):
        monkeypatch.setattr(progress, "console", lambda w=width: Console(width=w, force_terminal=False))
        progress.print_summary("pretrain: done", {"checkpoint": path, key: -231.0})
        out = capsys.readouterr().out
        assert "…" not in out and "-231" in out, out
        first_column = "".join(ln.split("│")[1].strip() for ln in out.splitlines() if ln.startswith("│"))
        assert "checkpoint" + key in first_column, out
        if width == 80:
            assert any(key in ln and "-231" in ln for ln in out.splitlines()), out


# The default logger (logger=wandb, offline) in every stage, as a user's first commands run it (issue #48): the
# test target sets WANDB_MODE=disabled for the suite, so these runs set offline themselves.  The stages of
# stage=all (simulate, mppi, pretrain, bc, eval) are checked so in tests/test_stages.py's whole-pipeline run; the
# one stage outside it is teleop (a replay here).
SMALL_SIM = ["sim.n_grid=20", "sim.cut_substeps=40", "sim.dwell_time=0.0005", "sim.push_time=0.002",
             "sim.settle_time=0.002", "sim.batch_size=2", "topology.resolution=32", "object.randomize_pose=false"]


def test_teleop_runs_with_the_default_wandb_logger_offline(tmp_path):
    """stage=teleop with logger=wandb under WANDB_MODE=offline: exit 0, an offline run directory in the stage's
    run directory, named by one line of the output, and no wandb banner (silenced: ~30 lines a stage)."""
    import os
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    env = dict(os.environ, WANDB_MODE="offline", HYDRA_FULL_ERROR="0", TOPOCUT_OUTPUTS=str(tmp_path))
    env.pop("CUDA_VISIBLE_DEVICES", None)
    proc = run_stage([sys.executable, "-m", "topocut.run", "logger=wandb", *SMALL_SIM, "stage=teleop",
                      "task=slice", "stage.run.replay=examples/teleop_slice_cake.json", f"outputs_root={tmp_path}"],
                     cwd=repo, env=env, timeout=300)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, f"exit {proc.returncode}\n{out[-4000:]}"
    (run_dir,) = (tmp_path / "runs" / "teleop").iterdir()
    offline = list((run_dir / "wandb").glob("offline-run-*"))
    assert len(offline) == 1 and list(offline[0].glob("*.wandb")), f"no offline run in {run_dir}"
    said = [ln for ln in out.splitlines() if "wandb: offline run written to" in ln]
    assert len(said) == 1 and str(offline[0]) in said[0], out[-3000:]
    assert "Tracking run with wandb" not in out and "Run summary" not in out, f"banner\n{out[-3000:]}"


def _keys_documented(summary: dict, doc) -> None:
    text = doc.read_text()
    missing = [k for k in summary if f"`{k}`" not in text]
    assert not missing, f"pretrain prints {missing} but {doc.name} does not explain them"


def test_every_key_the_pretrain_summary_can_print_is_in_the_perception_doc():
    """The summary's keys come from the stage (checkpoint, model, ...) and the module's logged metrics, every split
    suffix included (a run prints the suffixes its data has: tests/test_stages.py's pipeline checks a real one)."""
    from pathlib import Path

    from topocut.models.module import DERIVED_KEYS, VAL_KEYS

    keys = ["checkpoint", "reused", "rank", "model", "parameters", "train_episodes", "train/loss", "train/loss_pos",
            "train/loss_topo", *VAL_KEYS, *DERIVED_KEYS]
    _keys_documented(dict.fromkeys(keys), Path(__file__).resolve().parents[1] / "docs" / "perception.md")

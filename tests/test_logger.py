"""RunLogger: csv metrics land in the run directory; a picture that does not exist is refused for every kind."""
import csv

import pytest

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

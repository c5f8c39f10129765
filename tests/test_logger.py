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

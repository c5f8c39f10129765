"""Issue #54 at smoke scale on the CPU: the pyramid's own plane earns full marks and each wrong plane (2 cm deeper,
15° yawed, 15° tilted) scores at least 0.3 below it (experiments/reference_check.py, as docs/tasks.md runs it)."""
import json
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("taichi")
ROOT = Path(__file__).resolve().parent.parent


def test_pyramid_reference_beats_every_wrong_plane(tmp_path):
    out = tmp_path / "pyramid.json"
    proc = subprocess.run([sys.executable, "experiments/reference_check.py", "pyramid", "--n-grid", "48",
                           "--json", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    rows = {r["plane"]: r for r in json.loads(out.read_text())["rows"]}
    assert set(rows) == {"reference", "deeper 2 cm", "yawed 15°", "tilted 15°"}
    ref = rows.pop("reference")
    assert ref["reward"] >= 0.9 and ref["pieces"] == 2  # the tetrahedron and the rest of the cube
    for name, r in rows.items():
        assert r["reward"] <= ref["reward"] - 0.3, (name, r, ref)
    assert "reference" in proc.stdout and "tilted 15°" in proc.stdout

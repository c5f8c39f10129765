"""The ``--json`` option the reference checks' command lines share (issue #54: reference_check.py,
reference_writing.py, reference_scooping.py): each prints its rows and, when asked, writes them."""
from __future__ import annotations

import argparse
from pathlib import Path

from topocut.data.store import write_json_atomic


def add_json_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", default="", help="also write the rows here")


def save_json(out: dict, path: str) -> int:
    """Writes ``out`` to ``path`` where --json gave one; returns the command's exit status (0)."""
    if path:
        write_json_atomic(Path(path), out)  # a temporary name, then renamed: a killed run leaves no half file
    return 0

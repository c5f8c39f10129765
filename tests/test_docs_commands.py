"""The documentation's commands run as written (issue #48, "the first hour").

Every fenced code block of README.md and docs/*.md on the line right after ``<!-- runnable -->`` is run:

* a ```` ```bash ```` block with ``bash -euo pipefail`` from the repository root, ``python`` on its PATH being the
  interpreter running the tests (the venv's: ``.venv/bin`` first), so ``python -m topocut.run ...`` and
  ``.venv/bin/python -m topocut.run ...`` both mean the project's;
* a ```` ```python ```` block with that interpreter, from the repository root;

each with ``TOPOCUT_OUTPUTS`` set to a fresh temporary outputs root, shared by a document's blocks in document order
(a later block may read what an earlier one wrote), and ``WANDB_MODE=disabled`` (the default logger's offline runs
are tests/test_logger.py's).  A block passes when it exits 0 and every path it promises exists under that root:
one comment line per path inside the block, ``# expect: sim/cake-slice/v001/manifest.json`` (a glob is allowed).
A marker not followed by a fence, or on a block of another language, fails the harness.

Only blocks that run at smoke scale on a CPU in seconds are marked (the suite's budget: these add about a minute
and a half on 2 cores).  Left unmarked, and why:

* README: ``make run`` / ``make test`` (minutes; the test suite runs their pipeline shrunk in
  tests/test_stages.py), ``make paper`` (a GPU, hours), the list of stage commands after the first (each minutes at
  smoke scale; ``stage=teleop`` without a log needs a display; ``stage=all`` is ``make run``), the sweep (four
  MPPI jobs and a merge, minutes; tests/test_stages.py runs it shrunk);
* docs/architecture.md: a diagram, not a command;
* docs/results.md: the answer key's check (``benchmarks/gpu.sh``, ``device=cuda``, ``scale=paper``: a GPU);
* docs/sim.md's picture commands (minutes, and they rewrite docs/img/);
* docs/tasks.md: pyramid / cream-writing MPPI and their figures, ice-cream scooping (minutes each; their stages are
  tests/test_tasks_*.py's, shrunk);
* docs/gym.md's example: cheap, but that page is another engineer's (marking it is one line there).
"""
from __future__ import annotations

import glob
import os
import re
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
MARKER = "<!-- runnable -->"
LANGUAGES = ("bash", "python")
EXPECT = re.compile(r"^\s*#\s*expect:\s*(\S+)\s*$")
FENCE = re.compile(r"^(`{3,})\s*([\w+-]*)\s*$")
BLOCK_TIMEOUT = 300  # s: the slowest marked block takes about a minute on 2 cores


@dataclass
class Block:
    source: str  # "docs/x.md:12": the fence's line, for messages
    lang: str
    code: str
    expects: list[str] = field(default_factory=list)  # paths under the outputs root the block promises


def extract_blocks(text: str, source: str = "<markdown>") -> list[Block]:
    """The runnable blocks of a markdown text, in order; a stray or mislabelled marker raises ValueError."""
    lines = text.splitlines()
    blocks = []
    for i, line in enumerate(lines):
        if line.strip() != MARKER:
            continue
        where = f"{source}:{i + 2}"
        m = FENCE.match(lines[i + 1].strip()) if i + 1 < len(lines) else None
        if m is None:
            raise ValueError(f"{source}:{i + 1}: {MARKER} must be followed on the next line by a code fence")
        fence, lang = m.groups()
        if lang not in LANGUAGES:
            raise ValueError(f"{where}: a runnable block must be one of {', '.join(LANGUAGES)}, not {lang or 'unlabelled'!r}")
        body = []
        for j in range(i + 2, len(lines)):
            if lines[j].strip() == fence:
                break
            body.append(lines[j])
        else:
            raise ValueError(f"{where}: the block is never closed")
        expects = [m.group(1) for m in map(EXPECT.match, body) if m]
        for path in expects:
            if Path(path).is_absolute() or ".." in Path(path).parts:
                raise ValueError(f"{where}: expect: {path} must be relative to the outputs root, inside it")
        blocks.append(Block(where, lang, "\n".join(body) + "\n", expects))
    return blocks


def block_env(root: Path) -> dict:
    env = dict(os.environ, TOPOCUT_OUTPUTS=str(root), WANDB_MODE="disabled", HYDRA_FULL_ERROR="0")
    bindir = str(Path(sys.executable).parent)  # `python` (and .venv/bin's tools) are the tests' interpreter's
    env["PATH"] = os.pathsep.join([bindir, env.get("PATH", "")])
    env.pop("CUDA_VISIBLE_DEVICES", None)
    return env


def run_block(block: Block, root: Path, timeout: float = BLOCK_TIMEOUT) -> subprocess.CompletedProcess:
    cmd = ["bash", "-euo", "pipefail", "-c", block.code] if block.lang == "bash" else [sys.executable, "-c", block.code]
    return subprocess.run(cmd, cwd=REPO, env=block_env(root), capture_output=True, text=True, timeout=timeout)


def check_block(block: Block, root: Path, timeout: float = BLOCK_TIMEOUT) -> float:
    """Run ``block`` against the outputs root ``root``; AssertionError unless it exits 0 and writes what it
    promises.  Returns its wall seconds."""
    t0 = time.time()
    proc = run_block(block, root, timeout)
    seconds = time.time() - t0
    out = (proc.stdout + proc.stderr)[-4000:]
    assert proc.returncode == 0, f"{block.source} ({block.lang}) exit {proc.returncode}:\n{block.code}\n{out}"
    missing = [p for p in block.expects if not glob.glob(str(root / p))]
    assert not missing, f"{block.source}: exit 0 but no {', '.join(missing)} under {root}\n{out}"
    return seconds


def documents() -> list[Path]:
    return [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]


def _marked() -> list[str]:
    return [str(p.relative_to(REPO)) for p in documents() if MARKER in p.read_text()]


@pytest.mark.parametrize("doc", _marked())
def test_runnable_blocks_run_as_written(doc, tmp_path):
    blocks = extract_blocks((REPO / doc).read_text(), doc)
    assert blocks
    for block in blocks:  # in document order, one outputs root: a block may use an earlier one's artifact
        seconds = check_block(block, tmp_path)
        print(f"{block.source}: {seconds:.1f} s")


def test_the_first_hour_is_covered():
    """The README's first stage command and the docs' API examples are among the blocks run (a marker lost in an
    edit would otherwise pass silently)."""
    marked = set(_marked())
    assert {"README.md", "docs/topology.md", "docs/evaluation.md"} <= marked, marked
    readme = extract_blocks((REPO / "README.md").read_text(), "README.md")
    assert any("stage=simulate" in b.code and b.expects for b in readme)


SYNTHETIC = """# A page

<!-- runnable -->
```bash
echo hi > "$TOPOCUT_OUTPUTS/a.txt"
python -c "import sys; print(sys.executable)" > "$TOPOCUT_OUTPUTS/which.txt"
# expect: a.txt
# expect: wh*.txt
```

```bash
echo "an unmarked block is not run" && exit 3
```

<!-- runnable -->
```python
import sys
sys.exit(1)
```

<!-- runnable -->
```bash
false
echo "-e: not reached"
```

<!-- runnable -->
```bash
true
# expect: never/written.json
```
"""


def test_harness_extracts_marked_blocks_and_fails_a_failing_one(tmp_path):
    ok, exits_1, stops_at_false, broken_promise = extract_blocks(SYNTHETIC, "synthetic.md")
    assert (ok.lang, ok.expects, ok.source) == ("bash", ["a.txt", "wh*.txt"], "synthetic.md:4")
    check_block(ok, tmp_path, timeout=60)
    assert (tmp_path / "a.txt").read_text() == "hi\n"
    assert Path((tmp_path / "which.txt").read_text().strip()).parent == Path(sys.executable).parent
    with pytest.raises(AssertionError, match=r"synthetic.md:\d+ \(python\) exit 1"):
        check_block(exits_1, tmp_path, timeout=60)
    with pytest.raises(AssertionError, match="exit 1"):  # bash -e: the first failing command fails the block
        check_block(stops_at_false, tmp_path, timeout=60)
    with pytest.raises(AssertionError, match="no never/written.json under"):
        check_block(broken_promise, tmp_path, timeout=60)


@pytest.mark.parametrize("text,needle", [
    ("<!-- runnable -->\nnot a fence\n", "must be followed on the next line by a code fence"),
    ("<!-- runnable -->\n```\nls\n```\n", "not 'unlabelled'"),
    ("<!-- runnable -->\n```sh\nls\n```\n", "not 'sh'"),
    ("<!-- runnable -->\n```bash\nls\n", "never closed"),
    ("<!-- runnable -->\n```bash\n# expect: ../x\n```\n", "inside it"),
])
def test_a_bad_marker_is_an_error(text, needle):
    with pytest.raises(ValueError, match=re.escape(needle)):
        extract_blocks(text, "bad.md")

"""Issue #50: every key in conf/ is read by the code its name says.  Each stage's config is composed at both
scales; every leaf key (Hydra's own ``_target_``/``_partial_`` aside) must be read somewhere in topocut/ or
pipelines/: as an attribute (``cfg.key``), a string (``cfg["key"]``, a field name in a tuple), a keyword
(``key=``) or a parameter of a stage function -- the schema's own field definitions (``key: type = value``) and
comments do not count.  A key that nothing reads does nothing and says otherwise: delete it, or read it.  Every
task is composed too: each has keys of its own (its dataclass, topocut/tasks/<task>.py)."""
from __future__ import annotations

import re
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig, ListConfig

from topocut.config import STAGES, register_configs
from topocut.tasks import TASKS

REPO = Path(__file__).resolve().parents[1]
DEFINITION = re.compile(r"^\s+\w+\s*:\s*[\w\[\]|., ]+\s*=")  # a dataclass field: `    n_grid: int = 64`


def leaf_keys(node, path=()) -> set[tuple]:
    """Key paths of the leaves of a composed config (an empty dict counts as a leaf: its key is set)."""
    if isinstance(node, DictConfig):
        if len(node) == 0:
            return {path}
        out = set()
        for k in node.keys():
            child = node._get_node(k)
            out |= leaf_keys(child, path + (str(k),)) if isinstance(child, (DictConfig, ListConfig)) else {path + (str(k),)}
        return out
    return {path}


def code_that_reads(roots=("topocut", "pipelines")) -> str:
    lines = []
    for root in roots:
        for f in sorted((REPO / root).rglob("*.py")):
            lines += [line.split("#")[0] for line in f.read_text().splitlines() if not DEFINITION.match(line)]
    return "\n".join(lines)


def is_read(key: str, code: str) -> bool:
    k = re.escape(key)
    return re.search(rf"\.{k}\b|[\"']{k}[\"']|\b{k}=|\b{k}\s*[:,)]", code) is not None


def test_the_reader_finds_reads_and_ignores_definitions_and_comments():
    code = code_that_reads(()) + "\n".join(["x = cfg.alpha", 'y = d["beta"]', "f(gamma=1)", "def run(ctx, delta):",
                                            "    epsilon: int = 3", "z = 1  # cfg.zeta"])
    code = "\n".join(line.split("#")[0] for line in code.splitlines() if not DEFINITION.match(line))
    assert all(is_read(k, code) for k in ("alpha", "beta", "gamma", "delta"))
    assert not is_read("epsilon", code) and not is_read("zeta", code)


@pytest.mark.parametrize("scale", ["smoke", "paper"])
def test_every_config_key_is_read_by_the_code(scale):
    register_configs()
    keys = set()
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        for stage in STAGES:
            keys |= leaf_keys(compose(config_name="config", overrides=[f"stage={stage}", f"scale={scale}",
                                                                       "logger=none"]))
        for task in TASKS:  # each task's own keys (its dataclass) and its scale's (conf/scale_task)
            keys |= leaf_keys(compose(config_name="config", overrides=[f"task={task}", f"scale={scale}",
                                                                       "logger=none"]))
    code = code_that_reads()
    unread = sorted(".".join(p) for p in keys if p and not p[-1].startswith("_") and not is_read(p[-1], code))
    assert len(keys) > 300  # the whole tree was walked
    assert not unread, f"config keys nothing reads (delete them or read them): {unread}"

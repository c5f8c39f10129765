"""The import graph: the simulator stands alone, and no two modules import each other at load time.

Parsed with ast (nothing is imported).  Module-level imports are the top-level statements and those inside
top-level ``if`` / ``try`` (not under ``if TYPE_CHECKING:``), not those inside functions or classes: a
function-local import runs after every module has loaded, so it cannot close a cycle.  ``from pkg import name``
is an edge to ``pkg.name`` when that is a module of the tree, else to ``pkg``; no implicit edges to parent packages.
"""
from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

ROOT = Path(__file__).resolve().parents[1]
SIM_MAY_NOT_IMPORT = ("topocut.tasks", "topocut.goals", "topocut.policies", "topocut.eval", "topocut.planning",
                      "topocut.episode")


def module_files(root: Path, packages=("topocut", "pipelines")) -> dict[str, Path]:
    """Dotted module name -> file, for every .py under the given top-level folders of root."""
    out = {}
    for pkg in packages:
        for f in sorted((root / pkg).rglob("*.py")):
            parts = list(f.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = f
    return out


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _module_level(body):
    """Import statements of a module body, descending into if / try (not TYPE_CHECKING) but no def or class."""
    for node in body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        elif isinstance(node, ast.If):
            if not _is_type_checking(node.test):
                yield from _module_level(node.body)
            yield from _module_level(node.orelse)
        elif isinstance(node, ast.Try):
            for part in (node.body, node.orelse, node.finalbody, *(h.body for h in node.handlers)):
                yield from _module_level(part)


def imports_of(name: str, path: Path, modules: dict[str, Path], everywhere: bool = False) -> set[str]:
    """Modules of the tree that module ``name`` imports: at module level, or at any level with everywhere."""
    tree = ast.parse(path.read_text(), str(path))
    nodes = [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))] if everywhere \
        else list(_module_level(tree.body))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        else:
            base = node.module or ""
            if node.level:  # relative: up level - 1 packages from this module's package
                up = package.split(".")
                up = up[:len(up) - (node.level - 1)]
                base = ".".join(up + ([base] if base else []))
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
        for t in targets:
            while t and t not in modules:  # `import topocut.sim.env` names a module; a deeper attribute does not
                t = t.rpartition(".")[0]
            if t and t != name:
                out.add(t)
    return out


def import_graph(root: Path, packages=("topocut", "pipelines"), everywhere: bool = False) -> dict[str, set[str]]:
    modules = module_files(root, packages)
    return {m: imports_of(m, f, modules, everywhere) for m, f in modules.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (or a module importing itself), sorted."""
    names = sorted(graph)
    idx = {m: i for i, m in enumerate(names)}
    edges = [(idx[a], idx[b]) for a in names for b in graph[a] if b in idx]
    if not edges:
        return []
    rows, cols = np.array(edges).T
    adj = coo_matrix((np.ones(len(edges)), (rows, cols)), shape=(len(names), len(names)))
    n, label = connected_components(adj, directed=True, connection="strong")
    out = []
    for c in range(n):
        members = [names[i] for i in np.flatnonzero(label == c)]
        if len(members) > 1 or members[0] in graph[members[0]]:
            out.append(sorted(members))
    return sorted(out)


# -- the checker itself, on a tiny package ------------------------------------------------------------------------
def _write(root: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        f = root / rel
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_text(text)


def test_checker_finds_a_cycle_and_skips_local_and_type_checking_imports(tmp_path):
    _write(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/a.py": "from pkg import b\n",
        "pkg/b.py": "try:\n    from . import c\nexcept ImportError:\n    pass\n",
        "pkg/c.py": "import pkg.a\n",  # a -> b -> c -> a
        "pkg/d.py": "def f():\n    from pkg import e\n",  # function-local: no edge
        "pkg/e.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.d import f\nfrom pkg.d import f\n",
        "pkg/sub/__init__.py": "from ..a import x\n",  # relative from a package: pkg.a (x is no module)
    })
    g = import_graph(tmp_path, ("pkg",))
    assert g["pkg.a"] == {"pkg.b"} and g["pkg.b"] == {"pkg.c"} and g["pkg.c"] == {"pkg.a"}
    assert g["pkg.d"] == set() and g["pkg.e"] == {"pkg.d"} and g["pkg.sub"] == {"pkg.a"}
    assert g["pkg"] == set()  # no implicit edges to or from parent packages
    assert cycles(g) == [["pkg.a", "pkg.b", "pkg.c"]]  # d <-> e is one way only: d's import is local
    assert import_graph(tmp_path, ("pkg",), everywhere=True)["pkg.d"] == {"pkg.e"}
    assert cycles(import_graph(tmp_path, ("pkg",), everywhere=True)) == [["pkg.a", "pkg.b", "pkg.c"], ["pkg.d", "pkg.e"]]


# -- the tree -----------------------------------------------------------------------------------------------------
def test_the_simulator_imports_nothing_from_tasks_policies_eval_planning_or_goals():
    """topocut.sim is the bottom layer: at any level (function-local imports included) it needs none of these."""
    g = import_graph(ROOT, everywhere=True)
    bad = {m: sorted(t for t in ts if any(t == p or t.startswith(p + ".") for p in SIM_MAY_NOT_IMPORT))
           for m, ts in g.items()
           if m == "topocut.sim" or m.startswith("topocut.sim.")}
    bad = {m: ts for m, ts in bad.items() if ts}
    assert not bad, f"topocut.sim imports {bad}"


def test_the_module_level_import_graph_has_no_cycles():
    found = cycles(import_graph(ROOT))
    assert not found, "import cycles at module level:\n" + "\n".join(" <-> ".join(c) for c in found)

"""Lazy exports: a package names what it exports and from which module, and imports that module on first use
(so that importing the package pulls in no torch, Taichi or Warp)."""
from __future__ import annotations

import importlib


def lazy_exports(package: str, exports: dict[str, str]):
    """A module ``__getattr__`` for ``package`` (PEP 562): ``name`` in ``exports`` comes from the module
    ``exports[name]`` (a path from ``.`` is relative to ``package``), imported when first asked for."""

    def __getattr__(name: str):
        if name in exports:
            return getattr(importlib.import_module(exports[name], package), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    return __getattr__

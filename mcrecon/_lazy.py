"""Public names that import their sub-module on first use (PEP 562), for mcrecon's packages."""

from __future__ import annotations

import importlib
import sys
from typing import Callable, Iterable, Mapping


def lazy_exports(package: str, lazy: Mapping[str, str], submodules: Iterable[str],
                 public: Iterable[str]) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """The ``__getattr__`` and ``__dir__`` of ``package``.

    ``lazy`` maps a public name to the sub-module (relative to ``package``,
    without the dot) that defines it; ``submodules`` are reachable as
    attributes without importing them first.  A name, once imported, is
    stored in the package, so later look-ups skip ``__getattr__``.
    """
    module = sys.modules[package]
    submodules = frozenset(submodules)
    public = frozenset(public)

    def __getattr__(name: str):
        if name in lazy:
            value = getattr(importlib.import_module(f".{lazy[name]}", package), name)
        elif name in submodules:
            value = importlib.import_module(f".{name}", package)
        else:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        setattr(module, name, value)
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(module)) | public | submodules)

    return __getattr__, __dir__

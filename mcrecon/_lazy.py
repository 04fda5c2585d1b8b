"""Public names that import their sub-module on first use (PEP 562), for mcrecon's packages."""

from __future__ import annotations

import importlib
import sys
from typing import Callable, Iterable, Mapping


def lazy_exports(package: str, lazy: Mapping[str, str], submodules: Iterable[str],
                 public: Iterable[str]) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """The ``__getattr__`` and ``__dir__`` (:func:`public_dir`) of ``package``.

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

    return __getattr__, public_dir(package)


def public_dir(module_name: str) -> Callable[[], list[str]]:
    """A module's ``__dir__``: its ``__all__``, sorted, so ``dir()`` shows the public names only.

    Imports (``np``, ``InputError``) and helpers stay reachable as
    attributes; tab completion and ``dir()`` list the API.
    """
    module = sys.modules[module_name]

    def __dir__() -> list[str]:
        return sorted(module.__all__)

    return __dir__

"""Method registry: name -> class, imported lazily.

Each paper's method lives in its own module.  :func:`get_method` gives a
stable error listing the valid names for an unknown one.
"""

from __future__ import annotations

import importlib

from ..errors import InputError
from .base import AdaptiveState, Method, MethodInputs, Option, Requirements, RunState, uniform_counts, variant_option

__all__ = ["METHODS", "get_method", "method_class", "available_methods", "Method", "AdaptiveState",
           "Option", "Requirements", "MethodInputs", "RunState", "uniform_counts", "variant_option"]

#: Registry: method name -> "module:Class".
METHODS = {
    "box": "mcrecon.methods.box:BoxMethod",
    "gem": "mcrecon.methods.gem:GEMMethod",
    "awr": "mcrecon.methods.awr.method:AWRMethod",
    "splat": "mcrecon.methods.splat.method:SplatMethod",
    "ci": "mcrecon.methods.ci:CIMethod",
    "auto": "mcrecon.methods.auto:AutoMethod",
}


def _load(name: str):
    mod, cls = METHODS[name].split(":")
    return getattr(importlib.import_module(mod), cls)


def available_methods() -> list[str]:
    """Names of the registered methods whose module is present."""
    out = []
    for name in METHODS:
        try:
            _load(name)
        except (ImportError, AttributeError):
            continue
        out.append(name)
    return out


def method_class(name: str) -> type[Method]:
    if name not in METHODS:
        raise InputError("method", "name", f"unknown method {name!r}; valid: {', '.join(available_methods())}")
    try:
        return _load(name)
    except (ImportError, AttributeError) as exc:
        raise InputError("method", "name", f"method {name!r} is not available in this build ({exc}); "
                         f"valid: {', '.join(available_methods())}") from None


def get_method(name: str, **options) -> Method:
    """Instantiate a registered method with keyword options."""
    return method_class(name)(**options)

"""Method registry: name -> class, imported lazily.

Each paper's method lives in its own module.  :func:`get_method` gives a
stable error listing the valid names for an unknown one.  A user's package
adds a method without editing this registry: :func:`register_method` at
run time, or an entry point in the ``mcrecon.methods`` group of its
packaging metadata (``[project.entry-points."mcrecon.methods"]``,
``blur = "mypkg.blur:BlurMethod"``), read on the registry's first use.
"""

from __future__ import annotations

import importlib
import warnings

from ..errors import InputError, McreconWarning
from .base import AdaptiveState, Method, MethodInputs, Option, Requirements, RunState, uniform_counts, variant_option

__all__ = ["METHODS", "get_method", "method_class", "available_methods", "register_method", "half_buffer_methods",
           "statistics_methods", "Method", "AdaptiveState", "Option", "Requirements", "MethodInputs", "RunState",
           "uniform_counts", "variant_option"]

#: Registry: method name -> "module:Class".
METHODS = {
    "box": "mcrecon.methods.box:BoxMethod",
    "gem": "mcrecon.methods.gem:GEMMethod",
    "awr": "mcrecon.methods.awr.method:AWRMethod",
    "splat": "mcrecon.methods.splat.method:SplatMethod",
    "ci": "mcrecon.methods.ci.method:CIMethod",
    "auto": "mcrecon.methods.auto:AutoMethod",
    "nfor": "mcrecon.methods.nfor:NFORMethod",
}


#: The entry-point group a package declares its methods in.
ENTRY_POINT_GROUP = "mcrecon.methods"
_BUILTIN = frozenset(METHODS)
_entry_points_read = False


def register_method(name: str, target, *, replace: bool = False) -> None:
    """Add a method to the registry under ``name``.

    Parameters
    ----------
    name : str
        The name ``get_method``, ``mcrecon.reconstruct(..., method=name)``
        and ``--method`` use.
    target : type or str
        A :class:`Method` subclass, or ``"package.module:Class"`` (imported
        on first use).
    replace : bool
        Allow replacing a registered method of that name (never a built-in one).
    """
    if not isinstance(name, str) or not name.isidentifier():
        raise InputError("register_method", "name", f"{name!r}, expected a method name (letters, digits, _)")
    cls = None
    if isinstance(target, type):
        if not issubclass(target, Method):
            raise InputError("register_method", "target", f"{target.__name__} is not a subclass of "
                             "mcrecon.methods.Method")
        if getattr(target, "name", None) != name:
            raise InputError("register_method", "name", f"{name!r}, but {target.__name__}.name is "
                             f"{getattr(target, 'name', None)!r}: a run's log records the method's own name and "
                             f"--resume looks it up; register it as {getattr(target, 'name', None)!r} or set "
                             f"name = {name!r} on the class")
        cls, target = target, f"{target.__module__}:{target.__qualname__}"
    elif not (isinstance(target, str) and target.count(":") == 1):
        raise InputError("register_method", "target", f"{target!r}, expected a Method subclass or "
                         "'package.module:Class'")
    if name in METHODS and (name in _BUILTIN or not replace) and METHODS[name] != target:
        raise InputError("register_method", "name", f"{name!r} is registered already ({METHODS[name]})"
                         + ("" if name in _BUILTIN else "; pass replace=True to replace it"))
    METHODS[name] = target
    if cls is not None:
        _CLASSES[name] = cls
    else:
        _CLASSES.pop(name, None)


#: Classes registered as objects (one defined in __main__ or in a function cannot be imported by name).
_CLASSES: dict = {}


def _read_entry_points() -> None:
    global _entry_points_read
    if _entry_points_read:
        return
    _entry_points_read = True
    from importlib.metadata import entry_points

    for ep in entry_points(group=ENTRY_POINT_GROUP):
        if ep.name in METHODS and METHODS[ep.name] != ep.value:
            warnings.warn(f"entry point {ep.name} = {ep.value!r} ({ENTRY_POINT_GROUP}): the name is taken by "
                          f"{METHODS[ep.name]}; ignored", McreconWarning, stacklevel=3)
            continue
        METHODS[ep.name] = ep.value


def _load(name: str):
    if name in _CLASSES:
        return _CLASSES[name]
    mod, cls = METHODS[name].split(":")
    obj = importlib.import_module(mod)
    for part in cls.split("."):
        obj = getattr(obj, part)
    if getattr(obj, "name", None) != name:
        raise ImportError(f"{METHODS[name]}.name is {getattr(obj, 'name', None)!r}, registered as {name!r} "
                          "(a run's log records the method's own name: they must agree)")
    return obj


def available_methods() -> list[str]:
    """Names of the registered methods whose module is present."""
    _read_entry_points()
    out = []
    for name in METHODS:
        try:
            _load(name)
        except (ImportError, AttributeError):
            continue
        out.append(name)
    return out


def method_class(name: str) -> type[Method]:
    _read_entry_points()
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


def _defaults_declaring(test) -> list[str]:
    out = []
    for name in available_methods():
        try:
            if test(get_method(name).requires):
                out.append(name)
        except Exception:  # a method that cannot be built with its defaults here (missing extra)
            continue
    return out


def half_buffer_methods() -> list[str]:
    """Names of the registered methods whose default configuration declares ``requires.half_buffers``."""
    return _defaults_declaring(lambda req: req.half_buffers)


def statistics_methods() -> list[str]:
    """Names of the registered methods whose default configuration takes pixel statistics alone."""
    return _defaults_declaring(lambda req: req.statistics and not req.samples and not req.subpixels
                               and not req.range and req.features != "required")


from .._lazy import public_dir as _public_dir  # noqa: E402

__dir__ = _public_dir(__name__)

"""The renderer spec format: what a spec holds, how one is written, and the check of one.

A spec is a small JSON-able dict saying how to build a renderer again
(:mod:`mcrecon.renderers.spec` describes its three kinds and builds
renderers from them).  This module is the part the renderers themselves
use: each one's ``spec()`` writes its kind here, so it sits below them,
and :mod:`.spec`, which builds every kind, sits above them.
"""

from __future__ import annotations

import numbers
import os
from typing import Any, Mapping, Sequence

from ..errors import InputError

__all__ = ["KINDS", "MITSUBA_FEATURES", "check_mitsuba_features", "scene_spec", "command_spec", "mitsuba_spec",
           "check_spec"]

#: The per-sample features the Mitsuba bridge can write, and their components
#: (``features="all"``, its default, is all of them).
MITSUBA_FEATURES: dict[str, int] = {"albedo": 3, "normal": 3, "depth": 1}


#: The built-in scenes' samplers (``SceneRenderer(sampler=)``, a scene spec's ``sampler``, ``--sampler``): here,
#: where the command line can read them without importing the scenes' compiled kernels.
SAMPLERS = ("independent", "sobol")

#: The renderer kinds a spec can name, with their required and optional keys.
KINDS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "scene": (("scene", "width", "height"), ("seed", "features", "sampler", "params")),
    "command": (("argv", "width", "height"), ("channels", "timeout", "workdir", "cwd")),
    "mitsuba": (("width", "height"), ("scene", "features")),
}


# ---------------------------------------------------------------- writing
def scene_spec(scene: str, *, width: int, height: int, seed: int = 0, features: bool | None = None,
               sampler: str | None = None, params: dict | None = None) -> dict:
    """The spec of a built-in scene (:class:`mcrecon.renderers.scenes.SceneRenderer`); ``features``: whether
    it sends its per-sample features (None: the scene's default, recorded as no key); ``sampler``: its
    sampler (None: ``independent``, recorded as no key, as in specs written before samplers existed)."""
    spec = {"kind": "scene", "scene": scene, "width": width, "height": height, "seed": seed}
    if features is not None:
        spec["features"] = features
    if sampler is not None:
        spec["sampler"] = sampler
    if params:  # the scene's parameters other than its defaults (absent: the default scene)
        spec["params"] = dict(params)
    return check_spec(spec)


def command_spec(argv: Sequence[str], *, width: int, height: int, channels: Sequence[str] = ("R", "G", "B"),
                 timeout: float | None = 600.0, workdir=None, cwd=None) -> dict:
    """The spec of an external renderer command (:class:`mcrecon.renderers.command.CommandRenderer`).

    ``cwd`` (default: the current directory, now) is where the command runs,
    recorded as an absolute path: the relative paths of ``argv``
    (``data_tools/example_renderer.py``), and those the renderer opens
    itself, mean the same when the run is resumed from another directory.
    The program is still looked up on ``PATH`` (``python``) unless it is a
    path (``./render``, relative to ``cwd``).  ``workdir`` is recorded as an
    absolute path too.
    """
    return check_spec({"kind": "command", "argv": list(argv), "width": width, "height": height,
                       "channels": list(channels), "timeout": timeout,
                       "workdir": None if workdir is None else os.path.abspath(workdir),
                       "cwd": os.path.abspath(os.getcwd() if cwd is None else cwd)})


def mitsuba_spec(scene=None, *, width: int, height: int, features="all") -> dict:
    """The spec of a Mitsuba 3 scene file (recorded as an absolute path, so a resume from another
    directory finds it), or of the built-in Cornell box for None; ``features`` as
    :class:`~mcrecon.renderers.mitsuba.MitsubaRenderer` (recorded as a comma-separated list or "none")."""
    names = check_mitsuba_features(features, where="mitsuba_spec")
    return check_spec({"kind": "mitsuba", "scene": None if scene is None else os.path.abspath(scene),
                       "width": width, "height": height, "features": ",".join(names) or "none"})


# ---------------------------------------------------------------- checking
def check_spec(spec: Any, *, where: str = "renderer spec", field: str = "renderer_spec") -> dict:
    """A validated copy of ``spec``, with the optional keys filled in.

    Parameters
    ----------
    spec : mapping
        A renderer spec (see the module notes).
    where, field : str
        How errors name the spec: the file it was read from and the
        field that holds it (e.g. a log path and ``run settings renderer_spec``).

    Raises
    ------
    InputError
        Naming ``where``, ``field.KEY`` and what was expected.
    """
    if not isinstance(spec, Mapping):
        raise InputError(where, field, f"got {type(spec).__name__}, expected a mapping with a 'kind' "
                         f"({', '.join(KINDS)})")
    kind = spec.get("kind")
    if kind not in KINDS:
        raise InputError(where, f"{field}.kind", f"{kind!r}; valid: {', '.join(KINDS)}")
    required, optional = KINDS[kind]
    missing = [k for k in required if k not in spec]
    if missing:
        raise InputError(where, f"{field}.{missing[0]}", f"missing: a {kind} spec needs {', '.join(required)}")
    unknown = sorted(set(spec) - {"kind", *required, *optional})
    if unknown:
        raise InputError(where, f"{field}.{unknown[0]}", f"unknown key of a {kind} spec; valid: "
                         f"{', '.join(('kind',) + required + optional)}")

    def bad(key, problem):
        return InputError(where, f"{field}.{key}", f"{spec[key]!r}, expected {problem}")

    def integer(key, minimum):
        v = spec[key]
        if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < minimum:
            raise bad(key, f"an integer >= {minimum}")
        return int(v)

    def strings(key):
        v = spec[key]
        if isinstance(v, str) or not isinstance(v, Sequence) or not v or not all(isinstance(x, str) for x in v):
            raise bad(key, "a non-empty list of strings")
        return [str(x) for x in v]

    def text_or_none(key):
        v = spec.get(key)
        if v is not None and (not isinstance(v, str) or not v):
            raise bad(key, "a non-empty string or null")
        return v

    out = {"kind": kind, "width": integer("width", 1), "height": integer("height", 1)}
    if kind == "scene":
        from .scenes.catalog import SCENES  # the scene registry, at call time: importing this module stays light

        if spec["scene"] not in SCENES:
            raise bad("scene", f"a built-in scene: {', '.join(SCENES)}")
        out["scene"] = spec["scene"]
        out["seed"] = integer("seed", 0) if "seed" in spec else 0
        if "features" in spec:  # absent: the scene's default
            if not isinstance(spec["features"], bool):
                raise bad("features", "true or false (absent: the scene's default)")
            out["features"] = spec["features"]
        if "sampler" in spec:  # absent: independent (what every spec before samplers rendered)
            if spec["sampler"] not in SAMPLERS:
                raise bad("sampler", f"one of {', '.join(SAMPLERS)} (absent: independent)")
            out["sampler"] = spec["sampler"]
        if "params" in spec:  # absent: the scene's default parameters
            from .scenes.params import check_params

            if not isinstance(spec["params"], Mapping):
                raise bad("params", "a mapping of parameter names to numbers (absent: the defaults)")
            out["params"] = check_params(spec["scene"], dict(spec["params"]))
    elif kind == "command":
        argv = strings("argv")
        joined = " ".join(argv)
        if "{request}" not in joined or "{reply}" not in joined:
            raise bad("argv", "a command with the {request} and {reply} placeholders")
        out["argv"] = argv
        out["channels"] = channels = strings("channels") if "channels" in spec else ["R", "G", "B"]
        if len(set(channels)) != len(channels) or any(not c or c != c.strip() or "," in c for c in channels):
            # --channels R,G,B: comma-separated, no spaces, distinct non-empty names
            raise bad("channels", "distinct non-empty names without commas or surrounding spaces, e.g. "
                      "--channels R,G,B (comma-separated, no spaces; the order of the columns of /values)")
        timeout = spec.get("timeout")
        if timeout is not None and (isinstance(timeout, bool) or not isinstance(timeout, numbers.Real)
                                    or not timeout > 0):
            raise bad("timeout", "seconds > 0 or null (no time-out)")
        out["timeout"] = None if timeout is None else float(timeout)
        out["workdir"] = text_or_none("workdir")
        out["cwd"] = cwd = text_or_none("cwd")   # None (a spec without it): the current directory
        if cwd is not None and not os.path.isabs(cwd):
            raise bad("cwd", "an absolute directory (the one the run's command ran in) or null")
    else:
        out["scene"] = text_or_none("scene")
        # a spec written before features existed rendered none: resume it without them
        feats = spec.get("features", "none")
        if not isinstance(feats, str):
            raise bad("features", "a comma-separated string of albedo, normal, depth, or 'none'")
        out["features"] = ",".join(check_mitsuba_features(feats, where=where)) or "none"
    return out


def check_mitsuba_features(features, *, where: str = "MitsubaRenderer") -> tuple[str, ...]:
    """The feature names an option value asks for, in :data:`MITSUBA_FEATURES` order.

    ``"all"`` (every feature), ``"none"``, ``None`` or an empty sequence (no
    features), a comma-separated string (``"albedo,depth"``, as the CLI's
    ``--features``) or a sequence of names.
    """
    valid = ", ".join(MITSUBA_FEATURES)
    if features is None:
        return ()
    if isinstance(features, str):
        if features == "all":
            return tuple(MITSUBA_FEATURES)
        if features == "none":
            return ()
        features = [f.strip() for f in features.split(",")]
    try:
        names = list(features)
    except TypeError:
        raise InputError(where, "features", f"got {type(features).__name__}, expected 'all', 'none' or names "
                         f"from {valid}") from None
    bad = [f for f in names if not isinstance(f, str) or f not in MITSUBA_FEATURES]
    if bad:
        raise InputError(where, "features", f"unknown feature {bad[0]!r}; valid: 'all', 'none', or a "
                         f"comma-separated list of {valid}")
    if len(set(names)) != len(names):
        raise InputError(where, "features", f"{','.join(names)} names a feature twice")
    return tuple(f for f in MITSUBA_FEATURES if f in names)

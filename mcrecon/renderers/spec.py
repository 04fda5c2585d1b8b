"""Renderer specs: how to build a renderer again, as a small JSON-able dict.

An adaptive run records the spec of its renderer in its log
(``adapt(..., renderer_spec=spec)``), so that :func:`mcrecon.adaptive.run.resume`
and ``mcrecon adapt --resume LOG`` can rebuild the renderer and go on
without being told what it was.  Three kinds exist::

    {"kind": "scene",   "scene": NAME, "width": W, "height": H, "seed": S,
                        "features": true | false (optional; absent: the scene's default)}
    {"kind": "command", "argv": [...], "width": W, "height": H,
                        "channels": [...], "timeout": SECONDS or None, "workdir": DIR or None,
                        "cwd": DIR or None}
    {"kind": "mitsuba", "scene": XML or None (the Cornell box), "width": W, "height": H,
                        "features": "albedo,normal,depth" | "none" | ... (default all)}

:func:`scene_spec`, :func:`command_spec` and :func:`mitsuba_spec` write
one; :func:`check_spec` validates one (a spec read back from a log is
data from a file: every field is checked, and an error names it);
:func:`renderer_from_spec` builds the renderer and
:func:`reference_from_spec` its exact reference image, where it has one.

Example
-------
>>> from mcrecon.renderers import scene_spec, renderer_from_spec
>>> spec = scene_spec("flat", width=8, height=4)
>>> renderer_from_spec(spec).name
'scene:flat'
"""

from __future__ import annotations

import numbers
import os
from typing import Any, Mapping, Sequence

from ..errors import InputError

__all__ = ["KINDS", "scene_spec", "command_spec", "mitsuba_spec", "check_spec", "renderer_from_spec",
           "reference_from_spec"]

#: The renderer kinds a spec can name, with their required and optional keys.
KINDS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "scene": (("scene", "width", "height"), ("seed", "features")),
    "command": (("argv", "width", "height"), ("channels", "timeout", "workdir", "cwd")),
    "mitsuba": (("width", "height"), ("scene", "features")),
}


# ---------------------------------------------------------------- writing
def scene_spec(scene: str, *, width: int, height: int, seed: int = 0, features: bool | None = None) -> dict:
    """The spec of a built-in scene (:class:`mcrecon.renderers.scenes.SceneRenderer`); ``features``: whether
    it sends its per-sample features (None: the scene's default, recorded as no key)."""
    spec = {"kind": "scene", "scene": scene, "width": width, "height": height, "seed": seed}
    if features is not None:
        spec["features"] = features
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
    from .mitsuba import check_mitsuba_features

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
        from .scenes import scene_names

        if spec["scene"] not in scene_names():
            raise bad("scene", f"a built-in scene: {', '.join(scene_names())}")
        out["scene"] = spec["scene"]
        out["seed"] = integer("seed", 0) if "seed" in spec else 0
        if "features" in spec:  # absent: the scene's default
            if not isinstance(spec["features"], bool):
                raise bad("features", "true or false (absent: the scene's default)")
            out["features"] = spec["features"]
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
        from .mitsuba import check_mitsuba_features

        out["scene"] = text_or_none("scene")
        # a spec written before features existed rendered none: resume it without them
        feats = spec.get("features", "none")
        if not isinstance(feats, str):
            raise bad("features", "a comma-separated string of albedo, normal, depth, or 'none'")
        out["features"] = ",".join(check_mitsuba_features(feats, where=where)) or "none"
    return out


# ---------------------------------------------------------------- building
def renderer_from_spec(spec, *, where: str = "renderer spec", field: str = "renderer_spec"):
    """The renderer a spec describes (``where`` and ``field`` name the spec in errors, see :func:`check_spec`)."""
    spec = check_spec(spec, where=where, field=field)
    kind, w, h = spec["kind"], spec["width"], spec["height"]
    if kind == "scene":
        from .scenes import SceneRenderer

        return SceneRenderer(spec["scene"], width=w, height=h, seed=spec["seed"], features=spec.get("features"))
    if kind == "command":
        from .command import CommandRenderer

        if spec["cwd"] is not None and not os.path.isdir(spec["cwd"]):
            raise InputError(where, f"{field}.cwd", f"{spec['cwd']!r} is not a directory: the command ran there "
                             "and its relative paths are relative to it; restore it, or resume in Python "
                             "with resume(log, CommandRenderer(..., cwd=DIR))")
        return CommandRenderer(spec["argv"], width=w, height=h, channels=tuple(spec["channels"]),
                               timeout=spec["timeout"], workdir=spec["workdir"], cwd=spec["cwd"])
    from .mitsuba import MitsubaRenderer

    return MitsubaRenderer(spec["scene"], width=w, height=h, features=spec["features"])


def reference_from_spec(spec, *, where: str = "renderer spec", field: str = "renderer_spec"):
    """The exact reference image (H, W, C) float64 of a spec's renderer, or None where it has none.

    Built-in scenes have one (:func:`mcrecon.renderers.scenes.reference_image`);
    commands and Mitsuba scenes do not.
    """
    spec = check_spec(spec, where=where, field=field)
    if spec["kind"] != "scene":
        return None
    from .scenes import reference_image

    return reference_image(spec["scene"], spec["width"], spec["height"])

"""Renderer specs: how to build a renderer again, as a small JSON-able dict.

An adaptive run records the spec of its renderer in its log
(``adapt(..., renderer_spec=spec)``), so that :func:`mcrecon.adaptive.run.resume`
and ``mcrecon adapt --resume LOG`` can rebuild the renderer and go on
without being told what it was.  Three kinds exist::

    {"kind": "scene",   "scene": NAME, "width": W, "height": H, "seed": S,
                        "features": true | false (optional; absent: the scene's default),
                        "sampler": "independent" | "sobol" (optional; absent: independent),
                        "params": {NAME: VALUE} (optional; absent: the scene's defaults)}
    {"kind": "command", "argv": [...], "width": W, "height": H,
                        "channels": [...], "timeout": SECONDS or None, "workdir": DIR or None,
                        "cwd": DIR or None}
    {"kind": "mitsuba", "scene": XML or None (the Cornell box), "width": W, "height": H,
                        "features": "albedo,normal,depth" | "none" | ... (default all)}

:func:`scene_spec`, :func:`command_spec` and :func:`mitsuba_spec` write
one; :func:`check_spec` validates one (a spec read back from a log is
data from a file: every field is checked, and an error names it).  They
live in :mod:`.spec_format`, below the renderers, whose ``spec()`` writes
with them; this module, above the renderers, builds them:
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

import os

from ..errors import InputError
# writing and checking: the part the renderers use themselves, below them
from .spec_format import KINDS, check_spec, command_spec, mitsuba_spec, scene_spec

__all__ = ["KINDS", "scene_spec", "command_spec", "mitsuba_spec", "check_spec", "renderer_from_spec",
           "reference_from_spec"]


# ---------------------------------------------------------------- building
def renderer_from_spec(spec, *, where: str = "renderer spec", field: str = "renderer_spec"):
    """The renderer a spec describes (``where`` and ``field`` name the spec in errors, see :func:`check_spec`)."""
    spec = check_spec(spec, where=where, field=field)
    kind, w, h = spec["kind"], spec["width"], spec["height"]
    if kind == "scene":
        from .scenes import SceneRenderer, get_scene

        return SceneRenderer(get_scene(spec["scene"], spec.get("params")), width=w, height=h, seed=spec["seed"], features=spec.get("features"),
                             sampler=spec.get("sampler", "independent"))
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
    from .scenes import get_scene, reference_image

    return reference_image(get_scene(spec["scene"], spec.get("params")), spec["width"], spec["height"])

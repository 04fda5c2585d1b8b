"""Renderers: the protocol mcrecon speaks with them, and the renderers it ships.

* :mod:`.protocol`: the :class:`Renderer` protocol (the requests and replies it speaks,
  :class:`SampleRequest`, :class:`SampleBatch` and :func:`validate_reply`, are
  :mod:`mcrecon.core.requests`, re-exported here);
* :mod:`.callable`: :class:`CallableRenderer`, a Python function as a renderer;
* :mod:`.command`: ``CommandRenderer``, an external command exchanging HDF5 files;
* :mod:`.scenes`: the built-in procedural scenes with exact references;
* :mod:`.mitsuba`: the optional Mitsuba 3 bridge;
* :mod:`.spec`: how to describe a renderer so that a run can build it again.

Only the light parts are imported here; import :mod:`.command`,
:mod:`.scenes` and :mod:`.mitsuba` by their own names.
"""

from .callable import CallableRenderer
from .protocol import Renderer
from ..core.requests import SampleBatch, SampleRequest, validate_reply
from .spec import (KINDS, check_spec, command_spec, mitsuba_spec, reference_from_spec, renderer_from_spec,
                   scene_spec)

__all__ = ["SampleRequest", "SampleBatch", "Renderer", "validate_reply", "CallableRenderer",
           "KINDS", "scene_spec", "command_spec", "mitsuba_spec", "check_spec", "renderer_from_spec",
           "reference_from_spec"]


from .._lazy import public_dir as _public_dir  # noqa: E402

__dir__ = _public_dir(__name__)

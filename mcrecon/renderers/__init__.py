"""Renderers: how to describe one so that a run can build it again (:mod:`.spec`)."""

from .spec import (KINDS, check_spec, command_spec, mitsuba_spec, reference_from_spec, renderer_from_spec,
                   scene_spec)

__all__ = ["KINDS", "scene_spec", "command_spec", "mitsuba_spec", "check_spec", "renderer_from_spec",
           "reference_from_spec"]

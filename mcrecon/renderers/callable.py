"""A Python callable as a renderer: :class:`CallableRenderer`."""

from __future__ import annotations

from typing import Callable, Sequence

from ..errors import RendererError
from ..core.requests import SampleBatch, SampleRequest

__all__ = ["CallableRenderer"]


class CallableRenderer:
    """Wrap a Python callable ``fn(request) -> SampleBatch | (positions, values)``.

    Parameters
    ----------
    fn : callable
        Called once per round with a :class:`SampleRequest`.
    width, height : int
        Film size.
    channels : sequence of str
        Channel names of the values it returns.
    name : str, optional
        Used in error messages.
    """

    def __init__(self, fn: Callable[[SampleRequest], object], *, width: int, height: int,
                 channels: Sequence[str] = ("R", "G", "B"), name: str | None = None):
        if not callable(fn):
            raise TypeError("fn must be callable")
        self.fn = fn
        self.width = int(width)
        self.height = int(height)
        self.channels = tuple(channels)
        self.name = name or getattr(fn, "__name__", "callable renderer")

    def render(self, request: SampleRequest) -> SampleBatch:
        try:
            reply = self.fn(request)
        except Exception as exc:
            raise RendererError(self.name, "render", f"raised {type(exc).__name__}: {exc}") from exc
        return reply

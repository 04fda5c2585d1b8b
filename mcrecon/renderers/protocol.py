"""The renderer protocol: what mcrecon asks for and what a renderer answers.

A *renderer* is anything with ``width``, ``height``, ``channels`` and a
``render(request) -> SampleBatch`` method (see :class:`Renderer`).  A
request asks for samples in two ways that may be combined:

* ``counts`` (H, W): the renderer places ``counts[j, i]`` samples inside
  pixel (i, j) = [i, i+1) x [j, j+1), choosing the positions itself
  (e.g. with its own low-discrepancy sampler);
* ``positions`` (M, 2): the renderer evaluates exactly these film
  positions (x is the column, y the row).

The reply is a :class:`SampleBatch`: positions (N, 2) and values (N, C),
and optionally per-sample ``features`` (name -> (N,) or (N, k) array; the
canonical ``albedo`` (N, 3), ``normal`` (N, 3), ``depth`` (N,) of
:mod:`mcrecon.core.features`), which the adaptive driver stores in the run's
log and, for methods that declare features, in the statistics.  Every round
must send the same features (``docs/renderer-protocol.md``).
:func:`~mcrecon.core.requests.validate_reply` checks it against the request
before anything is stored: never trust a renderer's reply.  The request and
reply types live in :mod:`mcrecon.core.requests` (methods build requests and
must not import the renderers).
"""

from __future__ import annotations

from typing import Protocol, Sequence, runtime_checkable


from ..core.requests import SampleBatch, SampleRequest

__all__ = ['Renderer']

@runtime_checkable
class Renderer(Protocol):
    """Anything that answers sample requests."""

    width: int
    height: int
    channels: Sequence[str]

    def render(self, request: SampleRequest) -> SampleBatch:  # pragma: no cover - protocol
        ...

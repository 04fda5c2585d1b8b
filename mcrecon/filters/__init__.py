"""Image and sample numerics shared by the methods, with no knowledge of them.

* :mod:`.engine` -- the threaded separable correlation engine, thread counts;
* :mod:`.gaussian` -- the one Gaussian kernel, its pixel-level equivalent of a subpixel grid, scale ladders;
* :mod:`.masked` -- Gaussian smoothing of maps defined on a mask;
* :mod:`.luminance` -- luminance weights;
* :mod:`.fireflies` -- luminance cascades (splitting samples by magnitude).

It imports nothing of mcrecon but :mod:`mcrecon.errors` (docs/architecture.md).
"""

from .._lazy import lazy_exports as _lazy_exports

#: The sub-modules, reachable as attributes (imported on first use).
__all__ = ['engine', 'fireflies', 'gaussian', 'luminance', 'masked']

__getattr__, __dir__ = _lazy_exports(__name__, {}, __all__, __all__)

"""mcrecon: image-space adaptive sampling and reconstruction for Monte Carlo renderers.

The public API in one place::

    import mcrecon
    mcrecon.write_log(path, positions, values, width=W, height=H)
    log = mcrecon.read_log(path)
    image = mcrecon.reconstruct(log, method="gem", gamma=0.2)
    renderer = mcrecon.CallableRenderer(fn, width=W, height=H)   # fn(request) -> (positions, values)
    result = mcrecon.adapt(renderer, "gem", spp=32, log="run.h5")

``import mcrecon`` is cheap: each public name imports its module on first
use (PEP 562), so the command line starts without loading numba, SciPy or
the methods it does not need.
"""

from __future__ import annotations

from ._lazy import lazy_exports as _lazy_exports
from .errors import InputError, McreconWarning, RendererError

__version__ = "0.1.0"

__all__ = ["InputError", "RendererError", "McreconWarning", "write_log", "read_log", "append_log",
           "read_exr", "write_exr", "write_png_preview", "PixelStats", "SampleSet", "Reconstruction", "SampleRequest", "SampleBatch",
           "CallableRenderer", "reconstruct", "restoration", "adapt", "available_methods", "get_method", "__version__",
           # the public modules
           "adaptive", "core", "distributed", "experiments", "filters", "io", "methods", "offline", "renderers"]

#: Public name -> the module that defines it (imported on first access).
_LAZY = {
    "append_log": "io", "read_exr": "io", "read_log": "io", "write_exr": "io", "write_log": "io",
    "write_png_preview": "io",
    "available_methods": "methods", "get_method": "methods",
    "CallableRenderer": "renderers", "SampleBatch": "renderers", "SampleRequest": "renderers",
    "Reconstruction": "offline.reconstruction", "reconstruct": "offline.reconstruction",
    "adapt": "adaptive.run",
    "SampleSet": "core.samples",
    "PixelStats": "core.stats",
}

#: Sub-modules reachable as attributes (``mcrecon.io.read_log``) without importing them first.
_SUBMODULES = frozenset({"adaptive", "cli", "core", "distributed", "errors", "experiments", "filters", "io",
                         "methods", "offline", "renderers", "restoration"})


__getattr__, __dir__ = _lazy_exports(__name__, _LAZY, _SUBMODULES, __all__)

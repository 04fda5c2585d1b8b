"""mcrecon: image-space adaptive sampling and reconstruction for Monte Carlo renderers.

The public API in one place::

    import mcrecon
    mcrecon.write_log(path, positions, values, width=W, height=H)
    log = mcrecon.read_log(path)
    image = mcrecon.reconstruct(log, method="gem", gamma=0.2)
    result = mcrecon.adapt(renderer, "gem", spp=32, log="run.h5")
"""

from __future__ import annotations

from .errors import InputError, McreconWarning, RendererError
from .io import append_log, read_exr, read_log, write_exr, write_log, write_png_preview
from .methods import available_methods, get_method
from .renderers import CallableRenderer, SampleBatch, SampleRequest
from . import restoration
from .reconstruction import Reconstruction, reconstruct
from .samples import SampleSet
from .stats import PixelStats

__version__ = "0.1.0"

__all__ = ["InputError", "RendererError", "McreconWarning", "write_log", "read_log", "append_log",
           "read_exr", "write_exr", "write_png_preview", "PixelStats", "SampleSet", "Reconstruction", "SampleRequest", "SampleBatch",
           "CallableRenderer", "reconstruct", "restoration", "adapt", "available_methods", "get_method", "__version__"]


def adapt(renderer, method, *, spp, **kwargs):
    """Run adaptive rounds; see :func:`mcrecon.driver.adapt`."""
    from .driver import adapt as _adapt

    return _adapt(renderer, method, spp=spp, **kwargs)

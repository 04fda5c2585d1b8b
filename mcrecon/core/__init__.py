"""The data model every layer shares: samples, pixel statistics, half buffers, fill-in, requests, metrics.

* :mod:`.samples` -- sample sources (:class:`SampleSet`), validation, the NaN/Inf policy, memory checks;
* :mod:`.stats` -- :class:`PixelStats`: per-pixel Welford/Chan statistics;
* :mod:`.halves` -- two independent half buffers: checks, the merge, the one-pass split;
* :mod:`.fill` -- the one fill-in policy for pixels with fewer than two samples;
* :mod:`.safeguard` -- 3x3 sample ranges and confidence clamps;
* :mod:`.requests` -- :class:`SampleRequest`, :class:`SampleBatch`;
* :mod:`.metrics` -- error metrics (relative MSE, SMAPE, SSIM, FLIP) and output sanity;
* :mod:`.display` -- the display transform (exposure in stops, sRGB).

It imports nothing of mcrecon but :mod:`mcrecon.errors` and :mod:`mcrecon.filters` (docs/architecture.md).
"""

from .._lazy import lazy_exports as _lazy_exports

#: The sub-modules, reachable as attributes (imported on first use).
__all__ = ['display', 'fill', 'halves', 'metrics', 'requests', 'safeguard', 'samples', 'stats']

__getattr__, __dir__ = _lazy_exports(__name__, {}, __all__, __all__)

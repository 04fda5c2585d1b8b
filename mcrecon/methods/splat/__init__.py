"""``splat``: progressive variable-width Epanechnikov splatting of individual samples (Suykens and Willems 2000).

The method filters *samples*, not pixels: every sample is spread over the
image with an Epanechnikov kernel whose width grows with how "bad" the
sample is compared with the current estimate of the image (Eq. 8), and
shrinks as the number of samples grows; the image is built progressively
in doubling rounds (Fig. 3).  That is ``variant="paper"``; the default
``variant="robust"`` spreads the excess of outliers over their
neighbourhood guided by the local mean, and every consistent sample with
Eq. 8's width, but only into pixels whose statistics (and, when the
samples carry them, features: albedo, normal, depth) do not tell them
apart and within the local gradient's bound (``docs/methods/splat.md``,
"The default filters"); ``variant="outliers"`` moves the outliers' excess
only and leaves every consistent sample in its pixel.

:mod:`.kernels`
    The footprint of one sample: Eq. 4, the numba scatter loops, :func:`splat`.
:mod:`.progressive`
    Eq. 8 widths, the running image of Fig. 3 (:class:`ProgressiveSplatter`),
    round schedules.
:mod:`.outliers`, :mod:`.consistent`
    The default's outlier split, and its gated spread of consistent samples.
:mod:`.bands`
    A round's per-sample passes on the filters' threads, bit for bit one thread's.
:mod:`.method`
    :class:`SplatMethod` behind the method contract.

See ``docs/methods/splat.md`` for the paper-to-code map.

References
----------
.. [1] F. Suykens and Y. D. Willems, "Adaptive Filtering for Progressive
   Monte Carlo Image Rendering", WSCG 2000.
.. [2] I. S. Abramson, "On bandwidth variation in kernel estimates - a
   square root law", Annals of Statistics 10(4), 1982.
"""

from .kernels import BOUNDARY_MODES, epanechnikov, splat
from .method import SplatMethod
from .progressive import GUIDES, NORMS, SPREADS, ProgressiveSplatter, kernel_width, pilot_width, sample_norm
from ...filters.luminance import LUMINANCE_WEIGHTS
# Importable from here as before, though not in __all__:
from .schedule import doubling_schedule  # noqa: F401

__all__ = ["SplatMethod", "ProgressiveSplatter", "epanechnikov", "kernel_width", "pilot_width",
           "sample_norm", "splat", "BOUNDARY_MODES", "NORMS", "LUMINANCE_WEIGHTS", "SPREADS", "GUIDES"]

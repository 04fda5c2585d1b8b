"""``awr``: adaptive wavelet rendering (Overbeck, Donner and Ramamoorthi 2009).

Two stages that can be used together or apart (paper Fig. 10):

Reconstruction (§4.2, :mod:`.reconstruction`)
    The pixel means are analysed with a biorthogonal wavelet; every
    wavelet coefficient is soft-thresholded by its estimated standard
    deviation (Eq. 10, 11), propagated from a per-pixel variance image
    (Eq. 5, 6).  :func:`awr_reconstruct` is the array function.

Adaptive sampling (§4.1, :mod:`.sampling`)
    Scale coefficients ranked by Eq. 8 receive ``64 * 2**k`` samples each,
    importance-sampled from ``|Phi|`` (Fig. 5).  :func:`plan_awr_positions`
    is one batch.

Both rest on :mod:`.wavelets` (the registry of bases, the transform as
matrices, variance propagation, Eq. 9, 10, Appendix A); :mod:`.method`
puts them behind the method contract (:class:`AWRMethod`).  See
``docs/methods/awr.md`` for the equation-to-function map.

References
----------
.. [1] R. S. Overbeck, C. Donner, R. Ramamoorthi, "Adaptive Wavelet
   Rendering", ACM Trans. Graph. 28(5), 140 (SIGGRAPH Asia 2009).
.. [2] D. P. Mitchell, "Generating antialiased images at low sampling
   densities", SIGGRAPH 1987 (the contrast metric, Eq. 5).
.. [3] F. Rousselle, C. Knaus, M. Zwicker, "Adaptive Sampling and
   Reconstruction using Greedy Error Minimization", SIGGRAPH Asia 2011
   (the 1-D two-box comparison, Fig. 6).
"""

from .method import AWRMethod
from .reconstruction import (DOMAINS, VARIANCE_ESTIMATORS, awr_reconstruct, functional_variance,
    log_domain_reconstruct, pixel_variance, soft_threshold)
from ...core.safeguard import confidence_clamp, sample_range_bounds
from .sampling import plan_awr_positions, sample_scale_functions, scale_priorities
from .wavelets import (BOUNDARY_MODES, PROPAGATIONS, RECONSTRUCTION_RENORM, SAMPLING_RENORM, WAVELETS,
                       analysis_matrices, analyze, coefficient_variances, default_levels, equivalent_filter_norms,
                       get_wavelet, renormalisation_factor, synthesize)

__all__ = [
    "WAVELETS", "BOUNDARY_MODES", "VARIANCE_ESTIMATORS", "PROPAGATIONS",
    "SAMPLING_RENORM", "RECONSTRUCTION_RENORM",
    "get_wavelet", "default_levels", "functional_variance", "pixel_variance",
    "analysis_matrices", "analyze", "synthesize", "coefficient_variances",
    "renormalisation_factor", "equivalent_filter_norms", "soft_threshold", "awr_reconstruct", "scale_priorities",
    "sample_scale_functions", "plan_awr_positions", "AWRMethod",
    "DOMAINS", "confidence_clamp", "log_domain_reconstruct", "sample_range_bounds",
]

"""``gem``: adaptive sampling and reconstruction by greedy error minimization.

F. Rousselle, C. Knaus, M. Zwicker, "Adaptive Sampling and Reconstruction
using Greedy Error Minimization", ACM Transactions on Graphics 30(6)
(Proc. SIGGRAPH Asia), 2011.  They pick, at every pixel, one filter out
of a fixed bank (the renderer's pixel filter and Gaussians at growing
scales) so that the pixel's MSE is minimal, and send new samples where
the *relative* MSE of the selected filters falls fastest.
``docs/methods/gem.md`` maps each equation and section of the paper to
the function implementing it.

Modules (each name below is re-exported here):

* :mod:`.kernels` -- Gaussian scales and kernels, the subpixel grid, the
  filter bank (Sec. 6, Eq. 2);
* :mod:`.selection` -- gamma, the fill-in variance, the scale selector
  (Eq. 1), stopping maps, outlier removal, :func:`gem_select`,
  :func:`oracle_select`, :func:`estimate_mse` (Secs. 4-6);
* :mod:`.guard` -- the final reconstruction's regional risk guard (no
  neighbourhood above its pixel means' estimated error; not in the paper);
* :mod:`.sampling` -- sample priorities and their distribution (Sec. 5);
* :mod:`.experiment` -- the error-rate experiment of Sec. 4.3;
* :mod:`.method` -- :class:`GEMMethod`, the method of the registry.

Pipeline (one call of :func:`gem_select`):

1. **Finest scale** (the pixel filter, unbiased): the pixel mean, with the
   variance of Sec. 6 (:func:`mean_variance_policy`, explicit policy for
   n < 2).
2. **Filter bank** (Sec. 6): Gaussian scales, each the pixel-level
   equivalent of "Gaussian on the 4 x 4 subpixel grid, then box-reduce"
   (:func:`pixel_kernel`, exact when subpixels are constant per pixel);
   scales below ``subpixel_exact_below`` px are filtered on the hole-filled
   subpixel grid itself (:func:`filled_subpixels`: empty subpixels take
   the pixel mean, the paper's "two-step pull-push";
   :func:`subpixel_gaussian_exact`).  Variances from the per-pixel mean
   variances filtered with the *squared* kernel (Eq. 2, Sec. 6),
   :func:`filter_bank`.
3. **Scale selector** S (Eq. 1) per pair of consecutive scales with the
   bias term weighted by rho = 1 - 1/|P| and z(gamma) (Sec. 4.3),
   :func:`scale_selector_terms`; binary stopping maps ``S > 0``.  The
   default's final reconstruction sums S over channels weighted by
   1 / (value^2 + 0.01) (the pixel's relative MSE; the paper: a plain sum)
   and counts a Gaussian pair's stop only if the next pair stops too
   (:func:`confirm_pair_stops`; docs/methods/gem.md, "Default vs paper").
4. **Outlier removal** (Sec. 4.4, Sec. 6) on each stopping map,
   :func:`remove_outliers`; the selected scale is the finest with stop = 1
   (:func:`select_from_stops`).  The default's final reconstruction then
   clamps each pixel's scale where its neighbourhood's unbiased error
   estimate says a finer maximum scale does better (:func:`risk_guard`).
5. **Sample distribution** (Sec. 5): accumulated MSE estimates, relative
   MSE with eps = 0.001, priority relMSE * n / (n + n_s); the m best pixels
   each get n samples importance-sampled over their filter,
   :func:`estimate_mse`, :func:`sample_priority`, :func:`distribute_samples`.

The public array functions (:func:`filter_bank`, :func:`gem_select`,
:func:`oracle_select`) refuse NaN or Inf values and negative counts.  The
convolutions run on :mod:`mcrecon.filters.engine` (``MCRECON_THREADS`` sets
its worker threads; results are identical for any number).

References
----------
.. [1] F. Rousselle, C. Knaus, M. Zwicker, "Adaptive Sampling and
   Reconstruction using Greedy Error Minimization", ACM Trans. Graph.
   30(6) (SIGGRAPH Asia), 2011.
.. [2] B. W. Silverman, "Density Estimation for Statistics and Data
   Analysis", Chapman & Hall, 1986 (bias of kernel estimators ~ r^2).
.. [3] D. P. Mitchell, "Generating antialiased images at low sampling
   densities", SIGGRAPH 1987 (subpixel grid for non-uniform densities).
"""

from __future__ import annotations

from .experiment import error_rate_experiment
from .guard import RISK_RADIUS, risk_guard, scale_risks
from .kernels import FilterBank, filled_subpixels, filter_bank, subpixel_gaussian_exact
from ...filters.gaussian import adaptive_sigmas, final_sigmas, gaussian_kernel, kernel_radius, pixel_kernel
from .method import GEMMethod
from .sampling import SAMPLING_EPS, distribute_samples, sample_priority
from .selection import (CHANNEL_EPS, CHANNEL_WEIGHTS, GAMMA_MAX, GEMSelection, bias_coefficient, check_gamma,
    confirm_pair_stops, estimate_mse, gem_select, oracle_select, remove_outliers, scale_selector_terms,
    select_from_stops, stopping_maps, z_of_gamma)
from ...core.fill import mean_variance_policy

__all__ = [
    "GEMMethod",
    "GAMMA_MAX",
    "CHANNEL_WEIGHTS",
    "CHANNEL_EPS",
    "SAMPLING_EPS",
    "z_of_gamma",
    "check_gamma",
    "confirm_pair_stops",
    "adaptive_sigmas",
    "final_sigmas",
    "gaussian_kernel",
    "pixel_kernel",
    "kernel_radius",
    "filled_subpixels",
    "subpixel_gaussian_exact",
    "mean_variance_policy",
    "FilterBank",
    "filter_bank",
    "bias_coefficient",
    "scale_selector_terms",
    "stopping_maps",
    "remove_outliers",
    "select_from_stops",
    "GEMSelection",
    "gem_select",
    "oracle_select",
    "estimate_mse",
    "RISK_RADIUS",
    "scale_risks",
    "risk_guard",
    "sample_priority",
    "distribute_samples",
    "error_rate_experiment",
]

"""Statistical analysis of sampled pixels: the tools behind ``mcrecon bias`` and ``mcrecon experiment normality``.

* :mod:`~mcrecon.methods.ci.analysis.grouping`: samples grouped by pixel (each
  pixel's empirical distribution), from arrays or a sample source.
* :mod:`~mcrecon.methods.ci.analysis.bootstrap`: bootstrap estimation and correction
  of the bias of the ``ci`` stopping rule (Tamstorf and Jensen, Sec. 4).
* :mod:`~mcrecon.methods.ci.analysis.normality`: the chi-square test of the normality
  of pixel estimates that the ``ci`` interval assumes (Sec. 3, 5.1).

Like the methods, nothing here opens a file: sample logs come in as sample
sources (:mod:`mcrecon.core.samples`).  The names import their module (numba,
SciPy) on first use (PEP 562).
"""

from __future__ import annotations

from ...._lazy import lazy_exports as _lazy_exports

__all__ = ["PixelSamples", "group_samples", "group_log", "BiasEstimate", "BootstrapBiasResult", "bootstrap_bias",
           "bootstrap_bias_samples", "bootstrap_bias_log", "exact_two_point_bias", "ChiSquareResult",
           "chi2_normality", "repeated_estimates", "normality_experiment"]

#: Public name -> the sub-module that defines it.
_LAZY = {
    **dict.fromkeys(("BiasEstimate", "BootstrapBiasResult", "bootstrap_bias", "bootstrap_bias_log",
                     "bootstrap_bias_samples", "exact_two_point_bias"), "bootstrap"),
    **dict.fromkeys(("PixelSamples", "group_log", "group_samples"), "grouping"),
    **dict.fromkeys(("ChiSquareResult", "chi2_normality", "normality_experiment", "repeated_estimates"),
                    "normality"),
}


#: Sub-modules reachable as attributes without importing them first.
_SUBMODULES = frozenset(("bootstrap", "grouping", "normality"))


__getattr__, __dir__ = _lazy_exports(__name__, _LAZY, _SUBMODULES, __all__)

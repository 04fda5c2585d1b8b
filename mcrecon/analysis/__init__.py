"""Statistical analysis of sampled pixels: the tools behind ``mcrecon bias`` and ``mcrecon experiment normality``.

* :mod:`~mcrecon.analysis.grouping`: samples grouped by pixel (each
  pixel's empirical distribution), from arrays or a sample source.
* :mod:`~mcrecon.analysis.bootstrap`: bootstrap estimation and correction
  of the bias of the ``ci`` stopping rule (Tamstorf and Jensen, Sec. 4).
* :mod:`~mcrecon.analysis.normality`: the chi-square test of the normality
  of pixel estimates that the ``ci`` interval assumes (Sec. 3, 5.1).

Like the methods, nothing here opens a file: sample logs come in as sample
sources (:mod:`mcrecon.samples`).
"""

from __future__ import annotations

from .bootstrap import (BiasEstimate, BootstrapBiasResult, bootstrap_bias, bootstrap_bias_log,
                        bootstrap_bias_samples, exact_two_point_bias)
from .grouping import PixelSamples, group_log, group_samples
from .normality import ChiSquareResult, chi2_normality, normality_experiment, repeated_estimates

__all__ = ["PixelSamples", "group_samples", "group_log", "BiasEstimate", "BootstrapBiasResult", "bootstrap_bias",
           "bootstrap_bias_samples", "bootstrap_bias_log", "exact_two_point_bias", "ChiSquareResult",
           "chi2_normality", "repeated_estimates", "normality_experiment"]

"""``nfor``: Bitterli et al. 2016, nonlinearly weighted first-order regression (``docs/methods/nfor.md``).

* :mod:`.nlmeans` -- NL-means weights with the variance-normalised patch distance, per-channel filtering;
* :mod:`.regression` -- collaborative first-order regression (Sec. 5.2);
* :mod:`.pipeline` -- the stages on arrays (:func:`nfor_denoise`: the array-level API);
* :mod:`.method` -- :class:`NFORMethod`, the registered method.
"""

from __future__ import annotations

from .method import NFORMethod, NFORRun
from ...filters.nlmeans import nlmeans_filter
from .pipeline import PAPER, estimate_mse, nfor_denoise
from ...filters.regression import collaborative_regression

__all__ = ["NFORMethod", "NFORRun", "PAPER", "collaborative_regression", "estimate_mse", "nfor_denoise",
           "nlmeans_filter"]

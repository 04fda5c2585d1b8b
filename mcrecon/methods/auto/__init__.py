"""``auto``: per-pixel selection among reconstructions by their estimated error (``docs/methods/auto.md``).

* :mod:`.method` -- :class:`AutoMethod`, the registered method;
* :mod:`.nlmeans` -- cross-filtered non-local means with the variance-normalised
  patch distance of Rousselle, Knaus, Zwicker 2012.

The error estimators live in :mod:`mcrecon.methods.auto.estimates`.
"""

from __future__ import annotations

from .method import CANDIDATES, DEFAULT_CANDIDATES, DUAL_BUFFER, AutoMethod, AutoRun
from .nlmeans import nlmeans_cross

__all__ = ["AutoMethod", "AutoRun", "CANDIDATES", "DEFAULT_CANDIDATES", "DUAL_BUFFER", "nlmeans_cross"]

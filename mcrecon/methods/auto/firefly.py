"""A firefly pixel: one whose own mean is carried by a rare huge sample of its own.

The global prior (:func:`.selection._global_prior`) judges such a pixel as one its vote leaves out: it
keeps a default that is not a black box only where that default is nearer its neighbours than the
per-pixel choice (docs/methods/auto.md, "Global prior").
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ...filters.engine import parallel_rows
from ...filters.order import neighbour_median8
from .passes import _c64

__all__ = ["HEAVY_TAIL", "FIREFLY", "Z_FIREFLY"]

#: A pixel's neighbourhood is heavy-tailed when the largest sample around it exceeds this many times its mean.
HEAVY_TAIL = 10.0
#: Whether a pixel whose own mean is a firefly (:func:`_firefly`) keeps a non-steady default only where it is
#: nearer its neighbours than the per-pixel choice, as the pixels the vote leaves out do.
FIREFLY = True
#: Standard errors of its neighbours' means (the root of the median of their 8 variances) by which a
#: firefly pixel's mean (:func:`_firefly`) lies above their median: under Gaussian noise practically never
#: (at 8 spp, a dark background's means are 10x their neighbours' median at many pixels, 1-3 such errors
#: above it: the procedural blobs of tests/test_auto.py cost 1.19x without this test).
Z_FIREFLY = 10.0


@numba.njit(cache=True, nogil=True)
def _firefly_rows(y, v, scale, hi, heavy, z, out, i0, i1):
    """``y``, ``v``: the means and their variances, already divided by ``scale`` and its square where
    ``scale`` is not empty (``hi`` is not: colour)."""
    h, w, c = y.shape
    scaled = scale.size > 0
    for i in range(i0, i1):
        for j in range(w):
            hit = False
            for ch in range(c):
                yc = y[i, j, ch]
                raw = yc * scale[i, j, ch] if scaled else yc
                if not (yc > 0 and hi[i, j, ch] > heavy * raw):
                    continue
                med = neighbour_median8(y, i, j, ch)
                if yc > heavy * med and yc - med > z * math.sqrt(max(neighbour_median8(v, i, j, ch), 0.0)):
                    hit = True
            out[i, j] = hit


def _firefly(y, v, hi, scale=None) -> np.ndarray:
    """The pixels whose own mean is a firefly, (H, W) bool: in some channel the 3 x 3 sample maximum ``hi``
    above :data:`HEAVY_TAIL` times the pixel's mean, and that mean above :data:`HEAVY_TAIL` times the median
    ``m`` of its 8 neighbours' means and above ``m`` by :data:`Z_FIREFLY` times the root of the median of
    their variances ``v`` (means and variances divided by ``scale``, the albedo, and its square where given:
    on a texture a neighbour's colour is another square's).  Such a pixel's mean is carried by a rare huge
    sample of its own, and a default whose value there is its mean (NL-means: the pixel's patch is like no
    other) keeps the firefly; the vote's own test (:data:`.apart.HEAVY_PRIOR`, 30x) misses it where the sample is
    10-30x the mean.  False where a value is NaN."""
    out = np.zeros(y.shape[:2], bool)
    yr, vr = (y, v) if scale is None else (y / scale, v / (scale * scale))
    sc = np.ones((0, 0, 0)) if scale is None else scale
    parallel_rows(_firefly_rows, (_c64(yr), _c64(vr), _c64(sc), _c64(hi), HEAVY_TAIL, Z_FIREFLY, out), y.shape[0])
    return out

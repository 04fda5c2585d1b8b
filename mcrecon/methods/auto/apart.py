"""The pixels auto's global prior leaves out of its vote (:func:`_apart`): rare huge samples around, or far
brighter than the neighbourhood.  Read by the selection's vote (:mod:`.selection`) and by an adaptive round's
thin-vote test (:func:`.thinvote.thin_vote_shown`).
"""

from __future__ import annotations

import numba
import numpy as np

from ...core.metrics import DEFAULT_EPS
from ...filters.engine import parallel_rows
from ...filters.order import median9
from .estimates import relative_denominator_loo
from .passes import _c64, _nanmax

__all__ = ["HEAVY_PRIOR"]

#: The global prior leaves out pixels whose 3 x 3 sample maximum exceeds this many times their mean
#: and their 3 x 3 neighbourhood's mean (rare huge samples around).  Not HEAVY_TAIL's 10: 32 exponential samples per pixel exceed 10x
#: their mean somewhere in a 3 x 3 neighbourhood at ~4 % of the pixels, 30x practically never.
HEAVY_PRIOR = 30.0


@numba.njit(cache=True, nogil=True, inline="always")
def _abs0(x):
    return abs(x) if np.isfinite(x) else 0.0


@numba.njit(cache=True, nogil=True)
def _apart_rows(y, v, hi, den_loo, heavy, bright, need_v, out, i0, i1):
    # rows [i0, i1) of _apart; |y| read as 0 where y is not finite
    h, w, c = y.shape
    for i in range(i0, i1):
        ia, ib = max(i - 1, 0), min(i + 1, h - 1)
        for j in range(w):
            ja, jb = max(j - 1, 0), min(j + 1, w - 1)
            apart = False
            any_v = False
            for ch in range(c):
                yc = y[i, j, ch]
                ay = _abs0(yc)
                if hi[i, j, ch] > heavy * ay:
                    med = median9(_abs0(y[ia, ja, ch]), _abs0(y[ia, j, ch]), _abs0(y[ia, jb, ch]),
                                  _abs0(y[i, ja, ch]), ay, _abs0(y[i, jb, ch]),
                                  _abs0(y[ib, ja, ch]), _abs0(y[ib, j, ch]), _abs0(y[ib, jb, ch]))
                    if hi[i, j, ch] > heavy * med:
                        apart = True
                if _nanmax(yc * yc - v[i, j, ch], 0.0) > bright * den_loo[i, j, ch]:
                    apart = True
                if v[i, j, ch] > 0:
                    any_v = True
            out[i, j] = apart or (need_v and not any_v)


def _apart(y: np.ndarray, v: np.ndarray, hi: np.ndarray, den_loo: np.ndarray, need_v: bool) -> np.ndarray:
    """The pixels the global prior leaves out, (H, W) bool: in any channel, rare huge samples around (the
    3 x 3 sample maximum ``hi`` above :data:`HEAVY_PRIOR` times both ``|y|`` and the median of ``|y|``
    over the 3 x 3 neighbourhood, edges repeated), or far brighter than the neighbourhood
    (``max(y^2 - v, 0)`` above ``HEAVY_PRIOR^2`` times ``den_loo``); with ``need_v`` also pixels without
    variance in any channel.  One compiled pass, the median only where the first test fires."""
    out = np.empty(y.shape[:2], bool)
    parallel_rows(_apart_rows, (_c64(y), _c64(v), _c64(hi), _c64(den_loo), HEAVY_PRIOR, HEAVY_PRIOR ** 2,
                                bool(need_v), out), y.shape[0])
    return out


def left_out(y: np.ndarray, v: np.ndarray, count: np.ndarray, hi: np.ndarray, need_v: bool):
    """``(den_loo, apart)`` of a frame's statistics: the leave-one-out relative denominator the vote's
    estimates are divided by (:func:`.estimates.relative_denominator_loo`) and the pixels the vote leaves out
    (:func:`_apart` on it).  ``hi``: the top of the pixels' sample range."""
    den_loo = relative_denominator_loo(y, v, count, eps=DEFAULT_EPS)
    return den_loo, _apart(y, v, hi, den_loo, need_v)

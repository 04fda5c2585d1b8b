"""Order statistics of a pixel's neighbourhood: medians of 8 and 9 numbers by compare-exchange networks.

A network only selects (min and max, no arithmetic), so its result is the
value a sort would put there (of +0 and -0, which compare equal, not
necessarily the same one: a caller whose output could keep the zero's sign
takes a zero from its sort); unlike an insertion sort it has no
data-dependent branches, which is what costs time when the values are
noise (a mispredicted branch per element), and it vectorises over a row.
With a NaN among the inputs min and max do not order them: callers take
the networks only for NaN-free inputs.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["median9", "middle8", "neighbour_median8", "neighbour_medians8"]


@numba.njit(cache=True, nogil=True, inline="always")
def median9(p0, p1, p2, p3, p4, p5, p6, p7, p8):
    """The median of 9 numbers by the 19 compare-exchanges of Paeth's network."""
    p1, p2 = min(p1, p2), max(p1, p2)
    p4, p5 = min(p4, p5), max(p4, p5)
    p7, p8 = min(p7, p8), max(p7, p8)
    p0, p1 = min(p0, p1), max(p0, p1)
    p3, p4 = min(p3, p4), max(p3, p4)
    p6, p7 = min(p6, p7), max(p6, p7)
    p1, p2 = min(p1, p2), max(p1, p2)
    p4, p5 = min(p4, p5), max(p4, p5)
    p7, p8 = min(p7, p8), max(p7, p8)
    p3 = max(p0, p3)
    p5 = min(p5, p8)
    p4, p7 = min(p4, p7), max(p4, p7)
    p6 = max(p3, p6)
    p4 = max(p1, p4)
    p2 = min(p2, p5)
    p4 = min(p4, p7)
    p4, p2 = min(p4, p2), max(p4, p2)
    p4 = max(p6, p4)
    return min(p4, p2)


@numba.njit(cache=True, nogil=True, inline="always")
def middle8(p0, p1, p2, p3, p4, p5, p6, p7):
    """The 4th and 5th smallest of 8 numbers (whose mean is their median), by Batcher's odd-even merge
    network cut to the compare-exchanges and halves of them that reach these two."""
    p0, p1 = min(p0, p1), max(p0, p1)
    p2, p3 = min(p2, p3), max(p2, p3)
    p4, p5 = min(p4, p5), max(p4, p5)
    p6, p7 = min(p6, p7), max(p6, p7)
    p0, p2 = min(p0, p2), max(p0, p2)
    p1, p3 = min(p1, p3), max(p1, p3)
    p4, p6 = min(p4, p6), max(p4, p6)
    p5, p7 = min(p5, p7), max(p5, p7)
    p1, p2 = min(p1, p2), max(p1, p2)
    p5, p6 = min(p5, p6), max(p5, p6)
    p4 = max(p0, p4)
    p5 = max(p1, p5)
    p2 = min(p2, p6)
    p3 = min(p3, p7)
    p4 = max(p2, p4)
    p3 = min(p3, p5)
    p3, p4 = min(p3, p4), max(p3, p4)
    return p3, p4


@numba.njit(cache=True, nogil=True, inline="always")
def neighbour_median8(q, i, j, ch):
    """The median of the 8 neighbours of pixel (i, j) of ``q`` (H, W, C) in channel ``ch``, edges repeated
    (the mean of the middle pair, as :func:`numpy.median` computes it); NaN if any of them is NaN."""
    h, w = q.shape[0], q.shape[1]
    ia, ib = max(i - 1, 0), min(i + 1, h - 1)
    ja, jb = max(j - 1, 0), min(j + 1, w - 1)
    p0, p1, p2, p3 = q[ia, ja, ch], q[ia, j, ch], q[ia, jb, ch], q[i, ja, ch]
    p4, p5, p6, p7 = q[i, jb, ch], q[ib, ja, ch], q[ib, j, ch], q[ib, jb, ch]
    if p0 != p0 or p1 != p1 or p2 != p2 or p3 != p3 or p4 != p4 or p5 != p5 or p6 != p6 or p7 != p7:
        return np.nan
    a, b = middle8(p0, p1, p2, p3, p4, p5, p6, p7)
    return (a + b) / 2.0


@numba.njit(cache=True, nogil=True)
def neighbour_medians8(q, i, med):
    """:func:`neighbour_median8` of every pixel of row ``i`` but the first and last, all channels:
    ``med[(j - 1) * C + ch]``, in one loop over equal-length slices of the three rows (vectorised).
    Returns how many are NaN."""
    h, w, c = q.shape
    n = w * c
    m = max(n - 2 * c, 0)
    ra, rb, rd = q[max(i - 1, 0)].reshape(n), q[i].reshape(n), q[min(i + 1, h - 1)].reshape(n)
    a0, a1, a2 = ra[:m], ra[c:c + m], ra[2 * c:2 * c + m]
    b0, b2 = rb[:m], rb[2 * c:2 * c + m]
    d0, d1, d2 = rd[:m], rd[c:c + m], rd[2 * c:2 * c + m]
    odd = 0
    for k in range(m):
        a, b = middle8(a0[k], a1[k], a2[k], b0[k], b2[k], d0[k], d1[k], d2[k])
        med[k] = (a + b) / 2.0
        t = a0[k] + a1[k] + a2[k] + b0[k] + b2[k] + d0[k] + d1[k] + d2[k]
        odd += t != t  # a NaN among them, or +inf and -inf
    nan = 0
    if odd:
        for k in range(m):
            t = a0[k] + a1[k] + a2[k] + b0[k] + b2[k] + d0[k] + d1[k] + d2[k]
            if t != t:
                med[k] = neighbour_median8(q, i, k // c + 1, k % c)
                nan += med[k] != med[k]
    return nan

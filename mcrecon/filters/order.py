"""Order statistics of a pixel's neighbourhood: medians of 8 and 9 numbers by compare-exchange networks.

A network only selects (min and max, no arithmetic), so its result is the
same element a sort would put there, bit for bit; unlike an insertion sort
it has no data-dependent branches, which is what costs time when the
values are noise (a mispredicted branch per element).  With a NaN among the
inputs min and max do not order them: callers take the networks only for
NaN-free inputs.
"""

from __future__ import annotations

import numba

__all__ = ["median9", "middle8"]


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

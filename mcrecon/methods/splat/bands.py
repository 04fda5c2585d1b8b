"""A round's per-sample passes on the filters' thread pool, bit for bit as on one thread.

A pass that adds samples into per-pixel sums (the image, the statistics) runs
in bands of image rows: each thread follows the samples in order and adds only
into its own rows, so every pixel receives the same terms in the same order as
from one thread, whatever the bands.  When the rows of a chunk's samples never
decrease (renderers reply pixel by pixel), a band's thread visits only the
samples of its rows (and of the rows within reach of it); otherwise it visits
every sample and skips the others' (the skip costs a pass over the positions,
about as much as a cheap pass itself).  A pass that writes one value per sample
runs on ranges of the samples.  Threads: the filters' setting
(:func:`mcrecon.filters.engine.n_threads`, ``$MCRECON_THREADS``).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ...filters.engine import n_threads, parallel_calls

#: Passes over fewer samples run on the calling thread: a band costs a task on the pool.
BAND_MIN = 1 << 16


def _parts(n_samples: int, threads: int | None) -> int:
    return n_threads(threads) if n_samples >= BAND_MIN else 1


@numba.njit(cache=True, nogil=True, inline="always")
def _row_of(pos, k, h):
    return min(max(int(math.floor(pos[k, 1])), 0), h - 1)


@numba.njit(cache=True, nogil=True)
def _rows_never_decrease(pos, h):
    prev = 0
    for k in range(pos.shape[0]):
        y = pos[k, 1]
        if y < prev:  # a row (floor of y, clipped to the film) below the last one: y below its start
            if _row_of(pos, k, h) < _row_of(pos, k - 1, h):
                return False
        else:
            prev = math.floor(y)
    return True


@numba.njit(cache=True, nogil=True)
def _first_at_rows(pos, h, rows, out):
    """``out[i]``: the first sample at a row >= ``rows[i]`` (binary search: the rows never decrease)."""
    for i in range(rows.shape[0]):
        lo = 0
        hi = pos.shape[0]
        while lo < hi:
            mid = (lo + hi) // 2
            if _row_of(pos, mid, h) < rows[i]:
                lo = mid + 1
            else:
                hi = mid
        out[i] = lo


def rows_sorted(pos, height: int, *, threads: int | None = None) -> bool:
    """Whether the samples' rows never decrease, when the passes over them run in bands (else False: a
    single band visits every sample anyway)."""
    return _parts(pos.shape[0], threads) > 1 and bool(_rows_never_decrease(pos, height))


def row_bands(row_work, n: int) -> list[tuple[int, int]]:
    """At most ``n`` bands of consecutive rows ``(j0, j1)`` covering the film, of about equal
    ``row_work`` (the work of each row, e.g. its samples; its length is the film's height)."""
    row_work = np.asarray(row_work, dtype=np.float64)
    h = row_work.shape[0]
    cum = np.cumsum(row_work)
    if n <= 1 or h <= 1 or not cum[-1] > 0.0:
        return [(0, h)]
    cuts = np.searchsorted(cum, cum[-1] * np.arange(1, n) / n, side="left") + 1
    edges = np.unique(np.concatenate([[0], np.clip(cuts, 1, h - 1), [h]]))
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def in_bands(kernel, args, pos, height: int, *, row_work=None, sorted_rows: bool = False, reach: int = 0,
             threads: int | None = None) -> list:
    """``kernel(*args, k0, k1, j0, j1)`` for bands of rows ``(j0, j1)`` covering the film, one per thread
    (:func:`row_bands` of ``row_work``, else of equal rows), on the pool; the band's pass visits the samples
    ``k0 <= k < k1`` of ``pos``: with ``sorted_rows`` (:func:`rows_sorted`) those of the rows
    ``j0 - reach <= j < j1 + reach``, else all.  Returns the results in band order."""
    n = pos.shape[0]
    bands = row_bands(np.ones(height) if row_work is None else row_work, _parts(n, threads))
    if sorted_rows and len(bands) > 1:
        rows = np.array([max(j0 - reach, 0) for j0, _ in bands] + [min(j1 + reach, height) for _, j1 in bands],
                        np.int64)
        at = np.empty(rows.shape[0], np.int64)
        _first_at_rows(pos, height, rows, at)
        ranges = [(int(a), int(b)) for a, b in zip(at[:len(bands)], at[len(bands):])]
    else:
        ranges = [(0, n)] * len(bands)
    return parallel_calls(kernel, [tuple(args) + (k0, k1, j0, j1) for (k0, k1), (j0, j1) in zip(ranges, bands)],
                          threads)


def in_ranges(kernel, args, n_samples: int, *, threads: int | None = None) -> list:
    """``kernel(*args, k0, k1)`` for consecutive ranges of the samples, one per thread (one below
    :data:`BAND_MIN`), on the pool: for a pass that writes one value per sample.  Returns the results in
    range order."""
    n = _parts(n_samples, threads)
    return parallel_calls(kernel, [tuple(args) + (n_samples * t // n, n_samples * (t + 1) // n) for t in range(n)],
                          threads)

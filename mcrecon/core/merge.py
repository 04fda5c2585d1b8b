"""The Chan et al. merge of two sets of per-pixel statistics, as one compiled pass (:meth:`PixelStats.merge`).

Each output element is computed, term for term, by the NumPy expressions
the merge was first written with (``np.minimum``/``np.maximum`` included:
NaN propagates, and of two equal values the second is kept), so the
results are bit-identical to them; but every array is read and written
once, without the temporaries (several the size of the mean) those
expressions allocated, and :meth:`PixelStats.merged` writes new statistics
without copying the first input first.  The output may be the first input
(a merge in place): each element is read before it is written.

The merge of one run of samples into a pixel (:func:`_run_add`, :func:`_merge_run`) is written here
once for :meth:`PixelStats.add` (:func:`_accumulate`) and the half buffers' split
(:mod:`mcrecon.core.halves`), whose statistics of a half are then bit for bit those of its samples
added alone.
"""

from __future__ import annotations

from collections.abc import MutableMapping

import numpy as np

from .samples import lazy_njit

__all__ = ["merge_moments", "MergedOnRead"]

#: What the kernels get for the ``min``/``max`` of statistics that keep no range (``ranged`` False):
#: an empty array of the range's type, never indexed.
NO_RANGE = np.empty((0, 0, 0))

@lazy_njit(cache=True, nogil=True, inline="always")
def _run_add(acc, lo, hi, v):
    """The sum and the extremes of a run of samples, with the value ``v`` added."""
    return acc + v, min(lo, v), max(hi, v)


@lazy_njit(cache=True, nogil=True, inline="always")
def _merge_run(mean, m2, vmin, vmax, iy, ix, c, na, wb, mu, q, lo, hi, ranged):
    """Chan et al.'s merge of a run of samples into channel ``c`` of pixel (iy, ix) (in place).

    The run's mean ``mu``, sum of squared deviations ``q`` and extremes ``lo``, ``hi``; the pixel held
    ``na`` samples before it, and ``wb`` is the run's share of all of them, m / (na + m).  ``ranged``
    False: statistics without a range (a feature's: ``vmin``/``vmax`` are empty and not written).
    """
    delta = mu - mean[iy, ix, c]
    mean[iy, ix, c] += delta * wb
    m2[iy, ix, c] += q + delta * delta * na * wb
    if ranged:
        vmin[iy, ix, c] = min(vmin[iy, ix, c], lo)
        vmax[iy, ix, c] = max(vmax[iy, ix, c], hi)


#: Rows merged by one task of the filters' thread pool (a task costs ~20 us).
_ROWS_PER_TASK = 64


@lazy_njit(cache=True, nogil=True)
def _merge_rows(count_a, mean_a, m2_a, min_a, max_a, count_b, mean_b, m2_b, min_b, max_b, count, mean, m2, vmin,
                vmax, ranged, i0, i1):
    for i in range(i0, i1):
        for j in range(count_a.shape[1]):
            na = float(count_a[i, j])
            nb = float(count_b[i, j])
            n = na + nb
            wb = nb / n if n > 0 else 0.0
            count[i, j] = count_a[i, j] + count_b[i, j]
            for c in range(mean_a.shape[2]):
                delta = mean_b[i, j, c] - mean_a[i, j, c]
                m2[i, j, c] = m2_a[i, j, c] + (m2_b[i, j, c] + delta * delta * na * wb)
                mean[i, j, c] = mean_a[i, j, c] + delta * wb
                if not ranged:
                    continue
                lo, hi = min_a[i, j, c], min_b[i, j, c]
                vmin[i, j, c] = lo if lo < hi or lo != lo else hi
                lo, hi = max_a[i, j, c], max_b[i, j, c]
                vmax[i, j, c] = lo if lo > hi or lo != lo else hi


def merge_moments(a, b, out) -> None:
    """Write the Chan merge of ``a`` and ``b`` (count, mean, m2, min, max) into ``out``'s arrays.

    ``a``, ``b`` and ``out`` are :class:`~mcrecon.core.stats.PixelStats`
    of one film and channels (``out`` may be ``a``).  Statistics that keep
    no range (a feature's, ``min`` None) merge count, mean and ``m2``.  Row
    blocks are merged on the filters' thread pool
    (:func:`mcrecon.filters.engine.parallel_calls`).
    """
    from ..filters.engine import parallel_calls

    h = a.count.shape[0]
    ranged = a.min is not None and b.min is not None and out.min is not None
    lo_hi = lambda st: (st.min, st.max) if ranged else (NO_RANGE, NO_RANGE)  # noqa: E731
    arrays = (a.count, a.mean, a.m2, *lo_hi(a), b.count, b.mean, b.m2, *lo_hi(b),
              out.count, out.mean, out.m2, *lo_hi(out), ranged)
    parallel_calls(_merge_rows, [arrays + (i, min(i + _ROWS_PER_TASK, h)) for i in range(0, h, _ROWS_PER_TASK)])


class MergedOnRead(MutableMapping):
    """The features of the merge of two statistics, each merged from the two inputs' features when read.

    The dispatcher's merge of the halves it splits (:func:`mcrecon.offline.inputs.statistics_for`)
    keeps its features this way: a method reads the merged colour throughout and a feature's merge
    once or twice (nfor: the features' variance before its filter, the albedo after it), so the
    merged features are never held all at once beside the filter's buffers (at 1920 x 1080 with
    albedo, normal and depth: 0.28 GB).  Each read merges anew (the same bits each time): a write
    into a feature read from here does not persist; :meth:`PixelStats.merge` into such statistics
    first makes their features a plain dict.  ``layout`` is ``{name: components}`` without a merge.
    """

    def __init__(self, a, b):
        self._a, self._b = a, b
        self._set = {}
        self.layout = {name: len(st.channels) for name, st in a.items()}

    def __getitem__(self, name):
        if name in self._set:
            return self._set[name]
        if name not in self.layout:
            raise KeyError(name)
        return self._a[name].merged(self._b[name])

    def __setitem__(self, name, value):
        self._set[name] = value
        self.layout[name] = len(value.channels)

    def __delitem__(self, name):
        if name not in self.layout:
            raise KeyError(name)
        del self.layout[name]
        self._set.pop(name, None)

    def __iter__(self):
        return iter(tuple(self.layout))

    def __len__(self):
        return len(self.layout)


@lazy_njit(cache=True, nogil=True)
def _accumulate(pos, val, s, count, mean, m2, vmin, vmax, ranged, sub_sum, sub_count, oy, ox):
    """Add every sample into the per-pixel arrays (in place; ``vmin``/``vmax`` only when ``ranged``).

    Renderers usually emit the samples of a pixel one after another, so
    the loop takes *runs* of consecutive samples in the same pixel: a
    two-pass mean and sum of squared deviations over the run (exact and
    stable, in cache), then one Chan et al. merge into the pixel.  A run
    of one sample is exactly Welford's update.  Values must be finite and
    positions valid (the caller applies the policies first, see ``_scan``).

    The arrays hold the window of the film whose first pixel is (``oy``,
    ``ox``) and whose size is ``count``'s: runs are found on every sample
    (a window's runs are the film's) and those of other pixels skipped.
    """
    nch = val.shape[1]
    n_total = pos.shape[0]
    hh, ww = count.shape
    k = 0
    while k < n_total:
        ix = int(pos[k, 0])
        iy = int(pos[k, 1])
        end = k + 1
        while end < n_total and int(pos[end, 0]) == ix and int(pos[end, 1]) == iy:
            end += 1
        if not (0 <= iy - oy < hh and 0 <= ix - ox < ww):
            k = end
            continue
        m = end - k
        py = iy - oy
        px = ix - ox
        na = count[py, px]
        n = na + m
        count[py, px] = n
        wb = m / n
        for c in range(nch):
            acc = 0.0
            lo = np.inf
            hi = -np.inf
            for j in range(k, end):
                acc, lo, hi = _run_add(acc, lo, hi, float(val[j, c]))
            mu = acc / m
            q = 0.0
            for j in range(k, end):
                d = float(val[j, c]) - mu
                q += d * d
            _merge_run(mean, m2, vmin, vmax, py, px, c, na, wb, mu, q, lo, hi, ranged)
        if s > 0:
            last = s - 1
            for j in range(k, end):
                sx = int(pos[j, 0] * s)
                sy = int(pos[j, 1] * s)
                # x * s can round up past the pixel's last subpixel; keep it inside.
                sx = min(sx, ix * s + last) - ox * s
                sy = min(sy, iy * s + last) - oy * s
                sub_count[sy, sx] += 1
                for c in range(nch):
                    sub_sum[sy, sx, c] += float(val[j, c])
        k = end

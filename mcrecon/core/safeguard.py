"""Safeguards of a reconstruction against its samples: 3x3 sample ranges, confidence clamps.
"""

from __future__ import annotations


import numba
import numpy as np

from ..filters.engine import parallel_rows
from ..filters.order import median9
from .stats import PixelStats

__all__ = ['sample_range_bounds', 'confidence_clamp', 'pooled_mean_variance']

# --------------------------------------------------------------------------
# Safeguard of the robust default (not in the paper)
# --------------------------------------------------------------------------

@numba.njit(cache=True, nogil=True)
def _neighbourhood_range(lo_src, hi_src, has, radius, lo, hi, i0, i1):
    # rows [i0, i1): (2 radius + 1)^2 (edge pixels repeated) min of lo_src / max of hi_src over pixels
    # with samples, per channel; no sample around: (-inf, inf)
    h, w, c = lo_src.shape
    for i in range(i0, i1):
        for j in range(w):
            for ch in range(c):
                a = np.inf
                b = -np.inf
                for di in range(-radius, radius + 1):
                    ii = min(max(i + di, 0), h - 1)
                    for dj in range(-radius, radius + 1):
                        jj = min(max(j + dj, 0), w - 1)
                        if has[ii, jj]:
                            a = min(a, lo_src[ii, jj, ch])
                            b = max(b, hi_src[ii, jj, ch])
                lo[i, j, ch] = a if np.isfinite(a) else -np.inf
                hi[i, j, ch] = b if np.isfinite(b) else np.inf


def sample_range_bounds(stats: PixelStats, radius: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Smallest and largest sample of each pixel's (2 radius + 1)^2 neighbourhood, per channel.

    The range :func:`mcrecon.core.metrics.output_sanity` checks a reconstruction
    against.  Statistics without a per-pixel range (built from moments)
    use the neighbourhood's pixel means instead (a narrower range inside
    the samples' one).  A neighbourhood without any sample gets
    ``(-inf, inf)``: no bound.  One compiled pass (min and max are exact:
    equal to ``scipy.ndimage`` minimum/maximum filters with ``nearest``
    edges, tested).
    """
    src_lo, src_hi = (stats.min, stats.max) if stats.has_range else (stats.mean, stats.mean)
    lo = np.empty(stats.mean.shape)
    hi = np.empty(stats.mean.shape)
    parallel_rows(_neighbourhood_range, (np.ascontiguousarray(src_lo, dtype=np.float64),
                                         np.ascontiguousarray(src_hi, dtype=np.float64),
                                         np.ascontiguousarray(stats.count > 0), int(radius), lo, hi), lo.shape[0])
    return lo, hi


def confidence_clamp(image: np.ndarray, mean: np.ndarray, var_mean: np.ndarray, k: float,
                     lo: np.ndarray | None = None, hi: np.ndarray | None = None) -> np.ndarray:
    """Clamp a reconstruction into each pixel's confidence interval of its mean.

    ``out = clip(image, a, b)`` with ``a = max(mean - k se, lo)``,
    ``b = min(mean + k se, hi)``, ``se = sqrt(var_mean)`` (the standard
    error of the pixel mean), and the interval widened to contain ``mean``
    if the bounds ``lo``/``hi`` exclude it.

    Why: the interval ``mean +- k se`` holds the true pixel value with high
    probability wherever the mean is reliable.  Clipping onto an interval
    that contains the true value never moves an estimate away from it
    (projection onto a convex set), and bounds every pixel's departure
    from its mean by ``k`` standard errors.  So wavelet shrinkage can still
    remove noise where the mean is uncertain, but it cannot smear an
    emitter's large rim variance into dim neighbours whose means are
    precise (AWR's failure on HDR edges, docs/methods/awr.md).  A pixel
    whose samples all agree (se = 0) keeps its mean.  ``lo``/``hi``
    (:func:`sample_range_bounds`) keep the output inside the range of the
    samples around it: no negative pixel from non-negative samples.

    Parameters
    ----------
    image, mean, var_mean : ndarray, same shape
    k : float
        Interval half-width in standard errors (>= 0; 0 returns ``mean``).
    lo, hi : ndarray, optional
        Extra bounds (same shape; ``-inf``/``inf`` for none).
    """
    image = np.asarray(image, dtype=np.float64)
    mean = np.asarray(mean, dtype=np.float64)
    # the same operations in place: two image-sized temporaries, not eight (fresh memory costs more
    # than the arithmetic)
    half = np.maximum(np.asarray(var_mean, dtype=np.float64), 0.0)
    np.sqrt(half, out=half)
    np.multiply(float(k), half, out=half)
    a = mean - half
    b = np.add(mean, half, out=half)
    if lo is not None:
        np.maximum(a, lo, out=a)
    if hi is not None:
        np.minimum(b, hi, out=b)
    np.minimum(a, mean, out=a)
    np.maximum(b, mean, out=b)
    return np.clip(image, a, b, out=a)


@numba.njit(cache=True, nogil=True)
def _pooled_rows(v, count, radius, out, i0, i1):
    # rows [i0, i1): per pixel and channel, max(v, median of n_q v_q over the neighbourhood's pixels q
    # with samples / n).  A full 3 x 3 neighbourhood without NaN (nearly every pixel) takes the median by
    # the network: the same element the sort gives, unless it is a zero (+0 and -0 sort as equals, and
    # which one the sort keeps can decide the output's sign), which takes the sort
    h, w, c = v.shape
    side = 2 * radius + 1
    buf = np.empty(side * side)
    for i in range(i0, i1):
        for j in range(w):
            n = count[i, j]
            for ch in range(c):
                out[i, j, ch] = v[i, j, ch]
            if n <= 0:
                continue
            full = radius == 1 and 0 < i < h - 1 and 0 < j < w - 1
            if full:
                for ii in range(i - 1, i + 2):
                    for jj in range(j - 1, j + 2):
                        if count[ii, jj] <= 0:
                            full = False
            for ch in range(c):
                if full:
                    p0, p1, p2 = count[i - 1, j - 1] * v[i - 1, j - 1, ch], count[i - 1, j] * v[i - 1, j, ch], \
                        count[i - 1, j + 1] * v[i - 1, j + 1, ch]
                    p3, p4, p5 = count[i, j - 1] * v[i, j - 1, ch], count[i, j] * v[i, j, ch], \
                        count[i, j + 1] * v[i, j + 1, ch]
                    p6, p7, p8 = count[i + 1, j - 1] * v[i + 1, j - 1, ch], count[i + 1, j] * v[i + 1, j, ch], \
                        count[i + 1, j + 1] * v[i + 1, j + 1, ch]
                    t = p0 + p1 + p2 + p3 + p4 + p5 + p6 + p7 + p8
                    med = median9(p0, p1, p2, p3, p4, p5, p6, p7, p8)
                    if t == t and med != 0.0:
                        if med / n > out[i, j, ch]:
                            out[i, j, ch] = med / n
                        continue
                m = 0
                for ii in range(max(i - radius, 0), min(i + radius + 1, h)):
                    for jj in range(max(j - radius, 0), min(j + radius + 1, w)):
                        if count[ii, jj] > 0:
                            x = count[ii, jj] * v[ii, jj, ch]
                            k = m  # insertion sort into buf[:m] (NaN sorts last, as np.sort puts it)
                            while k > 0 and (buf[k - 1] > x or (x == x and buf[k - 1] != buf[k - 1])):
                                buf[k] = buf[k - 1]
                                k -= 1
                            buf[k] = x
                            m += 1
                med = buf[m // 2] if m % 2 == 1 else 0.5 * (buf[m // 2 - 1] + buf[m // 2])
                if med / n > out[i, j, ch]:
                    out[i, j, ch] = med / n


def pooled_mean_variance(var_mean: np.ndarray, count: np.ndarray, radius: int = 1) -> np.ndarray:
    """Each pixel's variance of its mean, floored by its neighbourhood's typical per-sample variance.

    ``max(v_p, median_q(n_q v_q) / n_p)`` over the pixels ``q`` with samples
    in the ``(2 radius + 1)^2`` neighbourhood of ``p`` (cut at the film's
    border); empty pixels keep ``v_p``.  Per channel.

    Why: a pixel's own sample variance misses what its samples missed.
    Under a rare large component (a small light found by 1 sample in 20,
    a caustic) the pixels that drew none of it have a small variance and a
    low mean, and an interval ``mean +- k sqrt(v)`` built on them excludes
    the true value: the confidence clamp then pins a good reconstruction
    back onto the noise (auto on the built-in checker_spot: 0.39 of the
    pixel mean's error with the clamp on the pixel's own variance, 0.22
    without any clamp).  Their neighbours did draw it; the median of the
    neighbourhood's per-sample variances says how spread a pixel's samples
    typically are there.  A median, not a mean or a maximum: beside an
    emitter's rim (a line of high-variance pixels) most of a dim pixel's
    3 x 3 neighbours are dim, so its interval stays narrow and the clamp
    still stops a filter from smearing the rim into it.

    Parameters
    ----------
    var_mean : ndarray (H, W, C)
        Variance of each pixel's mean (:func:`mcrecon.core.fill.mean_variance_policy`).
    count : ndarray (H, W)
        Samples per pixel.
    radius : int
        Neighbourhood radius (1: 3 x 3).
    """
    v = np.ascontiguousarray(var_mean, dtype=np.float64)
    if v.ndim != 3 or count.shape != v.shape[:2]:
        raise ValueError(f"pooled_mean_variance: var_mean (H, W, C) and count (H, W) expected, got "
                         f"{v.shape} and {count.shape}")
    out = np.empty_like(v)
    parallel_rows(_pooled_rows, (v, np.ascontiguousarray(count, dtype=np.int64), int(radius), out), v.shape[0])
    return out

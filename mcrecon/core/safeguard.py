"""Safeguards of a reconstruction against its samples: 3x3 sample ranges, confidence clamps.
"""

from __future__ import annotations

import contextlib

import numba
import numpy as np

from ..filters.box import box_any, box_mean
from ..filters.engine import parallel_rows
from ..filters.order import median9
from .stats import PixelStats

__all__ = ['sample_range_bounds', 'widened_range_bounds', 'confidence_clamp', 'pooled_mean_variance', 'albedo_divisor',
           'safeguard_variance', 'empty_pixels_kept',
           'neighbourhood_mean_variance', 'rare_component_mask', 'rare_component_variance']

# --------------------------------------------------------------------------
# Safeguard of the robust default (not in the paper)
# --------------------------------------------------------------------------

@numba.njit(cache=True, nogil=True)
def _neighbourhood_range(lo_src, hi_src, has, radius, lo, hi, i0, i1):
    # rows [i0, i1): (2 radius + 1)^2 (edge pixels repeated) min of lo_src / max of hi_src over pixels
    # with samples, per channel (NaN never taken); no sample around: (-inf, inf).  Separable, over
    # whole rows (vectorised): the min of the column minima.  Exact, as min and max are, but for
    # which of +0 and -0 wins a tie: a zero is taken again in the pixel-by-pixel scan's order, as
    # are the first and last columns.
    h, w, c = lo_src.shape
    n = w * c
    r = radius
    m = max(n - 2 * r * c, 0)
    cmin = np.empty(n)
    cmax = np.empty(n)
    for i in range(i0, i1):
        every = True
        for di in range(-r, r + 1):
            ii = min(max(i + di, 0), h - 1)
            for j in range(w):
                every = every and has[ii, j]
        for q in range(n):
            cmin[q] = np.inf
            cmax[q] = -np.inf
        for di in range(-r, r + 1):
            ii = min(max(i + di, 0), h - 1)
            lr, hr = lo_src[ii].reshape(n), hi_src[ii].reshape(n)
            if every:
                for q in range(n):
                    cmin[q] = min(cmin[q], lr[q])
                    cmax[q] = max(cmax[q], hr[q])
            else:
                for j in range(w):
                    if has[ii, j]:
                        for ch in range(c):
                            q = j * c + ch
                            cmin[q] = min(cmin[q], lr[q])
                            cmax[q] = max(cmax[q], hr[q])
        lo1, hi1 = lo[i].reshape(n)[r * c:r * c + m], hi[i].reshape(n)[r * c:r * c + m]
        for k in range(m):
            lo1[k] = np.inf
            hi1[k] = -np.inf
        for dj in range(2 * r + 1):
            a, b = cmin[dj * c:dj * c + m], cmax[dj * c:dj * c + m]
            for k in range(m):
                lo1[k] = min(lo1[k], a[k])
                hi1[k] = max(hi1[k], b[k])
        zeros = 0
        for k in range(m):
            a, b = lo1[k], hi1[k]
            zeros += (a == 0.0) | (b == 0.0)
            lo1[k] = a if np.isfinite(a) else -np.inf
            hi1[k] = b if np.isfinite(b) else np.inf
        for j in range(w):
            inner = r <= j < w - r
            if inner and zeros == 0:
                continue
            for ch in range(c):
                if inner and lo[i, j, ch] != 0.0 and hi[i, j, ch] != 0.0:
                    continue
                a = np.inf
                b = -np.inf
                for di in range(-r, r + 1):
                    ii = min(max(i + di, 0), h - 1)
                    for dj in range(-r, r + 1):
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


#: The neighbourhood radius of :func:`widened_range_bounds` (2: 5 x 5, as
#: :func:`neighbourhood_mean_variance`'s).
WIDE_RANGE = 2


def widened_range_bounds(stats: PixelStats, where: np.ndarray, lo: np.ndarray, hi: np.ndarray, *,
                         radius: int = WIDE_RANGE) -> tuple[np.ndarray, np.ndarray]:
    """``(lo, hi)`` with the :func:`sample_range_bounds` of a ``(2 radius + 1)^2`` neighbourhood at ``where``.

    Why: under a rarely found bright component (a spotlight or caustic found by a sample in 30) every
    sample of a 3 x 3 neighbourhood can miss it, and the 3 x 3 range's top then lies below the truth:
    clamped into that range, the reference itself keeps half the pixel mean's error at such pixels.
    Where the clamp's interval is built on the wider neighbourhood's mean variance (the pixels of a
    black-box default, :func:`neighbourhood_mean_variance`), the range comes from the same wider
    neighbourhood, whose samples find the component.  Elsewhere the 3 x 3 range stays: beside an
    emitter's rim it keeps a blur from carrying the emitter into dim pixels.

    Parameters
    ----------
    stats : PixelStats
        The statistics ``lo`` and ``hi`` came from.
    where : ndarray of bool (H, W)
        The pixels that take the wider range.
    lo, hi : ndarray (H, W, C)
        The 3 x 3 bounds (:func:`sample_range_bounds`); not modified.
    radius : int
        The wider neighbourhood's radius (> 1).
    """
    if not np.any(where):
        return lo, hi
    lo_w, hi_w = sample_range_bounds(stats, radius)
    at = np.asarray(where, dtype=bool)[..., None]
    return np.where(at, lo_w, lo), np.where(at, hi_w, hi)


def confidence_clamp(image: np.ndarray, mean: np.ndarray, var_mean: np.ndarray, k: float,
                     lo: np.ndarray | None = None, hi: np.ndarray | None = None,
                     out: np.ndarray | None = None) -> np.ndarray:
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
    out : ndarray, optional
        C-contiguous float64 array of the result's shape to write into
        (``image`` itself may be given); default a new one.
    """
    # one compiled pass of numpy's operations (np.maximum, np.minimum and np.clip as numpy computes
    # them: the first NaN, else the second operand on a tie of +0 and -0), bit-identical to
    # np.clip(image, np.minimum(np.maximum(mean - half, lo), mean), np.maximum(np.minimum(mean + half, hi),
    # mean)) with half = k * np.sqrt(np.maximum(var_mean, 0)) (tested); eight image-sized temporaries
    # cost more than the arithmetic
    arrs = np.broadcast_arrays(*[np.asarray(a, dtype=np.float64) for a in (image, mean, var_mean)
                                 + tuple(b for b in (lo, hi) if b is not None)])
    shape = arrs[0].shape
    rows = shape[0] if len(shape) > 1 else 1
    flat = [np.ascontiguousarray(a).reshape(rows, -1) for a in arrs]
    it = iter(flat[3:])
    lo_f = next(it) if lo is not None else None
    hi_f = next(it) if hi is not None else None
    out = np.empty(shape) if out is None else out
    if out.shape != shape or out.dtype != np.float64 or not out.flags.c_contiguous:
        raise ValueError("confidence_clamp: out must be a C-contiguous float64 array of the result's shape")
    parallel_rows(_clamp_rows, (flat[0], flat[1], flat[2], float(k), lo_f, hi_f, out.reshape(rows, -1)), rows)
    return out


@contextlib.contextmanager
def empty_pixels_kept(image: np.ndarray, count: np.ndarray):
    """Within the block, clamp ``image`` in place; every pixel without a sample leaves it with its value on entry.

    A pixel without samples has no confidence interval (its mean 0, its
    variance 0): :func:`confidence_clamp` and the rules that follow it would
    set it to 0, while its value, filled in from its sampled neighbours
    (:func:`mcrecon.core.fill.fill_empty_pixels`), is the reconstruction's
    best guess there.  ``image`` (H, W, C) and ``count`` (H, W).
    """
    empty = np.asarray(count) == 0
    filled = image[empty] if empty.any() else None
    yield image
    if filled is not None:
        image[empty] = filled


@numba.njit(cache=True, nogil=True, inline="always")
def _np_max(a, b):
    # np.maximum: the first NaN, else the larger, the second on a tie (+0 and -0)
    return a if a != a else (b if b != b else (a if a > b else b))


@numba.njit(cache=True, nogil=True, inline="always")
def _np_min(a, b):
    return a if a != a else (b if b != b else (a if a < b else b))


@numba.njit(cache=True, nogil=True)
def _clamp_rows(image, mean, var, k, lo, hi, out, i0, i1):
    for i in range(i0, i1):
        for p in range(image.shape[1]):
            m = mean[i, p]
            half = k * np.sqrt(_np_max(var[i, p], 0.0))
            a = m - half
            b = m + half
            if lo is not None:
                a = _np_max(a, lo[i, p])
            if hi is not None:
                b = _np_min(b, hi[i, p])
            out[i, p] = _np_min(_np_max(image[i, p], _np_min(a, m)), _np_max(b, m))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _pooled_rows(v, count, radius, out, i0, i1):
    # rows [i0, i1): per pixel and channel, max(v, median of n_q v_q over the neighbourhood's pixels q
    # with samples / n).  An interior pixel whose 3 x 3 neighbours all have samples (nearly every pixel)
    # takes the median from the network, run with the floor over a whole row in one loop on
    # equal-length slices (vectorised, no data-dependent branch): the element the sort gives, unless
    # NaN is among them or it is a zero (+0 and -0 sort as equals, and which one the sort keeps can
    # decide the output's sign).  Those, and the other pixels, are redone with the sort.
    h, w, c = v.shape
    n = w * c
    m = max(n - 2 * c, 0)
    buf = np.empty((2 * radius + 1) ** 2)
    x = np.empty((3, n))  # n_q v_q of rows i - 1, i, i + 1 (a ring: row r in x[r % 3])
    col = np.empty(w, np.bool_)  # the 3 pixels of column j in those rows have samples
    cnt = np.empty(n)  # row i's counts, per value
    med = np.empty(m)
    tot = np.empty(m)
    have = -2  # the last row in the ring
    for i in range(i0, i1):
        orow, vrow = out[i].reshape(n), v[i].reshape(n)
        for q in range(n):
            orow[q] = vrow[q]
        fast = radius == 1 and 0 < i < h - 1 and w > 2
        every = False  # every pixel of the row between its first and last has a full neighbourhood
        redo = 1  # values the network leaves to the sort
        if fast:
            for r in range(max(i - 1, have + 1), i + 2):
                xr = x[r % 3]
                for j in range(w):
                    for ch in range(c):
                        xr[j * c + ch] = count[r, j] * v[r, j, ch]
            have = i + 1
            for j in range(w):
                col[j] = count[i - 1, j] > 0 and count[i, j] > 0 and count[i + 1, j] > 0
                for ch in range(c):
                    cnt[j * c + ch] = count[i, j]
            xa, xb, xd = x[(i - 1) % 3], x[i % 3], x[(i + 1) % 3]
            a0, a1, a2 = xa[:m], xa[c:c + m], xa[2 * c:]
            b0, b1, b2 = xb[:m], xb[c:c + m], xb[2 * c:]
            d0, d1, d2 = xd[:m], xd[c:c + m], xd[2 * c:]
            o1, v1, n1 = orow[c:c + m], vrow[c:c + m], cnt[c:c + m]
            redo = 0
            for q in range(m):
                md = median9(a0[q], a1[q], a2[q], b0[q], b1[q], b2[q], d0[q], d1[q], d2[q])
                med[q] = md
                t = a0[q] + a1[q] + a2[q] + b0[q] + b1[q] + b2[q] + d0[q] + d1[q] + d2[q]
                tot[q] = t
                redo += (t != t) | (md == 0.0)
                f = md / n1[q]
                o1[q] = f if f > v1[q] else v1[q]
            every = True
            for j in range(w):
                every = every and col[j]
        for j in range(w):
            if every and redo == 0 and 0 < j < w - 1:
                continue
            nn = count[i, j]
            full = fast and 0 < j < w - 1 and col[j - 1] and col[j] and col[j + 1]
            for ch in range(c):
                if full:
                    q = (j - 1) * c + ch
                    if tot[q] == tot[q] and med[q] != 0.0:
                        continue
                out[i, j, ch] = v[i, j, ch]
                if nn <= 0:
                    continue
                k = 0
                for ii in range(max(i - radius, 0), min(i + radius + 1, h)):
                    for jj in range(max(j - radius, 0), min(j + radius + 1, w)):
                        if count[ii, jj] > 0:
                            xq = count[ii, jj] * v[ii, jj, ch]
                            p = k  # insertion sort into buf[:k] (NaN sorts last, as np.sort puts it)
                            while p > 0 and (buf[p - 1] > xq or (xq == xq and buf[p - 1] != buf[p - 1])):
                                buf[p] = buf[p - 1]
                                p -= 1
                            buf[p] = xq
                            k += 1
                md = buf[k // 2] if k % 2 == 1 else 0.5 * (buf[k // 2 - 1] + buf[k // 2])
                if md / nn > out[i, j, ch]:
                    out[i, j, ch] = md / nn


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


def albedo_divisor(stats: PixelStats) -> np.ndarray | None:
    """Each pixel's albedo as a divisor of its colour, or None without an ``albedo`` feature.

    :func:`~mcrecon.filters.demodulation.demodulation_divisor` of the albedo's pixel means
    (floored at 0.02); empty pixels take their nearest sampled neighbour's albedo.
    """
    import warnings

    from ..errors import McreconWarning
    from ..filters.demodulation import demodulation_divisor
    from .fill import fill_empty_pixels

    alb = stats.features.get("albedo") if stats.features else None
    if alb is None:
        return None
    mean = alb.mean
    if (alb.count == 0).any():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", McreconWarning)  # the colour's fill warns once for the pixel
            mean = fill_empty_pixels(mean.copy(), alb.count, source="albedo")
    return demodulation_divisor(mean, stats.mean.shape[2])


def safeguard_variance(var_mean: np.ndarray, count: np.ndarray, divisor: np.ndarray | None = None) -> np.ndarray:
    """The variance a confidence clamp is built on: :func:`pooled_mean_variance`, in units of the albedo.

    With ``divisor`` (:func:`albedo_divisor`, (H, W, C)) the neighbourhood is pooled in units of each
    pixel's albedo, ``pooled_mean_variance(v / d^2) d^2``: on a texture a light square's
    neighbourhood holds dark squares, whose variance in colour units would narrow its interval.
    """
    if divisor is None:
        return pooled_mean_variance(var_mean, count)
    d2 = divisor * divisor
    return pooled_mean_variance(var_mean / d2, count) * d2


def neighbourhood_mean_variance(var_mean: np.ndarray, count: np.ndarray, *, radius: int = 2,
                                divisor: np.ndarray | None = None) -> np.ndarray:
    """Each pixel's variance of its mean from the *mean* per-sample variance of its neighbourhood.

    ``mean_q(n_q v_q / d_q^2) d_p^2 / n_p`` over the pixels ``q`` with samples in the
    ``(2 radius + 1)^2`` neighbourhood of ``p`` (cut at the film's border), ``d`` the ``divisor``
    (the albedo, :func:`albedo_divisor`; 1 without); empty pixels keep ``var_mean``.  Per channel.

    Why a mean, where :func:`pooled_mean_variance` takes a median: under rare huge samples (a caustic, a
    spotlight found by a sample in 30) most pixels' samples missed the rare component, so their own
    variances, and the median of their neighbourhood's, are far below the true variance; the mean of
    the per-sample variances is unbiased for it wherever the neighbourhood shares one distribution.
    An interval built on it holds the true value where the median's excludes it.  Wide beside an
    emitter's rim, where the median is the right guard against smearing: the caller decides where
    the wider interval applies.

    Parameters
    ----------
    var_mean : ndarray (H, W, C)
        Variance of each pixel's mean.
    count : ndarray (H, W)
        Samples per pixel.
    radius : int
        Neighbourhood radius (2: 5 x 5).
    divisor : ndarray (H, W, C), optional
        Positive; the pooling runs in units of it.
    """
    v = np.ascontiguousarray(var_mean, dtype=np.float64)
    if v.ndim != 3 or count.shape != v.shape[:2]:
        raise ValueError(f"neighbourhood_mean_variance: var_mean (H, W, C) and count (H, W) expected, got "
                         f"{v.shape} and {count.shape}")
    n = np.ascontiguousarray(count, dtype=np.float64)
    # a writable copy (a read-only view would compile the kernels a second time)
    d2 = np.ones((1, 1, 1)) if divisor is None else \
        np.array(np.broadcast_to(np.asarray(divisor, dtype=np.float64) ** 2, v.shape), order="C")
    per_sample = np.empty(v.shape)
    ok = np.empty(v.shape)
    _per_sample_variance(v, n, d2, divisor is not None, per_sample, ok)
    # the box means as scipy's uniform_filter(size=(5, 5, 1), mode="constant") computes them, bit for bit
    num = box_mean(per_sample, radius, "constant")
    den = box_mean(ok, radius, "constant")
    out = np.empty(v.shape)
    _pooled_variance(num, den, d2, divisor is not None, n, v, out)
    return out


@numba.njit(cache=True, nogil=True)
def _per_sample_variance(v, n, d2, div, per_sample, ok):
    # np.where(has & isfinite(v), v * n / d2, 0.0) and (has & isfinite(v)) as float64, has = n > 0
    h, w, c = v.shape
    for i in range(h):
        for j in range(w):
            for ch in range(c):
                x = v[i, j, ch]
                if n[i, j] > 0 and np.isfinite(x):
                    y = x * n[i, j]
                    per_sample[i, j, ch] = y / d2[i, j, ch] if div else y
                    ok[i, j, ch] = 1.0
                else:
                    per_sample[i, j, ch] = 0.0
                    ok[i, j, ch] = 0.0


@numba.njit(cache=True, nogil=True)
def _pooled_variance(num, den, d2, div, n, v, out):
    # np.where(has & (den > 0), np.maximum(num / den * d2 / n, 0.0), v): numpy's maximum keeps a NaN
    h, w, c = v.shape
    for i in range(h):
        for j in range(w):
            for ch in range(c):
                dn = den[i, j, ch]
                if n[i, j] > 0 and dn > 0:
                    p = num[i, j, ch] / dn
                    if div:
                        p = p * d2[i, j, ch]
                    p = p / n[i, j]
                    out[i, j, ch] = p if (p > 0.0 or p != p) else 0.0
                else:
                    out[i, j, ch] = v[i, j, ch]


#: Per-sample relative variance ``s^2 / (mean^2 + RARE_EPS)`` above which a pixel's samples show a rare
#: bright component (:func:`rare_component_variance`): a component of relative size ``L`` found with
#: probability ``p`` gives about ``1 / p``; an edge or a texture inside a pixel at most about 1.
RARE_THRESHOLD = 5.0
#: The ``eps`` of that ratio (radiance units squared): dark pixels with a little noise stay below it.
RARE_EPS = 1e-4


def rare_component_mask(var_mean: np.ndarray, mean: np.ndarray, count: np.ndarray, *, radius: int = 2,
                        threshold: float = RARE_THRESHOLD) -> np.ndarray:
    """(H, W, C) bool: where a pixel of the ``(2 radius + 1)^2`` neighbourhood shows a rare bright component.

    A pixel's per-sample relative variance ``n v / (mean^2 + RARE_EPS)``
    (``v`` the variance of its mean) above ``threshold``, per channel: one
    sample of ``n`` carrying all of a pixel's value gives ``n``, a
    component found with probability ``p`` about ``1 / p``, a texture inside
    the pixel about 1 or less; but a sharp edge's bright side over a share
    ``s`` of an otherwise black pixel reads ``(1 - s) / s`` like a component
    found with probability ``s``: 3 or more below a quarter, so high-contrast
    edges pass a gate of 3 (docs/adaptive.md, mitsuba-thin_lens).  Arguments
    as :func:`rare_component_variance`.
    """
    v = np.ascontiguousarray(var_mean, dtype=np.float64)
    m = np.ascontiguousarray(mean, dtype=np.float64)
    if v.ndim != 3 or m.shape != v.shape or count.shape != v.shape[:2]:
        raise ValueError(f"rare_component_variance: var_mean and mean (H, W, C), count (H, W) expected, got "
                         f"{v.shape}, {m.shape} and {count.shape}")
    rel = np.empty(v.shape)
    above = np.empty(v.shape, np.bool_)
    if _relative_variance(v, m, np.ascontiguousarray(count, dtype=np.float64), float(threshold), rel, above):
        # a NaN ratio (inf / inf: values near the float64 range): scipy's maximum filter decides as it does
        from scipy.ndimage import maximum_filter

        size = (2 * radius + 1, 2 * radius + 1, 1)
        return maximum_filter(rel, size=size, mode="nearest") > threshold
    # the window's maximum exceeds the threshold wherever one of its entries does
    return box_any(above, radius)


@numba.njit(cache=True, nogil=True)
def _relative_variance(v, m, n, threshold, rel, above):
    # rel = np.where((n > 0) & isfinite(v) & isfinite(m), v * n / (m * m + RARE_EPS), 0.0), above = rel >
    # threshold; returns whether a ratio is NaN
    h, w, c = v.shape
    nan = False
    for i in range(h):
        for j in range(w):
            for ch in range(c):
                x = v[i, j, ch]
                mu = m[i, j, ch]
                r = 0.0
                if n[i, j] > 0 and np.isfinite(x) and np.isfinite(mu):
                    r = x * n[i, j] / (mu * mu + RARE_EPS)
                    if r != r:
                        nan = True
                rel[i, j, ch] = r
                above[i, j, ch] = r > threshold
    return nan


def rare_component_variance(var_mean: np.ndarray, mean: np.ndarray, count: np.ndarray, *, radius: int = 2,
                            threshold: float = RARE_THRESHOLD) -> np.ndarray:
    """Each pixel mean's variance, floored at its neighbourhood's mean where a neighbour shows a rare component.

    Where most samples miss a rare bright component (a small light found by
    one sample in 20, a caustic), the pixels whose few samples all missed it
    have a variance near 0 and a low mean: an allocation that reads their
    own variance sends them nothing, exactly where their means lack the
    component.  A neighbour whose samples found it shows a per-sample
    relative variance ``n v / (mean^2 + eps)`` of about ``1 / p``; wherever
    one in the ``(2 radius + 1)^2`` neighbourhood exceeds ``threshold``
    (per channel), the pixel takes ``max(v, neighbourhood mean)``
    (:func:`neighbourhood_mean_variance`, unbiased for the shared rare
    component's variance).  Elsewhere (edges, textures, a penumbra's lit
    side, whose neighbourhood variance is another distribution's) each
    pixel keeps its own.  Empty pixels keep ``var_mean``.

    Parameters
    ----------
    var_mean : ndarray (H, W, C)
        Variance of each pixel's mean.
    mean : ndarray (H, W, C)
        Pixel means.
    count : ndarray (H, W)
        Samples per pixel.
    radius : int
        Neighbourhood radius (2: 5 x 5).
    threshold : float
        Per-sample relative variance that marks a rare component.
    """
    v = np.asarray(var_mean, dtype=np.float64)
    rare = rare_component_mask(v, mean, count, radius=radius, threshold=threshold)
    return np.where(rare, np.maximum(v, neighbourhood_mean_variance(v, count, radius=radius)), v)

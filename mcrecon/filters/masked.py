"""Gaussian smoothing of maps defined on a mask (undefined pixels neither read nor written).
"""

from __future__ import annotations


import numba
import numpy as np
from scipy import ndimage

from .engine import correlate_jobs, parallel_rows


def smooth_masked(a: np.ndarray, sigma: float) -> np.ndarray:
    """Normalised Gaussian smoothing of an (H, W) map over its finite entries.

    NaN entries (no estimate) take their neighbours' average; +inf entries
    (candidate impossible there) stay +inf; a pixel without any finite
    neighbour stays +inf.
    """
    fin = np.isfinite(a)
    if sigma <= 0:
        return np.where(fin, a, np.inf)
    z = np.where(fin, a, 0.0)
    f = fin.astype(np.float64)
    num = ndimage.gaussian_filter(z, sigma, mode="constant", truncate=3.0)
    den = ndimage.gaussian_filter(f, sigma, mode="constant", truncate=3.0)
    out = np.full(a.shape, np.inf)
    np.divide(num, den, out=out, where=den > 1e-12)
    return np.where(np.isposinf(a), np.inf, out)


def _gauss_kernel(sigma: float, truncate: float = 3.0) -> np.ndarray:
    """The 1-D kernel ``scipy.ndimage.gaussian_filter`` uses (same arithmetic, so bit-identical)."""
    radius = int(truncate * float(sigma) + 0.5)
    x = np.arange(-radius, radius + 1)
    phi = np.exp(-0.5 / (float(sigma) * float(sigma)) * x ** 2)
    return phi / phi.sum()


class MaskedSmoothing:
    """:func:`smooth_masked` of (H, W) float64 maps of one film at one ``sigma``, on the threaded filter engine.

    Bit-identical to it (:mod:`mcrecon.filters.engine` reproduces
    ``scipy.ndimage``'s arithmetic term for term).  A map finite everywhere is
    filtered as it is (zeroing its non-finite entries would copy it), and
    the weight sum of such maps, the same for all of them, is filtered once
    for every call on the object.  Each result is written over its filtered
    values, or into ``out`` (arrays of the maps' shape, the maps themselves
    allowed): no full-image temporary but the filtered maps (fresh memory
    costs more than the arithmetic here).
    """

    def __init__(self, sigma: float):
        self.sigma = float(sigma)
        self._full_den = None

    def __call__(self, maps: list, out: list | None = None) -> list:
        if self.sigma <= 0:
            res = [smooth_masked(a, self.sigma) for a in maps]
            if out is None:
                return res
            for o, r in zip(out, res):
                o[...] = r
            return out
        k = _gauss_kernel(self.sigma)
        maps = [np.ascontiguousarray(a, dtype=np.float64) for a in maps]
        jobs, full = [], []
        for a in maps:
            full.append(bool(_all_finite(a.ravel())))
            if full[-1]:
                jobs.append((a, k, None, 0))
            else:
                z, f = np.empty(a.shape), np.empty(a.shape)
                _split_finite(a.ravel(), z.ravel(), f.ravel())
                jobs += [(z, k, None, 0), (f, k, None, 0)]
        shape = maps[0].shape if maps else None
        new_den = any(full) and (self._full_den is None or self._full_den.shape != shape)
        if new_den:
            jobs.append((np.ones(shape), k, None, 0))
        res = correlate_jobs(jobs)
        if new_den:
            self._full_den = res.pop()
        res = iter(res)
        result = []
        for p, (a, f) in enumerate(zip(maps, full)):
            num = next(res)
            den = self._full_den if f else next(res)
            dst = num if out is None else out[p]
            parallel_rows(_normalise_rows, (num, den, a, dst), a.shape[0])
            result.append(dst)
        return result


@numba.njit(cache=True, nogil=True)
def _all_finite(a):
    for x in a:
        if not np.isfinite(x):
            return False
    return True


@numba.njit(cache=True, nogil=True)
def _split_finite(a, z, f):
    # z = where(isfinite(a), a, 0), f = isfinite(a) as 0/1
    for i in range(a.size):
        fin = np.isfinite(a[i])
        z[i] = a[i] if fin else 0.0
        f[i] = 1.0 if fin else 0.0


@numba.njit(cache=True, nogil=True)
def _normalise_rows(num, den, a, dst, i0, i1):
    # rows [i0, i1): dst = num / den where den > 1e-12, else +inf; +inf where a is (dst may be num or a)
    for i in range(i0, i1):
        for j in range(num.shape[1]):
            d = den[i, j]
            if a[i, j] == np.inf or not d > 1e-12:
                dst[i, j] = np.inf
            else:
                dst[i, j] = num[i, j] / d


def effective_counts(masks: list, sigma: float) -> list:
    """Per pixel, how many independent pixels :func:`smooth_masked` of a map defined on each mask averages.

    The smoothed value at p is ``sum_j w_j m_j x_j / sum_j w_j m_j`` (w the
    Gaussian of ``sigma``, m the mask); for independent x_j of equal
    variance s^2 its variance is ``s^2 / n_p`` with ``n_p = (sum_j w_j
    m_j)^2 / sum_j w_j^2 m_j``: ``4 pi sigma^2`` inside a full mask (the
    continuous limit), about half that along the image's edges and a
    quarter in its corners, where the normalised kernel sees half or a
    quarter of its pixels.  0 where the mask is empty within reach.
    """
    k = _gauss_kernel(sigma)
    jobs = []
    for m in masks:
        f = np.asarray(m, dtype=np.float64)
        jobs += [(f, k, None, 0), (f, k * k, None, 0)]
    res = correlate_jobs(jobs)
    for i in range(len(masks)):
        _effective_rows(res[2 * i].ravel(), res[2 * i + 1].ravel())
    return res[::2]


@numba.njit(cache=True, nogil=True)
def _effective_rows(s1, s2):
    # s1 = s1^2 / s2 where s2 > 1e-300, else 0 (in place)
    for p in range(s1.size):
        s1[p] = s1[p] * s1[p] / s2[p] if s2[p] > 1e-300 else 0.0

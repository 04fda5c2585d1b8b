"""Gaussian smoothing of maps defined on a mask (undefined pixels neither read nor written).
"""

from __future__ import annotations


import numpy as np
from scipy import ndimage

from .engine import correlate_jobs


def _smooth_masked(a: np.ndarray, sigma: float) -> np.ndarray:
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


def _smooth_masked_many(maps: list, sigma: float) -> list:
    """:func:`_smooth_masked` of several maps at once, on the threaded filter engine.

    Bit-identical to it (:mod:`mcrecon.filters.engine` reproduces
    ``scipy.ndimage``'s arithmetic term for term; the weight sums of maps
    finite everywhere are filtered once).
    """
    if sigma <= 0:
        return [_smooth_masked(a, sigma) for a in maps]
    k = _gauss_kernel(sigma)
    jobs, full = [], []
    for a in maps:
        fin = np.isfinite(a)
        jobs.append((np.where(fin, a, 0.0), k, None, 0))
        full.append(bool(fin.all()))
        if not full[-1]:
            jobs.append((fin.astype(np.float64), k, None, 0))
    if any(full):
        jobs.append((np.ones(maps[0].shape), k, None, 0))
    res = correlate_jobs(jobs)
    full_den = res[-1] if any(full) else None
    res = iter(res)
    out = []
    for a, f in zip(maps, full):
        num = next(res)
        den = full_den if f else next(res)
        o = np.full(a.shape, np.inf)
        np.divide(num, den, out=o, where=den > 1e-12)
        out.append(np.where(np.isposinf(a), np.inf, o))
    return out


def effective_counts(masks: list, sigma: float) -> list:
    """Per pixel, how many independent pixels :func:`_smooth_masked` of a map defined on each mask averages.

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
    out = []
    for i in range(len(masks)):
        s1, s2 = res[2 * i], res[2 * i + 1]
        n = np.zeros(s1.shape)
        np.divide(s1 * s1, s2, out=n, where=s2 > 1e-300)
        out.append(n)
    return out

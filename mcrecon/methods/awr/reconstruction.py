"""Reconstruction (Overbeck et al. 2009, §4.2): the variance image and soft thresholding.

The pixel means are analysed with a biorthogonal wavelet (CDF 9/7 by
default); every wavelet coefficient is shrunk towards zero by its
estimated standard deviation ``Delta`` (Eq. 10, 11), then the image is
synthesised.  ``Delta`` comes from a per-pixel variance image
``sigma^2(B) = sigma^2(F) / N`` (Eq. 5, 6: :func:`functional_variance`,
:func:`pixel_variance`) propagated through the transform with squared
basis functions (Eq. 9, 10: :func:`~mcrecon.methods.awr.wavelets.coefficient_variances`).
"""

from __future__ import annotations

import math
from typing import Sequence

import numba
import numpy as np

from ...errors import InputError
from ...core.stats import PixelStats
from ...core.fill import fill_from_neighbours
from .wavelets import (RECONSTRUCTION_RENORM, _check_mode, analyze, coefficient_variances, default_levels,
    get_wavelet, synthesize)

__all__ = ['VARIANCE_ESTIMATORS', 'functional_variance', 'pixel_variance', 'soft_threshold', 'awr_reconstruct',
           'log_domain_reconstruct', 'DOMAINS']

#: Domains the wavelet shrinkage can work in: the pixel values (paper) or
#: their logarithm (robust default, see :func:`log_domain_reconstruct`).
DOMAINS = ("linear", "log")

#: sigma^2(F) estimators: (Imax-Imin)^2 (paper, reconstruction), Mitchell's
#: squared contrast (paper Eq. 5, sampling), unbiased sample variance.
VARIANCE_ESTIMATORS = ("range", "contrast", "sample")


# --------------------------------------------------------------------------
# Variance image (Eq. 5, 6)
# --------------------------------------------------------------------------

def functional_variance(stats: PixelStats, estimator: str = "range") -> np.ndarray:
    """Per-pixel, per-channel estimate of the sample variance sigma^2(F).

    Parameters
    ----------
    stats : PixelStats
    estimator : {'range', 'contrast', 'sample'}
        ``range``: ``(Imax - Imin)^2`` (paper §4.2, reconstruction);
        ``contrast``: Mitchell's squared contrast
        ``(Imax - Imin)^2 / (Imax + Imin)^2`` (Eq. 5, sampling), with
        ``|Imax| + |Imin|`` in the denominator so that signed inputs stay in
        [0, 1] and 0 where both are 0 (an all-black pixel has no contrast);
        ``sample``: the unbiased sample variance ``m2 / (n - 1)``.

    Returns
    -------
    ndarray (H, W, C)
        Finite and >= 0.  Policy for pixels with ``n <= 1`` (no spread
        measurable; the shared :func:`mcrecon.core.fill.fill_from_neighbours`):
        they take the average of ``sigma^2(F)`` over the pixels with
        ``n >= 2`` in their 3x3 neighbourhood inside the image, else the
        channel's average over all pixels with ``n >= 2``, else 0 (then the
        reconstruction does not smooth).

    Raises
    ------
    InputError
        ``range`` or ``contrast`` on statistics without the per-pixel sample
        range (built from moments: ``stats.has_range`` is False).

    References
    ----------
    .. [1] Overbeck et al. 2009, Eq. 5 and §4.2; Mitchell 1987.
    """
    if estimator not in VARIANCE_ESTIMATORS:
        raise InputError("awr", "variance", f"unknown estimator {estimator!r}; valid: {', '.join(VARIANCE_ESTIMATORS)}")
    if estimator != "sample" and not stats.has_range:
        raise InputError("awr", "variance", f"the {estimator!r} estimator needs each pixel's sample minimum and "
                         "maximum, which statistics built from moments (mean, variance, count) do not carry; "
                         "use variance='sample' (--variance sample)")
    n = stats.count
    ok = n >= 2
    okc = np.broadcast_to(ok[..., None], stats.mean.shape)
    out = np.zeros(stats.mean.shape)
    if estimator == "sample":
        np.divide(np.maximum(stats.m2, 0.0), np.maximum(n - 1, 1)[..., None], out=out, where=okc)
    else:
        _range_kernel(n, stats.min, stats.max, estimator == "contrast", out)
    return fill_from_neighbours(out, ok, fallback=0.0)


@numba.njit(cache=True, nogil=True)
def _range_kernel(count, vmin, vmax, contrast, out):
    """(Imax - Imin)^2, or divided by (|Imax| + |Imin|)^2 (Eq. 5), where n >= 2 (one pass)."""
    h, w, c = out.shape
    for j in range(h):
        for i in range(w):
            if count[j, i] < 2:
                continue
            for k in range(c):
                hi = vmax[j, i, k]
                lo = vmin[j, i, k]
                d2 = (hi - lo) * (hi - lo)
                if contrast:
                    den = abs(hi) + abs(lo)
                    out[j, i, k] = d2 / (den * den) if den > 0 else 0.0
                else:
                    out[j, i, k] = d2



def pixel_variance(stats: PixelStats, estimator: str = "range") -> np.ndarray:
    """Variance of the pixel means, ``sigma^2(B) = sigma^2(F) / N`` (Eq. 6).

    Empty pixels count as ``N = 1`` (their value is filled from a
    neighbour, which is one sample's worth of information at best).

    References
    ----------
    .. [1] Overbeck et al. 2009, Eq. 6.
    """
    f = functional_variance(stats, estimator)
    return f / np.maximum(stats.count, 1)[..., None]


# --------------------------------------------------------------------------
# Reconstruction (§4.2)
# --------------------------------------------------------------------------

def soft_threshold(w: np.ndarray, delta: np.ndarray, cs: float = 1.0) -> np.ndarray:
    """``sign(W) * max(0, |W| - cs * Delta)`` (Eq. 11), skipping ``Delta = 0``.

    References
    ----------
    .. [1] Overbeck et al. 2009, Eq. 11.
    """
    w = np.asarray(w, dtype=np.float64)
    t = cs * np.asarray(delta, dtype=np.float64)
    if not np.any(t > 0):
        return w.copy()
    # w - clip(w, -t, t) equals sign(w) max(0, |w| - t) and is w where t = 0.
    return w - np.clip(w, -t, t)


def awr_reconstruct(mean: np.ndarray, var: np.ndarray, *, wavelet: str = "cdf97", cs: float = 1.0,
                    levels: int | None = None, mode: str = "symmetric", propagation: str = "exact",
                    renorm: float | None = RECONSTRUCTION_RENORM, axes: Sequence[int] = (0, 1)) -> np.ndarray:
    """Adaptive wavelet reconstruction of an image from its pixel means.

    Parameters
    ----------
    mean : ndarray (H, W, C) (or any array; ``axes`` are transformed)
        Pixel means B (no empty pixels: fill them first).
    var : ndarray, same shape
        Variances of the pixel means sigma^2(B) (Eq. 6).
    wavelet : str
        :data:`WAVELETS` key.
    cs : float
        Smoothing constant c_s >= 0 (Eq. 11); 0 reproduces ``mean``.
    levels : int or None
        Decomposition depth (None: :func:`default_levels`).
    mode, propagation, renorm
        Boundary extension, variance propagation, squared-filter sum.

    axes : sequence of int
        The axes transformed (the pixel axes); any others (channels) are
        reconstructed independently.

    Returns
    -------
    ndarray, shape of ``mean``, float64

    Raises
    ------
    InputError
        Checked before any work, naming the argument: ``var`` not of the
        shape of ``mean``; NaN or Inf in ``mean`` or ``var``, or a negative
        variance, with the number of such pixels (one NaN would otherwise
        spread over the support of every basis function that covers it);
        ``cs`` not finite and >= 0; an unknown wavelet or boundary mode.

    References
    ----------
    .. [1] Overbeck et al. 2009, §4.2, Eq. 10 and 11.
    """
    mean = np.asarray(mean, dtype=np.float64)
    var = np.asarray(var, dtype=np.float64)
    _check_images(mean, var, axes)
    if not (math.isfinite(cs) and cs >= 0):
        raise InputError("awr_reconstruct", "cs", f"{cs!r}; expected a finite number >= 0")
    _check_mode(mode)
    get_wavelet(wavelet)
    if levels is None:
        levels = default_levels([mean.shape[a] for a in axes])
    if levels <= 0 or cs == 0:
        return mean.copy()
    out = mean.copy()
    kw = dict(wavelet=wavelet, cs=cs, levels=levels, mode=mode, propagation=propagation, renorm=renorm)
    if mean.ndim == 3 and tuple(axes) == (0, 1):
        # Channels with zero variance everywhere pass through without any
        # work; the others are transformed channel-first (contiguous rows
        # make PyWavelets and the sparse products ~2x faster).
        active = np.flatnonzero(np.any(var > 0, axis=(0, 1)))
        if active.size:
            mc = np.ascontiguousarray(np.moveaxis(mean[..., active], 2, 0))
            vc = np.ascontiguousarray(np.moveaxis(var[..., active], 2, 0))
            out[..., active] = np.moveaxis(_awr_core(mc, vc, axes=(1, 2), **kw), 0, 2)
        return out
    if not np.any(var > 0):
        return out
    return _awr_core(mean, var, axes=tuple(axes), **kw)


def _check_images(mean: np.ndarray, var: np.ndarray, axes: Sequence[int]) -> None:
    """The input checks of :func:`awr_reconstruct`: shapes, then finiteness, then signs.

    A pixel is one position on the transformed ``axes``; it is bad when
    any of its channels is.
    """
    where = "awr_reconstruct"
    if mean.shape != var.shape:
        raise InputError(where, "var", f"shape {var.shape}, expected the mean's shape {mean.shape}")
    nd = mean.ndim
    pixel_axes = {a % nd for a in axes if -nd <= a < nd}
    other = tuple(a for a in range(nd) if a not in pixel_axes)

    def n_pixels(bad: np.ndarray) -> str:
        per_pixel = bad.any(axis=other) if other else bad
        return f"{int(np.count_nonzero(per_pixel))} of {per_pixel.size} pixel(s)"

    for name, arr in (("mean", mean), ("var", var)):
        bad = ~np.isfinite(arr)
        if bad.any():
            raise InputError(where, name, f"{n_pixels(bad)} hold NaN or Inf; the wavelet transform would spread "
                             "each over every coefficient whose basis function covers it: fill or drop them first")
    negative = var < 0
    if negative.any():
        raise InputError(where, "var", f"{n_pixels(negative)} hold a negative variance (smallest "
                         f"{float(var.min()):g}); variances of the pixel means must be >= 0")


def _awr_core(mean, var, *, wavelet, cs, levels, mode, propagation, renorm, axes):
    approx, details, shapes, _ = analyze(mean, wavelet, levels, mode=mode, axes=axes)
    dvar = coefficient_variances(var, wavelet, levels, mode=mode, axes=axes, propagation=propagation,
                                 renorm=renorm, which="details")
    new = []
    for det, dv in zip(details, dvar):
        new.append({key: soft_threshold(c, np.sqrt(dv[key]), cs) for key, c in det.items()})
    return synthesize(approx, new, shapes, wavelet, mode=mode, axes=axes)


def log_domain_reconstruct(mean: np.ndarray, var: np.ndarray, *, offset: float = 0.01, **kw) -> np.ndarray:
    """AWR shrinkage of ``log(mean + delta)``, mapped back with ``exp(.) - delta``.

    ``delta = offset x`` the channel's average pixel mean (scale-free: the
    result scales with the radiance).  The variance follows by the delta
    method, ``var / (mean + delta)^2``.  Channels with a negative mean
    somewhere (signed data) or no positive mean are shrunk in the linear
    domain as in the paper.

    Why: in the linear domain an emitter's rim (500 beside 1e-3) has
    wavelets and variances five orders of magnitude above its dim
    neighbours, and shrinking them spreads the bright side into the dark
    one (docs/methods/awr.md, "Why AWR can lose").  In the log domain a
    wavelet measures a *ratio*, so a threshold derived from relative
    noise smooths each side at its own brightness: the relative error,
    which is what HDR metrics and viewers weigh, is what gets reduced.

    ``kw`` are :func:`awr_reconstruct`'s arguments.  ``mean`` and ``var``
    are (H, W, C).
    """
    mean = np.asarray(mean, dtype=np.float64)
    var = np.asarray(var, dtype=np.float64)
    out = np.empty_like(mean)
    logc = [c for c in range(mean.shape[2]) if mean[..., c].min() >= 0 and mean[..., c].max() > 0]
    linc = [c for c in range(mean.shape[2]) if c not in logc]
    if linc:
        out[..., linc] = awr_reconstruct(mean[..., linc], var[..., linc], **kw)
    if logc:
        m = mean[..., logc]
        delta = float(offset) * m.mean(axis=(0, 1))
        y = np.log(m + delta)
        vy = var[..., logc] / (m + delta) ** 2
        out[..., logc] = np.exp(awr_reconstruct(y, vy, **kw)) - delta
    return out

"""Regional risk guard of ``gem``'s final reconstruction: no neighbourhood filtered worse than its pixel means.

GEM decides per pixel from two statistics: the difference of two scales
and their estimated variances (Eq. 1), then lets the neighbours vote
(Sec. 4.4).  On thin geometry both steps fail together.  A one-pixel wire
is a minority in its neighbourhood, so the vote overturns its "stop"; and
once a pixel has left the pixel filter the next pairs see almost no
difference (the finer scale has already averaged the wire away), so the
quadratic bias model of Sec. 4.2 reads "no bias" and the pixel runs to the
coarsest scale.  A pixel between thin bright wires and a pixel whose 32
samples all missed a rare light path carry the same per-pixel statistics
(a small mean, a small variance, a much larger coarse value): no per-pixel
rule tells them apart, and the vote is right for the second.  What tells
them apart is the neighbourhood's error, which the samples estimate
without bias.

For the selected scale s of a pixel, ``(v_s - v_0)^2 - Var[v_0] (1 - 2 w_s)``
estimates ``Bias[v_s]^2 + Var[v_s]`` without bias (``v_0`` the pixel mean,
``w_s`` the pixel's own weight in its filter: ``Cov[v_s, v_0] = w_s
Var[v_0]``), and ``Var[v_0]`` estimates the pixel mean's error.  One pixel's
estimate is too noisy to decide, but their Gaussian-weighted sums over a
neighbourhood of ``radius`` pixels are not: :func:`risk_guard` compares,
per pixel, the neighbourhood's summed estimate for GEM's selection clamped
to at most scale m, for every m from the pixel filter (m = 0: the pixel
means) to the coarsest (GEM's selection itself), and keeps the clamp of
least estimated error where it saves at least 1 % of the pixel means'
(:data:`RISK_TOLERANCE`).  Channels are weighed as the selection weighs them
(``1 / (value^2 + eps)``, the relative MSE; or a plain sum).
"""

from __future__ import annotations

import numba
import numpy as np

from ...errors import InputError
from ...filters.engine import correlate_jobs
from ...filters.gaussian import TRUNCATE, gaussian_kernel, pixel_kernel
from .kernels import FilterBank

__all__ = ["RISK_RADIUS", "RISK_TOLERANCE", "scale_risks", "risk_guard"]

#: Default radius (Gaussian sigma, pixels) of the neighbourhoods whose
#: estimated errors :func:`risk_guard` compares (``GEMMethod``'s ``risk_guard``).
RISK_RADIUS = 8.0
#: Least saving (a share of the pixel means' estimated error in the
#: neighbourhood) for which :func:`risk_guard` clamps a pixel.
RISK_TOLERANCE = 0.01


def _centre_weights(bank: FilterBank, subpixels: int, truncate: float) -> list:
    """Per scale, each pixel's own normalised weight in its filter (1 for the pixel filter)."""
    out = [None]
    for k in range(1, bank.n_scales):
        kern = pixel_kernel(float(bank.sigmas[k - 1]), subpixels, truncate=truncate)
        c0 = float(kern[(kern.size - 1) // 2]) ** 2
        w = np.asarray(bank.weight[k], dtype=np.float64)
        out.append(np.divide(c0, w, out=np.zeros_like(w), where=w > 0))
    return out


@numba.njit(cache=True, nogil=True)
def _risk_kernel(v, v0, var0, wc, is_pixel, cw, out):
    # out = sum_ch cw (v - v0)^2 - var0 (1 - 2 wc) cw: the unbiased estimate of
    # the scale's squared error (Bias^2 + Var); the pixel filter's is var0
    h, w, nc = v.shape
    for i in range(h):
        for j in range(w):
            r = 0.0
            sv = 1.0 if is_pixel else 2.0 * wc[i, j] - 1.0
            for ch in range(nc):
                d = v[i, j, ch] - v0[i, j, ch]
                r += cw[i, j, ch] * (d * d + sv * var0[i, j, ch])
            out[i, j] = r


def scale_risks(bank: FilterBank, channel_weights: np.ndarray, *, subpixels: int = 4,
                truncate: float = TRUNCATE, mean_variance: np.ndarray | None = None) -> np.ndarray:
    """(K, H, W): per scale and pixel, the unbiased estimate of the scale's squared error, summed over channels.

    Scale 0 (the pixel filter, unbiased) gets ``Var[v_0]``; scale k
    ``(v_k - v_0)^2 - Var[v_0] (1 - 2 w_k)`` with ``w_k`` the pixel's own
    normalised weight in the filter.  Each channel is multiplied by
    ``channel_weights`` (H, W, C) before the sum.  Needs per-channel
    variances (``filter_bank(..., per_channel=True)``).  ``mean_variance``
    (H, W, C), optional: ``Var[v_0]`` in place of the bank's (the one the
    selection read).
    """
    v0 = np.ascontiguousarray(bank.values[0], dtype=np.float64)
    var0 = np.ascontiguousarray(bank.var[0] if mean_variance is None else mean_variance, dtype=np.float64)
    cw = np.ascontiguousarray(channel_weights, dtype=np.float64)
    wcs = _centre_weights(bank, subpixels, truncate)
    h, w = v0.shape[:2]
    out = np.empty((bank.n_scales, h, w))
    ones = np.ones((h, w))
    for k in range(bank.n_scales):
        _risk_kernel(np.ascontiguousarray(bank.values[k], dtype=np.float64), v0, var0,
                     ones if k == 0 else wcs[k], k == 0, cw, out[k])
    return out


@numba.njit(cache=True, nogil=True)
def _clamped_risk(risks, selected, m, out):
    h, w = selected.shape
    for i in range(h):
        for j in range(w):
            s = selected[i, j]
            out[i, j] = risks[s if s < m else m, i, j]


def risk_guard(bank: FilterBank, selected: np.ndarray, image: np.ndarray, count: np.ndarray, *,
               radius: float = RISK_RADIUS, tolerance: float = RISK_TOLERANCE, channel_eps: float | None = None,
               subpixels: int = 4, truncate: float = TRUNCATE, threads: int | None = None,
               mean_variance: np.ndarray | None = None) -> np.ndarray:
    """GEM's selection clamped, per pixel, to the maximum scale of least estimated neighbourhood error.

    For m = 0 .. K-1 the candidate ``min(selected, m)`` (m = K-1: the
    selection itself, m = 0: the pixel means); each candidate's
    :func:`scale_risks` summed with a Gaussian of ``radius`` pixels; per
    pixel the candidate with the least sum, if it saves at least
    ``tolerance`` times the pixel means' summed estimate (ties and smaller
    savings: the larger m; without the tolerance the noise of the sums
    picks among near-equal coarse scales).  Pixels without samples keep
    their selection (their mean carries no data) and add nothing to the
    sums.

    Parameters
    ----------
    bank : FilterBank
        With per-channel variances.
    selected : ndarray (H, W) int
        GEM's selected scales.
    image : ndarray (H, W, C)
        The values of the selection: with ``channel_eps`` each channel is
        weighed by ``1 / (image^2 + channel_eps)`` (the relative MSE, the
        same weight for every candidate), else 1.
    count : ndarray (H, W)
        Samples per pixel.
    radius : float
        Gaussian sigma (pixels) of the neighbourhoods; > 0.
    tolerance : float
        Least saving, as a share of the pixel means' estimated error summed
        over the neighbourhood, for which a pixel is clamped.
    mean_variance : ndarray (H, W, C), optional
        The pixel means' variance ``Var[v_0]`` the estimates read; by default
        the bank's, which the selection itself read.  An estimate the
        selection did not see (:func:`~.selection.gem_select`'s
        ``guard_variance``) keeps the guard's check independent of the
        selection's luck.

    Returns
    -------
    ndarray (H, W) int
        The guarded selection (never coarser than ``selected``).
    """
    if not (np.isfinite(radius) and radius > 0):
        raise InputError("risk_guard", "radius", f"{radius!r}; expected a finite number > 0 (pixels)")
    if not (np.isfinite(tolerance) and tolerance >= 0):
        raise InputError("risk_guard", "tolerance", f"{tolerance!r}; expected a finite number >= 0")
    img = np.asarray(image, dtype=np.float64)
    if channel_eps is None:
        cw = np.ones_like(img)
    else:
        with np.errstate(over="ignore"):
            cw = 1.0 / (img * img + float(channel_eps))
    has = np.asarray(count) > 0
    cw = cw * has[..., None]
    if mean_variance is not None:
        mv = np.asarray(mean_variance, dtype=np.float64)
        if mv.shape != img.shape:
            raise InputError("risk_guard", "mean_variance", f"shape {mv.shape}, expected {img.shape}")
        mean_variance = np.where(np.isfinite(mv) & (mv >= 0), mv, np.asarray(bank.var[0], dtype=np.float64))
    risks = scale_risks(bank, cw, subpixels=subpixels, truncate=truncate, mean_variance=mean_variance)
    sel = np.ascontiguousarray(selected, dtype=np.int64)
    nk = bank.n_scales
    g = gaussian_kernel(float(radius), truncate=truncate)
    top = np.empty(sel.shape)
    _clamped_risk(risks, sel, nk - 1, top)
    diff = np.empty((nk - 1,) + sel.shape)
    for m in range(nk - 1):
        _clamped_risk(risks, sel, m, diff[m])
        diff[m] -= top
    jobs = [(diff[m], g, None, 0) for m in range(nk - 1)] + [(risks[0], g, None, 0)]
    res = correlate_jobs(jobs, threads)
    best = np.full(sel.shape, nk - 1, dtype=np.int64)
    low = -tolerance * res[nk - 1]
    for m in range(nk - 2, -1, -1):       # from coarse to fine: a tie keeps the larger m
        score = res[m]
        better = score < low
        best[better] = m
        low[better] = score[better]
    out = np.minimum(sel, best)
    return np.where(has, out, sel)

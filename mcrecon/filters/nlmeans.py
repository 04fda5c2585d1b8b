"""NL-means weights with the variance-normalised patch distance, as NFOR uses them.

Bitterli et al. 2016 (NFOR) weight every pixel pair (p, q = p + o) of a
search window with the NL-means weight of Rousselle, Knaus, Zwicker 2012:
per channel c, the pixel distance

    d_c(s, s + o) = ((u_c(s) - u_c(s+o))^2 - (V_c(s) + min(V_c(s), V_c(s+o))))
                    / (eps + k^2 (V_c(s) + V_c(s+o))),     clamped at 1e4,

averaged over the (2f+1)^2 patch pixels s around p (only pairs with s and
s + o inside the image), gives the patch distance D_c(p, o).  The weight
of a channel is ``exp(-max(0, D_c))``; a weight shared by all channels (the
regression's) is the smallest of the channels' weights, i.e. uses the
largest channel distance (the reference implementation's choice, Tungsten's
``src/denoiser/NlMeans.hpp``; Rousselle 2012 average the channels instead).
``V`` is the variance of the guide's pixel values: the variance of the full
buffer's mean times ``variance_scale`` (2 for a half buffer, whose mean has
twice the variance of the mean of all samples).  The centre weight is at
least 1e-4, so a pixel always keeps some of itself.

:func:`offset_distances` is the one compiled kernel of the distance (also used
by the regression), :func:`nlmeans_filter` the per-channel NL-means filter
of an image guided by another (feature prefiltering, MSE and selection-map
filtering).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .engine import numba_threads

__all__ = ["NLM_EPS", "DISTANCE_CLAMP", "MIN_CENTER_WEIGHT", "nlmeans_filter", "as_planes"]

#: eps of the distance's denominator (0 / 0 on noise-free pixels); the reference implementation's value.
NLM_EPS = 1e-7
#: Pixel distances are clamped here (a huge outlier then counts as "very different", not as infinity).
DISTANCE_CLAMP = 1e4
#: Smallest centre weight: a pixel whose own patch distance is large still keeps part of itself.
MIN_CENTER_WEIGHT = 1e-4
#: Rows per band of the parallel kernels; results do not depend on it.
BAND = 16


@numba.njit(cache=True, nogil=True, error_model="numpy")
def offset_distances(guide, var, dy, dx, i0, i1, f, k2, eps, clamp, sat, out):
    """Patch distances D_c(p, o) of offset o = (dy, dx) for the pixels p of rows [i0, i1).

    guide, var : (C, H, W) float32; sat : scratch (C, i1 - i0 + 2f + 1, W + 1) float64, the summed-area
    table of the pixel distances (0 where s or s + o is outside the image), so that a patch sum costs
    four look-ups whatever f; out : (C, i1 - i0, W) float32, the patch-mean distance where q = p + o
    lies in the image (elsewhere left unspecified: the callers skip those pairs).
    """
    c, h, w = guide.shape
    rows = i1 - i0 + 2 * f
    j0 = max(0, -dx)
    j1 = min(w, w - dx)
    for ch in range(c):
        for j in range(w + 1):
            sat[ch, 0, j] = 0.0
    for t in range(rows):
        i = i0 - f + t
        qi = i + dy
        inside = 0 <= i < h and 0 <= qi < h
        for ch in range(c):
            run = 0.0
            sat[ch, t + 1, 0] = 0.0
            for j in range(w):
                if inside and j0 <= j < j1:
                    vp = var[ch, i, j]
                    vq = var[ch, qi, j + dx]
                    diff = guide[ch, i, j] - guide[ch, qi, j + dx]
                    d = (diff * diff - (vp + min(vp, vq))) / (eps + k2 * (vp + vq))
                    run += min(d, clamp)
                sat[ch, t + 1, j + 1] = sat[ch, t, j + 1] + run
    for r in range(i1 - i0):
        i = i0 + r
        # rows s of the patch with s and s + dy inside the image (table rows: s - (i0 - f))
        rlo = max(i - f, 0, -dy)
        rhi = min(i + f + 1, h, h - dy)
        if rhi <= rlo:
            continue
        tlo = rlo - (i0 - f)
        thi = rhi - (i0 - f)
        for j in range(j0, j1):
            clo = max(j - f, j0)
            chi = min(j + f + 1, j1)
            inv_n = 1.0 / ((rhi - rlo) * (chi - clo))
            for ch in range(c):
                tot = sat[ch, thi, chi] - sat[ch, tlo, chi] - sat[ch, thi, clo] + sat[ch, tlo, clo]
                out[ch, r, j] = tot * inv_n


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _nlm_band(img, guide, var, r, f, k2, eps, clamp, min_centre, i0, i1, num, den):
    c, h, w = img.shape
    sat = np.zeros((guide.shape[0], i1 - i0 + 2 * f + 1, w + 1))
    dist = np.zeros((guide.shape[0], i1 - i0, w), np.float32)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            offset_distances(guide, var, dy, dx, i0, i1, f, k2, eps, clamp, sat, dist)
            j0 = max(0, -dx)
            j1 = min(w, w - dx)
            for rr in range(i1 - i0):
                i = i0 + rr
                qi = i + dy
                if qi < 0 or qi >= h:
                    continue
                for ch in range(c):
                    for j in range(j0, j1):
                        wt = math.exp(-max(float(dist[ch, rr, j]), 0.0))
                        if dy == 0 and dx == 0:
                            wt = max(wt, min_centre)
                        num[ch, i, j] += wt * img[ch, qi, j + dx]
                        den[ch, i, j] += wt


@numba.njit(cache=True, nogil=True, parallel=True)
def _nlm_kernel(img, guide, var, r, f, k2, eps, clamp, min_centre, band, num, den):
    h = img.shape[1]
    n_bands = (h + band - 1) // band
    for b in numba.prange(n_bands):
        i0 = b * band
        _nlm_band(img, guide, var, r, f, k2, eps, clamp, min_centre, i0, min(h, i0 + band), num, den)


def as_planes(a, dtype=np.float64) -> np.ndarray:
    """(H, W, C) or (H, W) -> contiguous (C, H, W) planes (the kernels' inner loops run along rows)."""
    a = np.asarray(a, dtype=np.float64)
    if a.ndim == 2:
        a = a[..., None]
    return np.ascontiguousarray(np.moveaxis(a, 2, 0), dtype=dtype)


def nlmeans_filter(image, guide, variance, *, radius: int, patch: int, k: float, variance_scale: float = 1.0,
                   threads: int | None = None) -> np.ndarray:
    """NL-means of ``image`` with per-channel weights from ``guide``.

    Parameters
    ----------
    image, guide, variance : ndarray (H, W, C) or (H, W)
        The image filtered, the image the weights compare (channel c of
        the image takes channel c's weights) and the variance of the
        guide's pixel values (before ``variance_scale``).
    radius, patch : int
        Search window (2 radius + 1)^2, patch (2 patch + 1)^2.
    k : float
        Bandwidth: larger smooths more.
    variance_scale : float
        Factor on ``variance`` (2: the guide is a half buffer and
        ``variance`` that of the full buffer's mean).
    threads : int, optional
        Worker threads (:func:`mcrecon.filters.engine.n_threads`); the
        result does not depend on it.

    Returns
    -------
    ndarray, the shape of ``image``, float64
    """
    img = as_planes(image)
    g = as_planes(guide, np.float32)
    v = np.ascontiguousarray(as_planes(variance) * float(variance_scale), dtype=np.float32)
    if g.shape != img.shape or v.shape != img.shape:
        raise ValueError(f"nlmeans_filter: image {img.shape}, guide {g.shape}, variance {v.shape} (C, H, W) differ")
    num = np.zeros(img.shape)
    den = np.zeros(img.shape)
    with numba_threads(threads):
        _nlm_kernel(img, g, v, int(radius), int(patch), np.float32(float(k) ** 2), np.float32(NLM_EPS),
                    np.float32(DISTANCE_CLAMP), MIN_CENTER_WEIGHT, BAND, num, den)
    out = np.moveaxis(num / den, 0, 2)
    return out[..., 0] if np.ndim(image) == 2 else out

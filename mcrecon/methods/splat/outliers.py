"""Splatting's outlier split: the samples inconsistent with their pixel's neighbourhood.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True, inline="always")
def _excess_width(g, t, f, n, c, alpha, min_w, max_w):
    """Eq. 8's kernel diameter for the excess ``g - t`` of a sample (``g > t``) against its window's
    pooled mean ``f`` and sample count ``n``, capped at ``max_w``: (diameter, capped)."""
    ex = g - t
    if f > 0.0 and f < np.inf:
        d = c * n ** (-alpha) * (math.sqrt(ex) / math.sqrt(f))
    else:
        d = np.inf
    capped = d > max_w
    if d >= max_w:
        d = max_w
    return d, capped


@numba.njit(cache=True, nogil=True)
def _split_outliers(pos, val, norm_code, weights, tau, fref, nmap, c, alpha, min_w, max_w, frac, radius, k0, k1):
    """Robust variant: the part of each sample ``k0 <= k < k1`` above its threshold, and that part's kernel radius.

    The threshold of a sample is its pixel's ``tau``
    (:func:`_outlier_thresholds`).  A sample with ``G <= tau``
    stays in its pixel (``frac = 0``).  Above, ``frac = 1 - tau / G`` of
    its value (every channel alike: the colour is kept, nothing is
    clipped) is the excess, splatted with Eq. 8's width for ``G - tau``
    against the pooled mean ``fref`` of its own window; ``radius = -1``
    where nothing is spread (also when that width is at most ``min_w``).
    Returns (outliers, capped).

    (Measured and rejected: leaving the sample itself out of the window
    statistics.  It lowers the threshold of lone spikes, which helped a
    smooth firefly scene little and made the thin caustic ring at 64^2,
    8-16 spp lose to box by up to 9 %.)
    """
    n_out = 0
    n_capped = 0
    for k in range(k0, k1):
        frac[k] = 0.0
        radius[k] = -1.0
        g, py, px, t, d, cap = _judge(pos, val, k, norm_code, weights, tau, fref, nmap, c, alpha, min_w, max_w)
        n_capped += cap
        if g > 0.0 and g > t and d > min_w:  # else the excess would stay in the pixel anyway
            n_out += 1
            frac[k] = (g - t) / g
            radius[k] = 0.5 * d
    return n_out, n_capped


@numba.njit(cache=True, nogil=True, inline="always")
def _judge(pos, val, k, norm_code, weights, tau, fref, nmap, c, alpha, min_w, max_w):
    """Sample ``k``'s G, its pixel (py, px), that pixel's threshold t and, where G > t, the width d of
    Eq. 8 for the excess G - t and whether it was capped: (g, py, px, t, d, capped).  d = 0 and
    capped = 0 where G <= t; everything but g is 0 where G <= 0 (or NaN).  The split and the consistent
    samples' radii (consistent.py) judge a sample alike."""
    g = _norm_of(val, k, norm_code, weights)
    if not g > 0.0:
        return g, 0, 0, 0.0, 0.0, 0
    h = nmap.shape[0]
    w = nmap.shape[1]
    px = min(max(int(math.floor(pos[k, 0])), 0), w - 1)
    py = min(max(int(math.floor(pos[k, 1])), 0), h - 1)
    t = tau[py, px]
    if not g > t:
        return g, py, px, t, 0.0, 0
    d, cap = _excess_width(g, t, fref[py, px], nmap[py, px], c, alpha, min_w, max_w)
    return g, py, px, t, d, cap


@numba.njit(cache=True, nogil=True)
def _count_and_moments(pos, val, norm_code, weights, counts, s1, s2, k0, k1, j0, j1):
    """One pass over the samples ``k0 <= k < k1``: add to each pixel of the rows ``j0 <= j < j1`` its sample
    count and the sums of G and G^2 (in sample order)."""
    h = s1.shape[0]
    w = s1.shape[1]
    for k in range(k0, k1):
        py = min(max(int(math.floor(pos[k, 1])), 0), h - 1)
        if not j0 <= py < j1:
            continue
        g = _norm_of(val, k, norm_code, weights)
        px = min(max(int(math.floor(pos[k, 0])), 0), w - 1)
        counts[py, px] += 1
        s1[py, px] += g
        s2[py, px] += g * g


@numba.njit(cache=True, nogil=True)
def _outlier_thresholds(wn, ws1, ws2, r, k_sigma, min_pool, tau, skip_small=False):
    """The outlier threshold tau of every pixel (robust variant).

    The threshold of a sample in pixel p is the largest, over the
    (2r+1)^2 windows that contain p (those centred within r of p), of
    ``mean + k std`` of the G of the window's samples (``wn``, ``ws1``,
    ``ws2``: count, sum of G, sum of G^2 per window); a window with fewer
    than ``min_pool`` samples gives no test (infinite threshold).  The
    maximum over windows keeps a sample beside a bright edge in place: the
    window on the bright side explains it.  It depends only on the pixel:
    computed once per pixel, a round costs one lookup per sample instead of
    (2r+1)^2 window visits with a square root each.  ``skip_small``: the
    maximum over the windows that hold ``min_pool`` samples, infinite only if
    none does (at the film border, where windows are clipped, the test still
    runs once the interior windows are full).
    """
    h, w = wn.shape
    for py in range(h):
        for px in range(w):
            t = 0.0
            counted = False
            for j in range(max(py - r, 0), min(py + r, h - 1) + 1):
                for i in range(max(px - r, 0), min(px + r, w - 1) + 1):
                    nw = wn[j, i]
                    if nw < min_pool:
                        if not skip_small:
                            t = np.inf
                        continue
                    counted = True
                    mean = ws1[j, i] / nw
                    var = ws2[j, i] / nw - mean * mean
                    if var < 0.0:
                        var = 0.0
                    tw = (mean + k_sigma * math.sqrt(var)) * (1.0 + 1e-9)
                    if tw > t:
                        t = tw
            tau[py, px] = t if counted or not skip_small else np.inf


@numba.njit(cache=True, nogil=True)
def _split_and_deposit(pos, val, norm_code, weights, tau, fref, nmap, c, alpha, min_w, max_w, w_round, inv_counts,
                       img, width_sum, width_n, out_idx, out_scale, out_rad):
    """Robust variant, one pass over a round held in memory: split each sample (as :func:`_split_outliers`
    does, with the per-pixel thresholds ``tau``), deposit what stays in its pixel, record the kernel
    diameters; the outliers' index, spread energy and radius go to ``out_*`` for the guided splat.

    The arithmetic of the streamed path (split, ``scale = w_round / n_p``, the
    own-pixel deposit ``scale (1 - frac)``, the widths' per-pixel sums) in the
    same sample order.  Returns (outliers, capped).
    """
    h = nmap.shape[0]
    w = nmap.shape[1]
    nc = img.shape[2]
    n_out = 0
    n_capped = 0
    for k in range(pos.shape[0]):
        px = min(max(int(math.floor(pos[k, 0])), 0), w - 1)
        py = min(max(int(math.floor(pos[k, 1])), 0), h - 1)
        frac = 0.0
        rad = -1.0
        g = _norm_of(val, k, norm_code, weights)
        if g > 0.0:
            t = tau[py, px]
            if g > t:
                d, cap = _excess_width(g, t, fref[py, px], nmap[py, px], c, alpha, min_w, max_w)
                n_capped += cap
                if d > min_w:
                    frac = (g - t) / g
                    rad = 0.5 * d
        scale = w_round * inv_counts[py, px]
        e = scale * (1.0 - frac)
        if e != 0.0:
            for ch in range(nc):
                img[py, px, ch] += val[k, ch] * e
        q = py * w + px
        if rad > 0.0:
            out_idx[n_out] = k
            out_scale[n_out] = scale * frac
            out_rad[n_out] = rad
            n_out += 1
            width_sum[q] += 2.0 * rad
        else:
            width_sum[q] += 2.0 * (0.5 * min_w)
        width_n[q] += 1
    return n_out, n_capped


def _box_sum(a: np.ndarray, r: int) -> np.ndarray:
    """Sum of ``a`` (H, W) over the (2r+1)^2 window around each pixel, the window clipped to the film.

    Shifted adds, not a summed-area table: cumulative sums over an HDR
    image would cancel catastrophically in the dark pixels.
    """
    h, w = a.shape
    out = np.zeros_like(a)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            out[max(0, -dy):h - max(0, dy), max(0, -dx):w - max(0, dx)] += \
                a[max(0, dy):h - max(0, -dy), max(0, dx):w - max(0, -dx)]
    return out


@numba.njit(cache=True, nogil=True, inline="always")
def _norm_of(val, k, norm_code, weights):
    """G of sample k (see ``NORMS``).  Inlined: as a call it made the per-sample passes 5-7x slower."""
    nc = val.shape[1]
    g = 0.0
    if norm_code == 0:  # weighted sum of |v| (luminance or mean)
        for c in range(nc):
            g += weights[c] * abs(np.float64(val[k, c]))
    else:  # max |v|
        for c in range(nc):
            a = abs(np.float64(val[k, c]))
            if a > g:
                g = a
    return g

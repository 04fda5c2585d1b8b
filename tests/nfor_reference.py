"""Reference kernels for nfor's filters: the tests check the fast kernels against them.

These kernels sum pixel distances per offset through a summed-area table,
form the normal equations as dot products over each window's gathered rows
and call ``math.exp`` per weight.  They compute the same formulas as
:mod:`mcrecon.filters.nlmeans` and :mod:`mcrecon.filters.regression`
(docstrings there) in a plainer order, so the fast kernels differ from them
only by rounding: the order of the patch and accumulation sums and a
polynomial ``exp``.  ``tests/test_nfor.py`` checks the two agree
(docs/methods/nfor.md states the tolerance); the package does not use this
module, so it lives with the tests.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from mcrecon.filters.nlmeans import DISTANCE_CLAMP, MIN_CENTER_WEIGHT, NLM_EPS, as_planes

__all__ = ["nlmeans_filter_reference", "collaborative_regression_reference"]

#: Rows per band of the reference kernels (serial: a test-size image needs no threads, and a
#: ``parallel=True`` kernel costs twice the compilation); results do not depend on it.
BAND = 16


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _offset_distances_sat(guide, var, dy, dx, i0, i1, f, k2, eps, clamp, sat, out):
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
            _offset_distances_sat(guide, var, dy, dx, i0, i1, f, k2, eps, clamp, sat, dist)
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


def _nlm_kernel(img, guide, var, r, f, k2, eps, clamp, min_centre, band, num, den):
    """The bands in order, each a call of the compiled :func:`_nlm_band` (a loop here: a compiled loop would
    re-optimise the band's whole body once more, seconds of a first run)."""
    h = img.shape[1]
    n_bands = (h + band - 1) // band
    for b in range(n_bands):
        i0 = b * band
        _nlm_band(img, guide, var, r, f, k2, eps, clamp, min_centre, i0, min(h, i0 + band), num, den)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _solve_spd(a, b, d, nc):
    """Solve a x = b in place (b (d, nc) becomes x) by Cholesky of the SPD a (d, d); a is overwritten.

    A non-positive pivot (a column with no weight left after the ridge: only
    when every weight is 0) drops that column (its coefficients 0)."""
    for j in range(d):
        s = a[j, j]
        for k in range(j):
            s -= a[j, k] * a[j, k]
        if s <= 1e-300:
            for i in range(j, d):
                a[i, j] = 0.0
            a[j, j] = 1.0
            for c in range(nc):
                b[j, c] = 0.0
            continue
        l = math.sqrt(s)
        a[j, j] = l
        for i in range(j + 1, d):
            t = a[i, j]
            for k in range(j):
                t -= a[i, k] * a[j, k]
            a[i, j] = t / l
    for c in range(nc):  # forward: L z = b, then back: L^T x = z
        for i in range(d):
            t = b[i, c]
            for k in range(i):
                t -= a[i, k] * b[k, c]
            b[i, c] = t / a[i, i]
        for i in range(d - 1, -1, -1):
            t = b[i, c]
            for k in range(i + 1, d):
                t -= a[k, i] * b[k, c]
            b[i, c] = t / a[i, i]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _band(y, guide, var, feats, r, f, k2, ridge, eps, clamp, min_centre, i0, i1, acc):
    """Rows [i0, i1) as window centres; predictions accumulated into acc (C + 1, i1 - i0 + 2r, W),
    whose row t is image row i0 - r + t (the last plane: the weights)."""
    nc, h, w = y.shape
    nf = feats.shape[0]
    d = 3 + nf
    n_rows = i1 - i0
    side = 2 * r + 1
    wts = np.zeros((side * side, n_rows, w), np.float32)
    cg = guide.shape[0]
    sat = np.zeros((cg, n_rows + 2 * f + 1, w + 1))
    dist = np.zeros((cg, n_rows, w), np.float32)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            o = (dy + r) * side + (dx + r)
            _offset_distances_sat(guide, var, dy, dx, i0, i1, f, k2, eps, clamp, sat, dist)
            j0 = max(0, -dx)
            j1 = min(w, w - dx)
            for rr in range(n_rows):
                qi = i0 + rr + dy
                if qi < 0 or qi >= h:
                    continue
                for j in range(j0, j1):
                    dm = dist[0, rr, j]
                    for ch in range(1, cg):
                        dm = max(dm, dist[ch, rr, j])
                    wt = math.exp(-max(float(dm), 0.0))
                    if dy == 0 and dx == 0:
                        wt = max(wt, min_centre)
                    wts[o, rr, j] = wt
    a = np.zeros((d, d))
    bm = np.zeros((d, nc))
    # the window as contiguous rows (design transposed, weighted design, colours): the normal equations
    # and the predictions are then dot products of length n over the window, which LLVM vectorises
    # (3x faster than accumulating outer products pixel by pixel, measured at 128^2)
    n_max = side * side
    xt = np.zeros((d, n_max))
    wx = np.zeros((d, n_max))
    yt = np.zeros((nc, n_max))
    wv = np.zeros(n_max)
    qrow = np.zeros(n_max, np.int64)
    qcol = np.zeros(n_max, np.int64)
    inv_r = 1.0 / max(r, 1)
    for rr in range(n_rows):
        i = i0 + rr
        for j in range(w):
            n = 0
            for dy in range(-r, r + 1):
                qi = i + dy
                if qi < 0 or qi >= h:
                    continue
                for dx in range(-r, r + 1):
                    qj = j + dx
                    if qj < 0 or qj >= w:
                        continue
                    wt = float(wts[(dy + r) * side + (dx + r), rr, j])
                    if wt == 0.0:
                        continue
                    wv[n] = wt
                    qrow[n] = qi
                    qcol[n] = qj
                    xt[0, n] = 1.0
                    xt[1, n] = dx * inv_r
                    xt[2, n] = dy * inv_r
                    for m in range(nf):
                        xt[3 + m, n] = feats[m, qi, qj] - feats[m, i, j]
                    for c in range(nc):
                        yt[c, n] = y[c, qi, qj]
                    n += 1
            for p in range(d):
                for t in range(n):
                    wx[p, t] = wv[t] * xt[p, t]
            for p in range(d):
                for q in range(p + 1):
                    acc_pq = 0.0
                    for t in range(n):
                        acc_pq += wx[p, t] * xt[q, t]
                    a[p, q] = acc_pq
                for c in range(nc):
                    acc_pc = 0.0
                    for t in range(n):
                        acc_pc += wx[p, t] * yt[c, t]
                    bm[p, c] = acc_pc
            s0 = a[0, 0]
            for p in range(1, d):
                a[p, p] += ridge * s0
            _solve_spd(a, bm, d, nc)
            for c in range(nc):
                for t in range(n):
                    yt[c, t] = 0.0
                for p in range(d):
                    beta = bm[p, c]
                    for t in range(n):
                        yt[c, t] += beta * xt[p, t]
            for t in range(n):
                row = qrow[t] - (i0 - r)
                col = qcol[t]
                wt = wv[t]
                for c in range(nc):
                    acc[c, row, col] += wt * yt[c, t]
                acc[nc, row, col] += wt


def _regression_kernel(y, guide, var, feats, r, f, k2, ridge, eps, clamp, min_centre, band, accs):
    """The bands in order, each a call of the compiled :func:`_band` (as :func:`_nlm_kernel`)."""
    h = y.shape[1]
    n_bands = (h + band - 1) // band
    for b in range(n_bands):
        i0 = b * band
        _band(y, guide, var, feats, r, f, k2, ridge, eps, clamp, min_centre, i0, min(h, i0 + band), accs[b])


@numba.njit(cache=True, nogil=True)
def _gather(accs, r, band, out):
    """Sum the bands' private accumulators into out (C + 1, H, W) (serial: bands overlap by 2r rows)."""
    h = out.shape[1]
    for b in range(accs.shape[0]):
        top = b * band - r
        for t in range(accs.shape[2]):
            i = top + t
            if 0 <= i < h:
                for c in range(out.shape[0]):
                    for j in range(out.shape[2]):
                        out[c, i, j] += accs[b, c, t, j]


def nlmeans_filter_reference(image, guide, variance, *, radius, patch, k, variance_scale=1.0):
    """:func:`.nlmeans.nlmeans_filter` by the reference kernels (its arguments but ``threads``: the reference
    is serial; the same result to rounding)."""
    img = as_planes(image)
    g = as_planes(guide, np.float32)
    v = np.ascontiguousarray(as_planes(variance) * float(variance_scale), dtype=np.float32)
    num = np.zeros(img.shape)
    den = np.zeros(img.shape)
    _nlm_kernel(img, g, v, int(radius), int(patch), np.float32(float(k) ** 2), np.float32(NLM_EPS),
                np.float32(DISTANCE_CLAMP), MIN_CENTER_WEIGHT, BAND, num, den)
    out = np.moveaxis(num / den, 0, 2)
    return out[..., 0] if np.ndim(image) == 2 else out


def collaborative_regression_reference(image, guide, variance, features, *, radius=9, patch=3, k=1.0,
                                       variance_scale=2.0, ridge=1e-10, return_weights=False):
    """:func:`.regression.collaborative_regression` by the reference kernels (its arguments but ``threads``:
    the reference is serial; the same result to rounding)."""
    from mcrecon.filters.regression import standardise

    y = as_planes(image)
    g = as_planes(guide, np.float32)
    v = np.ascontiguousarray(as_planes(variance) * float(variance_scale), dtype=np.float32)
    feats = np.asarray(features, dtype=np.float64)
    if feats.ndim == 2:
        feats = feats[..., None]
    fp = standardise(np.moveaxis(feats, 2, 0)) if feats.shape[2] else np.zeros((0,) + y.shape[1:])
    fp = np.ascontiguousarray(fp)
    nc, h, w = y.shape
    r = int(radius)
    n_bands = (h + BAND - 1) // BAND
    accs = np.zeros((n_bands, nc + 1, BAND + 2 * r, w))
    _regression_kernel(y, g, v, fp, r, int(patch), np.float32(float(k) ** 2), float(ridge), np.float32(NLM_EPS),
                       np.float32(DISTANCE_CLAMP), MIN_CENTER_WEIGHT, BAND, accs)
    out = np.zeros((nc + 1, h, w))
    _gather(accs, r, BAND, out)
    res = np.moveaxis(out[:nc] / out[nc], 0, 2)
    return (res, out[nc]) if return_weights else res

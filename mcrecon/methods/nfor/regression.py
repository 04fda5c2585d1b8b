"""Collaborative first-order regression (NFOR Sec. 5.2, after Moon et al. 2014).

For every pixel p, a weighted least-squares fit of the colour y over the
(2R+1)^2 window N(p) on the design

    x_q = (1, (q_x - p_x) / R, (q_y - p_y) / R, f(q) - f(p))       (one column per feature channel)

with the NL-means weights w_pq of :mod:`.nlmeans` (from a guide image,
one weight for all channels: the smallest channel weight):

    beta_p = argmin_b  sum_q w_pq |y_q - x_q^T b|^2 + lambda S0_p |b_1..|^2,   S0_p = sum_q w_pq

(the ridge ``lambda`` is on every column but the constant, on features
standardised over the image: it makes flat or collinear features solvable
and moves an exact linear fit by O(lambda), 1e-10 by default).  Each pixel's
fit predicts its whole window (``y_hat_p(q) = x_q^T beta_p``); the estimate
at q is the weighted average of the predictions of every window covering it:

    y_out(q) = sum_p w_pq y_hat_p(q) / sum_p w_pq          (collaborative averaging)

The pixel-offset columns are those of the reference implementation
(Tungsten's ``Regression.cpp``); normal equations in float64, solved by
Cholesky (d <= a few dozen columns).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ...filters.engine import numba_threads
from .nlmeans import BAND, DISTANCE_CLAMP, MIN_CENTER_WEIGHT, NLM_EPS, as_planes, exp_neg, offset_distances

__all__ = ["RIDGE", "collaborative_regression", "standardise"]

#: Default ridge on the non-constant columns, relative to the window's total weight.
RIDGE = 1e-10
#: Pixels of a row whose normal equations are accumulated together (their sums stay in the L1 cache);
#: results do not depend on it.
CHUNK = 128


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
def _band(ypad, guide, var, fpad, r, f, k2, ridge, eps, clamp, min_centre, i0, i1, chunk, acc):
    """Rows [i0, i1) as window centres; predictions accumulated into acc (C + 1, i1 - i0 + 2r, W + 2r),
    whose (t, u) is image pixel (i0 - r + t, u - r) (the last plane: the weights).

    ypad (C, H + 2r, W + 2r), fpad (D, H + 2r, W + 2r): colour and features padded by r zeros, so that
    every window is whole (outside the image the weight is 0 and adds exactly nothing).  Offset-major:
    for a run of ``chunk`` pixels of a row, each offset adds its term to the pixels' packed normal
    equations at once (loops along the row, vectorised, no reduction); the sums per pixel are in the
    reference's order (the window's offsets row by row), so the normal equations equal the reference's
    but for the weights' rounding.  Then one (d x d) Cholesky per pixel, and a second pass over the
    offsets scatters each fit's predictions of its window.
    """
    nc = ypad.shape[0]
    h, w = guide.shape[1], guide.shape[2]
    nf = fpad.shape[0]
    d = 3 + nf
    n_rows = i1 - i0
    side = 2 * r + 1
    cg = guide.shape[0]
    # 1. the weights of every offset for the band's pixels (0 where q is outside the image)
    wts = np.zeros((side * side, n_rows, w), np.float32)
    pd = np.zeros((cg, n_rows + 2 * f, w + 2 * f), np.float32)
    vs = np.zeros(w + 2 * f)
    hs = np.zeros(w + 2 * f)
    ic = np.zeros(w + 2 * f)
    dist = np.zeros((cg, n_rows, w), np.float32)
    dmax = np.zeros(w, np.float32)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            o = (dy + r) * side + (dx + r)
            offset_distances(guide, var, dy, dx, i0, i1, f, k2, eps, clamp, pd, vs, hs, ic, dist)
            j0 = max(0, -dx)
            j1 = min(w, w - dx)
            floor = min_centre if dy == 0 and dx == 0 else 0.0
            for rr in range(n_rows):
                qi = i0 + rr + dy
                if qi < 0 or qi >= h:
                    continue
                dst = wts[o, rr, j0:j1]
                dmax[:j1 - j0] = dist[0, rr, j0:j1]
                for ch in range(1, cg):  # the largest channel distance (slices: vectorised, see offset_distances)
                    dc = dist[ch, rr, j0:j1]
                    for t in range(j1 - j0):
                        dmax[t] = max(dmax[t], dc[t])
                for t in range(j1 - j0):
                    dst[t] = max(exp_neg(max(float(dmax[t]), 0.0)), floor)
    # 2. normal equations, packed lower triangle (pair k: columns pp[k] >= qq[k]) and right-hand sides
    npair = d * (d + 1) // 2
    pp = np.zeros(npair, np.int64)
    qq = np.zeros(npair, np.int64)
    k = 0
    for p in range(d):
        for q in range(p + 1):
            pp[k] = p
            qq[k] = q
            k += 1
    am = np.zeros((npair, chunk))
    bmat = np.zeros((d * nc, chunk))
    x = np.zeros((d, chunk))
    wx = np.zeros((d, chunk))
    beta = np.zeros((d * nc, chunk))
    pred = np.zeros(chunk)
    a = np.zeros((d, d))
    bm = np.zeros((d, nc))
    inv_r = 1.0 / max(r, 1)
    for rr in range(n_rows):
        i = i0 + rr
        for c0 in range(0, w, chunk):
            n = min(chunk, w - c0)
            am[:, :] = 0.0
            bmat[:, :] = 0.0
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    o = (dy + r) * side + (dx + r)
                    wrow = wts[o, rr, c0:c0 + n]
                    _design(fpad, i, dy, dx, r, c0, n, inv_r, x)
                    for p in range(d):
                        xp, wxp = x[p], wx[p]
                        for t in range(n):
                            wxp[t] = float(wrow[t]) * xp[t]
                    for kk in range(npair):
                        wxp, xq, ak = wx[pp[kk]], x[qq[kk]], am[kk]
                        for t in range(n):
                            ak[t] += wxp[t] * xq[t]
                    for p in range(d):
                        wxp = wx[p]
                        for c in range(nc):
                            yq, bk = ypad[c, i + r + dy, c0 + r + dx:c0 + r + dx + n], bmat[p * nc + c]
                            for t in range(n):
                                bk[t] += wxp[t] * yq[t]
            # 3. one Cholesky per pixel (the reference's ridge and solver)
            for t in range(n):
                for kk in range(npair):
                    a[pp[kk], qq[kk]] = am[kk, t]
                for p in range(d):
                    for c in range(nc):
                        bm[p, c] = bmat[p * nc + c, t]
                s0 = a[0, 0]
                for p in range(1, d):
                    a[p, p] += ridge * s0
                _solve_spd(a, bm, d, nc)
                for p in range(d):
                    for c in range(nc):
                        beta[p * nc + c, t] = bm[p, c]
            # 4. each fit predicts its window: acc(q) += w_pq x_q^T beta_p
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    o = (dy + r) * side + (dx + r)
                    wrow = wts[o, rr, c0:c0 + n]
                    _design(fpad, i, dy, dx, r, c0, n, inv_r, x)
                    row = rr + r + dy
                    for c in range(nc):
                        for t in range(n):
                            pred[t] = 0.0
                        for p in range(d):
                            xp, bp = x[p], beta[p * nc + c]
                            for t in range(n):
                                pred[t] += bp[t] * xp[t]
                        dst = acc[c, row, c0 + r + dx:c0 + r + dx + n]
                        for t in range(n):
                            dst[t] += float(wrow[t]) * pred[t]
                    dst = acc[nc, row, c0 + r + dx:c0 + r + dx + n]
                    for t in range(n):
                        dst[t] += float(wrow[t])


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _design(fpad, i, dy, dx, r, c0, n, inv_r, x):
    """Rows of the design for offset (dy, dx) and the pixels (i, c0 .. c0 + n - 1): x (d, chunk)."""
    ox = dx * inv_r
    oy = dy * inv_r
    x0, x1, x2 = x[0], x[1], x[2]
    for t in range(n):
        x0[t] = 1.0
        x1[t] = ox
        x2[t] = oy
    for m in range(fpad.shape[0]):
        fq = fpad[m, i + r + dy, c0 + r + dx:c0 + r + dx + n]
        fc = fpad[m, i + r, c0 + r:c0 + r + n]
        xm = x[3 + m]
        for t in range(n):
            xm[t] = fq[t] - fc[t]


@numba.njit(cache=True, nogil=True, parallel=True)
def _regression_kernel(ypad, guide, var, fpad, r, f, k2, ridge, eps, clamp, min_centre, band, chunk, accs):
    h = guide.shape[1]
    n_bands = (h + band - 1) // band
    for b in numba.prange(n_bands):
        i0 = b * band
        _band(ypad, guide, var, fpad, r, f, k2, ridge, eps, clamp, min_centre, i0, min(h, i0 + band), chunk,
              accs[b])


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
                        out[c, i, j] += accs[b, c, t, j + r]


def standardise(features) -> np.ndarray:
    """Feature planes (D, H, W) shifted and scaled to mean 0 and standard deviation 1 over the image
    (a constant plane: shifted only), so that one ridge suits every feature."""
    f = np.array(features, dtype=np.float64, copy=True)
    for m in range(f.shape[0]):
        f[m] -= f[m].mean()
        sd = f[m].std()
        if sd > 0:
            f[m] /= sd
    return f


def collaborative_regression(image, guide, variance, features, *, radius: int = 9, patch: int = 3, k: float = 1.0,
                             variance_scale: float = 2.0, ridge: float = RIDGE, threads: int | None = None,
                             return_weights: bool = False):
    """Collaborative first-order regression of ``image`` on ``features``, weighted by NL-means of ``guide``.

    Parameters
    ----------
    image : ndarray (H, W, C)
        The colour regressed (HDR, never clipped).
    guide : ndarray (H, W, Cg)
        The image the NL-means weights compare (NFOR: the *other* half
        buffer's colour, so the weights do not correlate with the noise of
        ``image``).
    variance : ndarray (H, W, Cg)
        Variance of the guide's pixel values before ``variance_scale``.
    features : ndarray (H, W, D)
        Feature channels (standardised here: :func:`standardise`); D may be 0.
    radius, patch, k : int, int, float
        Window (2 radius + 1)^2 (NFOR: 9), NL-means patch (2 patch + 1)^2
        (3) and bandwidth (0.5 and 1.0 as the two candidates).
    variance_scale : float
        Factor on ``variance`` (2: half buffers with the full buffer's variance).
    ridge : float
        Ridge on the non-constant columns, times the window's total weight.
    return_weights : bool
        Also return the per-pixel sum of the weights of the predictions
        averaged (the collaborative denominator).

    Returns
    -------
    ndarray (H, W, C) float64 (and (H, W) weights with ``return_weights``)
    """
    y = as_planes(image)
    g = as_planes(guide, np.float32)
    v = np.ascontiguousarray(as_planes(variance) * float(variance_scale), dtype=np.float32)
    feats = np.asarray(features, dtype=np.float64)
    if feats.ndim == 2:
        feats = feats[..., None]
    fp = standardise(np.moveaxis(feats, 2, 0)) if feats.shape[2] else np.zeros((0,) + y.shape[1:])
    fp = np.ascontiguousarray(fp)
    nc, h, w = y.shape
    if g.shape[1:] != (h, w) or v.shape != g.shape or fp.shape[1:] != (h, w):
        raise ValueError(f"collaborative_regression: shapes differ: image {y.shape}, guide {g.shape}, "
                         f"variance {v.shape}, features {fp.shape} (planes)")
    r = int(radius)
    n_bands = (h + BAND - 1) // BAND
    accs = np.zeros((n_bands, nc + 1, BAND + 2 * r, w + 2 * r))
    pad = ((0, 0), (r, r), (r, r))
    with numba_threads(threads):
        _regression_kernel(np.pad(y, pad), g, v, np.pad(fp, pad), r, int(patch), np.float32(float(k) ** 2),
                           float(ridge), np.float32(NLM_EPS), np.float32(DISTANCE_CLAMP), MIN_CENTER_WEIGHT, BAND,
                           CHUNK, accs)
    out = np.zeros((nc + 1, h, w))
    _gather(accs, r, BAND, out)
    res = np.moveaxis(out[:nc] / out[nc], 0, 2)
    return (res, out[nc]) if return_weights else res

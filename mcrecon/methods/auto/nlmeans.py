"""Non-local means on pixel statistics with the variance-normalised patch distance, cross-filtered.

Rousselle, Knaus, Zwicker 2012 ("Adaptive rendering with non-local means
filtering", ACM TOG 31(6)) compare pixels p and q of a noisy image u with
per-pixel variance of the mean Var by

    d2_i(p, q) = ((u_i(p) - u_i(q))^2 - alpha (Var_i[p] + Var_i[q, p]))
                 / (eps + k^2 (Var_i[p] + Var_i[q])),   Var_i[q, p] = min(Var_i[p], Var_i[q]),

averaged over the channels i and over the (2f+1)^2 pixel pairs of the
patches around p and q; the weight is ``exp(-max(0, d2))`` and the
filtered value the weighted mean over a (2r+1)^2 search window.  alpha = 1
cancels the noise's contribution ``Var[p] + Var[q]`` to the squared
difference (the authors' course-notes code), k = 0.45 as in the paper.

*Cross filtering* (dual buffers): the weights computed from half B filter
half A's means and vice versa.  ``F_B y_A`` is then a linear filter of
``y_A`` whose weights do not depend on ``y_A``, so Stein's estimate with the
exact centre weight ``1 / sum_q w_pq`` (w_pp = 1) is unbiased for its MSE
(:func:`mcrecon.estimates.sure`).
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["NLM_ALPHA", "NLM_EPS", "nlmeans_cross"]

#: Strength of the variance cancellation (1: the noise's expected contribution).
NLM_ALPHA = 1.0
#: eps of the distance's denominator (avoids 0 / 0 on noise-free pixels).
NLM_EPS = 1e-10


@numba.njit(cache=True, nogil=True)
def _pixel_distance(y, v, m, dy, dx, k2, alpha, eps, d, valid):
    h, w, c = y.shape
    for i in range(h):
        qi = i + dy
        for j in range(w):
            qj = j + dx
            if 0 <= qi < h and 0 <= qj < w and m[i, j] and m[qi, qj]:
                s = 0.0
                for ch in range(c):
                    a = v[i, j, ch]
                    b = v[qi, qj, ch]
                    diff = y[i, j, ch] - y[qi, qj, ch]
                    s += (diff * diff - alpha * (a + min(a, b))) / (eps + k2 * (a + b))
                d[i, j] = s / c
                valid[i, j] = 1.0
            else:
                d[i, j] = 0.0
                valid[i, j] = 0.0


@numba.njit(cache=True, nogil=True)
def _integral(a, out):
    h, w = a.shape
    for j in range(w + 1):
        out[0, j] = 0.0
    for i in range(h):
        out[i + 1, 0] = 0.0
        run = 0.0
        for j in range(w):
            run += a[i, j]
            out[i + 1, j + 1] = out[i, j + 1] + run


@numba.njit(cache=True, nogil=True)
def _accumulate(y, m, dy, dx, f, sd, sv, valid, num, den):
    # weight of the pair (p, p + o) from the patch-mean distance; accumulate the
    # other half's value at q
    h, w, c = y.shape
    for i in range(h):
        qi = i + dy
        if qi < 0 or qi >= h:
            continue
        i0 = max(i - f, 0)
        i1 = min(i + f + 1, h)
        for j in range(w):
            qj = j + dx
            if qj < 0 or qj >= w or valid[i, j] == 0.0 or not m[qi, qj]:
                continue
            j0 = max(j - f, 0)
            j1 = min(j + f + 1, w)
            nv = sv[i1, j1] - sv[i0, j1] - sv[i1, j0] + sv[i0, j0]
            dist = (sd[i1, j1] - sd[i0, j1] - sd[i1, j0] + sd[i0, j0]) / nv
            wt = 1.0 if dist <= 0.0 else math.exp(-dist)
            den[i, j] += wt
            for ch in range(c):
                num[i, j, ch] += wt * y[qi, qj, ch]


@numba.njit(cache=True, nogil=True)
def _nlm_cross_kernel(ya, va, ma, yb, vb, mb, r, f, k2, alpha, eps, num_a, den_a, num_b, den_b):
    h, w, c = ya.shape
    both = ma & mb
    d = np.empty((h, w))
    valid = np.empty((h, w))
    sd = np.empty((h + 1, w + 1))
    sv = np.empty((h + 1, w + 1))
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            # weights from B filter A
            _pixel_distance(yb, vb, both, dy, dx, k2, alpha, eps, d, valid)
            _integral(d, sd)
            _integral(valid, sv)
            _accumulate(ya, ma, dy, dx, f, sd, sv, valid, num_a, den_a)
            # weights from A filter B
            _pixel_distance(ya, va, both, dy, dx, k2, alpha, eps, d, valid)
            _integral(d, sd)
            _accumulate(yb, mb, dy, dx, f, sd, sv, valid, num_b, den_b)


def nlmeans_cross(y_a, v_a, count_a, y_b, v_b, count_b, *, radius: int = 3, patch: int = 1,
                  k: float = 0.45, alpha: float = NLM_ALPHA):
    """Cross-filtered non-local means of two halves.

    Parameters
    ----------
    y_a, v_a, y_b, v_b : ndarray (H, W, C)
        Pixel means and variances of the means of halves A and B.
    count_a, count_b : ndarray (H, W)
        Samples per pixel in each half (pixels lacking a sample in either
        half take part in no comparison).
    radius, patch : int
        Search window (2 radius + 1)^2, patch (2 patch + 1)^2.
    k : float
        Damping of the distance (0.45 in the paper).

    Returns
    -------
    fa, wa, fb, wb
        ``fa = F_B y_A`` (H, W, C) and its centre weight ``wa = 1 / sum_q w``
        (H, W); the same for B filtered with A's weights.  Pixels with no
        sample in their own half are NaN (weight 0).
    """
    ya = np.ascontiguousarray(y_a, dtype=np.float64)
    yb = np.ascontiguousarray(y_b, dtype=np.float64)
    va = np.ascontiguousarray(v_a, dtype=np.float64)
    vb = np.ascontiguousarray(v_b, dtype=np.float64)
    ma = np.ascontiguousarray(np.asarray(count_a) > 0)
    mb = np.ascontiguousarray(np.asarray(count_b) > 0)
    h, w, c = ya.shape
    num_a = np.zeros((h, w, c))
    num_b = np.zeros((h, w, c))
    den_a = np.zeros((h, w))
    den_b = np.zeros((h, w))
    _nlm_cross_kernel(ya, va, ma, yb, vb, mb, int(radius), int(patch), float(k) ** 2, float(alpha), NLM_EPS,
                      num_a, den_a, num_b, den_b)
    # a pixel with a sample in its own half but none in the other is not in
    # any comparison: it keeps its own mean (weight 1)
    for y, m, num, den in ((ya, ma, num_a, den_a), (yb, mb, num_b, den_b)):
        lone = m & (den <= 0)
        num[lone] = y[lone]
        den[lone] = 1.0
    with np.errstate(invalid="ignore", divide="ignore"):
        fa = num_a / den_a[..., None]
        fb = num_b / den_b[..., None]
        wa = np.where(den_a > 0, 1.0 / den_a, 0.0)
        wb = np.where(den_b > 0, 1.0 / den_b, 0.0)
    return fa, wa, fb, wb

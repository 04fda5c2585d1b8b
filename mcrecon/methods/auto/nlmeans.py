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
(:func:`mcrecon.methods.auto.estimates.sure`).
"""

from __future__ import annotations


import numba
import numpy as np

from ...filters.engine import parallel_calls

__all__ = ["NLM_ALPHA", "NLM_EPS", "nlmeans_cross"]

#: Strength of the variance cancellation (1: the noise's expected contribution).
NLM_ALPHA = 1.0
#: eps of the distance's denominator (avoids 0 / 0 on noise-free pixels).
NLM_EPS = 1e-10


#: 2^-k for k = 0 .. 127 (float32): the integer part of :func:`_exp_neg`.
_POW2_NEG = np.array([2.0 ** -k for k in range(128)], dtype=np.float32)


@numba.njit(cache=True, nogil=True, inline="always")
def _exp_neg(x, table):
    """exp(-x) for float32 x >= 0: within 2e-6 relative of exp for x <= 30, 4e-6 up to 88 (measured); 0 beyond.

    Written as 2^-n (a table) times the
    degree-9 Taylor polynomial of exp(-t) at t = frac(x log2 e) ln 2 < ln 2
    (truncation < ln2^10 / 10! = 7e-9; the rest is float32 rounding of
    x log2 e, which grows with x).  Unlike libm's expf it vectorises:
    with libm's expf the weights take a third of NL-means' time.
    Beyond x = 88 (weights below 1e-38 beside a centre weight of 1) it is 0.
    """
    y = x * np.float32(1.4426950408889634)
    if y != y:
        return y  # NaN stays NaN (as math.exp), never a table index
    if y >= np.float32(127.0):
        return np.float32(0.0)
    n = np.int64(y)
    t = (y - np.float32(n)) * np.float32(0.6931471805599453)
    p = np.float32(-2.7557319223985893e-06)
    p = p * t + np.float32(2.48015873015873e-05)
    p = p * t + np.float32(-0.0001984126984126984)
    p = p * t + np.float32(0.001388888888888889)
    p = p * t + np.float32(-0.008333333333333333)
    p = p * t + np.float32(0.041666666666666664)
    p = p * t + np.float32(-0.16666666666666666)
    p = p * t + np.float32(0.5)
    p = p * t + np.float32(-1.0)
    p = p * t + np.float32(1.0)
    return p * table[n]


# The row loops of _band run in these helpers on 0-based views of equal length:
# an index such as j + dx, whose sign numba cannot prove, gets a negative-index
# wraparound check that kept LLVM from vectorising the loops (2.6x slower).

@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _pair_dist(up, uq, xp, xq, alpha, k2, eps, acc, n):
    for j in range(n):
        a = up[j]
        b = uq[j]
        diff = xp[j] - xq[j]
        acc[j] += (diff * diff - alpha * (a + min(a, b))) / (eps + k2 * (a + b))


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _add_shifted(acc, x, n):
    for j in range(n):
        acc[j] += x[j]


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _axpy(acc, wt, x, n):
    for j in range(n):
        acc[j] += wt[j] * x[j]


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _weights(wa, wb, sa, sb, sv, pow2, nn):
    one = np.float32(1.0)
    zero = np.float32(0.0)
    for j in range(nn):
        n = max(sv[j], one)
        wa[j] = _exp_neg(max(sa[j] / n, zero), pow2)
        wb[j] = _exp_neg(max(sb[j] / n, zero), pow2)


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _mask_pairs(da, db, dv, mp, mq, inv_c, n):
    for j in range(n):
        m = mp[j] * mq[j]
        da[j] = da[j] * inv_c * m
        db[j] = db[j] * inv_c * m
        dv[j] = m


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _mask_weights(wa, wb, mp, mq, maq, mbq, n):
    for j in range(n):
        m = mp[j] * mq[j]
        wa[j] = wa[j] * (m * maq[j])
        wb[j] = wb[j] * (m * mbq[j])


#: Rows per band of the parallel kernel.  Results do not depend on it (nor
#: on the number of threads): every output pixel is computed by one band, with
#: the same arithmetic in the same order.
_BAND = 32


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _band(ya, yb, xa, ua, xb, ub, bothf, maf, mbf, full, r, f, k2, alpha, eps, i0, i1, num_a, den_a, num_b,
          den_b):
    """Output rows [i0, i1) of both cross-filtered halves, every offset of the search window.

    Per offset o: the per-pixel distances of the pairs (p, p + o) in rows
    [i0 - f, i1 + f) -- from half B's data (xb, ub: weights that filter A)
    and from half A's -- and their horizontal patch sums; then per output
    row the vertical patch sums, the weights and the accumulation of the
    other half's means at p + o.  Distances, patch sums and weights in
    float32 (the inputs xa, ua, xb, ub), accumulation in float64.  Masks are
    float 0/1 (``bothf``: a sample in both halves; ``maf``, ``mbf``: in A, in B).
    ``full``: every pixel has samples in both halves; the number of compared
    pairs of a patch is then the product of its row and column overlaps
    (integers, exact in float32: the same values as summing the mask).
    """
    c, h, w = ya.shape
    f32 = np.float32
    rows = i1 - i0 + 2 * f
    ha = np.zeros((rows, w), f32)
    hb = np.zeros((rows, w), f32)
    hv = np.zeros((rows, w), f32)
    da = np.zeros(w, f32)
    db = np.zeros(w, f32)
    dv = np.zeros(w, f32)
    sa = np.zeros(w, f32)
    sb = np.zeros(w, f32)
    sv = np.zeros(w, f32)
    wa = np.zeros(w)
    wb = np.zeros(w)
    inv_c = f32(1.0) / f32(c)
    pow2 = _POW2_NEG
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            j0 = max(0, -dx)
            j1 = min(w, w - dx)
            for t in range(rows):
                i = i0 - f + t
                qi = i + dy
                for j in range(w):
                    da[j] = 0.0
                    db[j] = 0.0
                    dv[j] = 0.0
                if 0 <= i < h and 0 <= qi < h:
                    n_j = j1 - j0
                    dav = da[j0:j1]
                    dbv = db[j0:j1]
                    for ch in range(c):
                        _pair_dist(ub[ch, i, j0:j1], ub[ch, qi, j0 + dx:j1 + dx], xb[ch, i, j0:j1],
                                   xb[ch, qi, j0 + dx:j1 + dx], alpha, k2, eps, dav, n_j)
                        _pair_dist(ua[ch, i, j0:j1], ua[ch, qi, j0 + dx:j1 + dx], xa[ch, i, j0:j1],
                                   xa[ch, qi, j0 + dx:j1 + dx], alpha, k2, eps, dbv, n_j)
                    if full:
                        for j in range(j0, j1):
                            da[j] = da[j] * inv_c
                            db[j] = db[j] * inv_c
                    else:
                        _mask_pairs(da[j0:j1], db[j0:j1], dv[j0:j1], bothf[i, j0:j1], bothf[qi, j0 + dx:j1 + dx],
                                    inv_c, j1 - j0)
                for j in range(w):
                    ha[t, j] = 0.0
                    hb[t, j] = 0.0
                for o in range(-f, f + 1):
                    lo = max(0, -o)
                    hi = min(w, w - o)
                    _add_shifted(ha[t, lo:hi], da[lo + o:hi + o], hi - lo)
                    _add_shifted(hb[t, lo:hi], db[lo + o:hi + o], hi - lo)
                if not full:
                    for j in range(w):
                        hv[t, j] = 0.0
                    for o in range(-f, f + 1):
                        lo = max(0, -o)
                        hi = min(w, w - o)
                        _add_shifted(hv[t, lo:hi], dv[lo + o:hi + o], hi - lo)
            for i in range(i0, i1):
                qi = i + dy
                if qi < 0 or qi >= h:
                    continue
                t = i - i0 + f
                for j in range(w):
                    sa[j] = ha[t - f, j]
                    sb[j] = hb[t - f, j]
                for tt in range(t - f + 1, t + f + 1):
                    for j in range(w):
                        sa[j] += ha[tt, j]
                        sb[j] += hb[tt, j]
                if full:
                    # rows si of the patch with si and si + dy in the image, times the columns
                    rc = min(i + f + 1, h, h - dy) - max(i - f, 0, -dy)
                    for j in range(w):
                        sv[j] = f32(rc * (min(j + f + 1, w, w - dx) - max(j - f, 0, -dx)))
                else:
                    for j in range(w):
                        sv[j] = hv[t - f, j]
                    for tt in range(t - f + 1, t + f + 1):
                        for j in range(w):
                            sv[j] += hv[tt, j]
                # weight exp(-max(0, patch-mean distance)), 0 where the pair is not
                # compared or q has no sample in the half filtered (a compared pair
                # has sv >= 1: its own centre)
                _weights(wa[j0:j1], wb[j0:j1], sa[j0:j1], sb[j0:j1], sv[j0:j1], pow2, j1 - j0)
                if not full:
                    _mask_weights(wa[j0:j1], wb[j0:j1], bothf[i, j0:j1], bothf[qi, j0 + dx:j1 + dx],
                                  maf[qi, j0 + dx:j1 + dx], mbf[qi, j0 + dx:j1 + dx], j1 - j0)
                for j in range(j0, j1):
                    den_a[i, j] += wa[j]
                    den_b[i, j] += wb[j]
                for ch in range(c):
                    _axpy(num_a[ch, i, j0:j1], wa[j0:j1], ya[ch, qi, j0 + dx:j1 + dx], j1 - j0)
                    _axpy(num_b[ch, i, j0:j1], wb[j0:j1], yb[ch, qi, j0 + dx:j1 + dx], j1 - j0)


def nlmeans_cross(y_a, v_a, count_a, y_b, v_b, count_b, *, radius: int = 3, patch: int = 1,
                  k: float = 0.45, alpha: float = NLM_ALPHA, threads: int | None = None):
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
    threads : int, optional
        Worker threads (default :func:`mcrecon.filters.engine.n_threads`:
        ``$MCRECON_THREADS``, else the usable cores); the result is
        bit-identical for any value.

    Returns
    -------
    fa, wa, fb, wb
        ``fa = F_B y_A`` (H, W, C) and its centre weight ``wa = 1 / sum_q w``
        (H, W); the same for B filtered with A's weights.  Pixels with no
        sample in their own half are NaN (weight 0).
    """
    # channel planes (C, H, W): the kernel's inner loops run along contiguous rows
    ya = np.ascontiguousarray(np.moveaxis(np.asarray(y_a, dtype=np.float64), 2, 0))
    yb = np.ascontiguousarray(np.moveaxis(np.asarray(y_b, dtype=np.float64), 2, 0))
    va = np.moveaxis(np.asarray(v_a, dtype=np.float64), 2, 0)
    vb = np.moveaxis(np.asarray(v_b, dtype=np.float64), 2, 0)
    ma = np.ascontiguousarray(np.asarray(count_a) > 0)
    mb = np.ascontiguousarray(np.asarray(count_b) > 0)
    # the distance is invariant to scaling y by s and Var by s^2 (up to eps):
    # bring large values into float32's range
    big = max(float(np.max(np.abs(ya), initial=0.0)), float(np.max(np.abs(yb), initial=0.0)))
    s = 1.0 if big < 1e15 else 1.0 / big
    # (s = 1, the usual case: the values rounded as they are, without a scaled float64 copy first)
    xa, xb = ((ya * s).astype(np.float32), (yb * s).astype(np.float32)) if s != 1.0 else (
        ya.astype(np.float32), yb.astype(np.float32))
    ua = np.ascontiguousarray(va * (s * s) if s != 1.0 else va, dtype=np.float32)
    ub = np.ascontiguousarray(vb * (s * s) if s != 1.0 else vb, dtype=np.float32)
    bothf = (ma & mb).astype(np.float32)
    c, h, w = ya.shape
    num_a = np.zeros((c, h, w))
    num_b = np.zeros((c, h, w))
    den_a = np.zeros((h, w))
    den_b = np.zeros((h, w))
    f32 = np.float32
    maf, mbf, full = ma.astype(f32), mb.astype(f32), bool(ma.all() and mb.all())
    consts = (int(radius), int(patch), f32(float(k) ** 2), f32(alpha), f32(NLM_EPS))
    # bands of rows on the filters' thread pool (a parallel=True kernel around _band cost 6.7 s of
    # compilation on a first run)
    parallel_calls(_band, [(ya, yb, xa, ua, xb, ub, bothf, maf, mbf, full) + consts
                           + (i0, min(h, i0 + _BAND), num_a, den_a, num_b, den_b) for i0 in range(0, h, _BAND)],
                   threads)
    num_a = np.moveaxis(num_a, 0, 2)
    num_b = np.moveaxis(num_b, 0, 2)
    ya = np.moveaxis(ya, 0, 2)
    yb = np.moveaxis(yb, 0, 2)
    # a pixel with a sample in its own half but none in the other is not in
    # any comparison: it keeps its own mean (weight 1)
    for y, m, num, den in ((ya, ma, num_a, den_a), (yb, mb, num_b, den_b)):
        lone = m & (den <= 0)
        num[lone] = y[lone]
        den[lone] = 1.0
    with np.errstate(invalid="ignore", divide="ignore"):
        # the quotients in place of the sums: no second pair of images beside them
        num_a /= den_a[..., None]
        num_b /= den_b[..., None]
        wa = np.where(den_a > 0, 1.0 / den_a, 0.0)
        wb = np.where(den_b > 0, 1.0 / den_b, 0.0)
    return num_a, wa, num_b, wb

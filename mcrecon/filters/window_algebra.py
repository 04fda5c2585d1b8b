"""The linear algebra of one regression window (:mod:`.regression`'s per-pixel fit).

For a window of n positions with design columns x_t (d of them), weights w_t
and colours y_t: the weighted normal equations A = sum_t w_t x_t x_t^T,
B = sum_t w_t x_t y_t^T (:func:`_normal_equations`), their Cholesky solve
(:func:`_solve_spd`), the window's predictions x_t^T beta (:func:`_predict`)
and the leverages x_t^T A^-1 x_t (:func:`_leverages`) that Stein's estimate of
the collaborative regression reads.  Compiled, nogil kernels called per window
from :func:`mcrecon.filters.regression._band`; each states the order of its sums.
"""

from __future__ import annotations

import math

import numba

__all__ = ["NE_PAD", "LEVERAGE_BLOCK"]

#: The window positions of :func:`_normal_equations`' sums are padded to a multiple of this (its vector
#: width times its unroll: no scalar remainder).
NE_PAD = 16


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _solve_spd(a, b, d, nc, tmp):
    """Solve a x = b in place (b (d, nc) becomes x) by Cholesky of the SPD a (d, d); a is overwritten.

    A pivot at most 1e-300 drops that column: its coefficients 0 and, in
    :func:`_leverages`, its term 0 (its row and column of L zero, its pivot
    infinite).  Every weight 0 drops every column; a column the earlier ones
    span (grey albedo's three channels) leaves a pivot at the ridge's scale,
    below 0 where the rounding of its elimination exceeds the ridge, and
    its row of L then holds the earlier columns' terms until zeroed.  Each
    entry is the same sequence of operations as a textbook loop (its k terms
    in order); the loops run over the independent entries innermost (the rows
    of a column of L, the columns of b), so their chains of dependent
    operations overlap instead of waiting on each other.  ``tmp``: scratch of
    at least max(d, nc) floats."""
    for j in range(d):
        s = a[j, j]
        for k in range(j):
            s -= a[j, k] * a[j, k]
        if s <= 1e-300:
            for k in range(j):
                a[j, k] = 0.0
            for i in range(j + 1, d):
                a[i, j] = 0.0
            a[j, j] = math.inf  # z_j = (b_j - 0) / inf = 0 in the substitutions and the leverages
            for c in range(nc):
                b[j, c] = 0.0
            continue
        l = math.sqrt(s)
        a[j, j] = l
        for i in range(j + 1, d):
            tmp[i] = a[i, j]
        for k in range(j):
            ajk = a[j, k]
            for i in range(j + 1, d):
                tmp[i] -= a[i, k] * ajk
        for i in range(j + 1, d):
            a[i, j] = tmp[i] / l
    for i in range(d):  # forward: L z = b, then back: L^T x = z (every column of b at once)
        for c in range(nc):
            tmp[c] = b[i, c]
        for k in range(i):
            aik = a[i, k]
            for c in range(nc):
                tmp[c] -= aik * b[k, c]
        aii = a[i, i]
        for c in range(nc):
            b[i, c] = tmp[c] / aii
    for i in range(d - 1, -1, -1):
        for c in range(nc):
            tmp[c] = b[i, c]
        for k in range(i + 1, d):
            aki = a[k, i]
            for c in range(nc):
                tmp[c] -= aki * b[k, c]
        aii = a[i, i]
        for c in range(nc):
            b[i, c] = tmp[c] / aii


@numba.njit(cache=True, nogil=True, error_model="numpy", fastmath={"reassoc", "contract"})
def _normal_equations(xt, wv, yt, a, bm, d, de, n):
    """a[:d, :d] (lower triangle and 2 x 2 blocks beside it) = sum_t w_t x_t x_t^T, bm = sum_t w_t x_t y_t^T.

    The sums are reassociated (fastmath ``reassoc``: vector lanes and FMA), so their rounding differs
    from a sequential sum's; the order is fixed by the code, so the result does not depend on threads.
    Two rows p by four columns q per pass (two by two at the diagonal), and two rows by three colours:
    each loaded element serves two to four products.  The weighted rows ``w_t x_pt`` are formed in the
    pass, not stored beforehand: a multiply is cheaper than the store and the reloads (the passes are
    bound by their loads and stores; 1.5x faster than 2 x 2 blocks over stored weighted rows, measured)."""
    for p in range(0, de, 2):
        xp0, xp1 = xt[p], xt[p + 1]
        q = 0
        while q + 3 <= p + 1:  # columns q .. q + 3, all at or left of the diagonal block
            x0, x1, x2, x3 = xt[q], xt[q + 1], xt[q + 2], xt[q + 3]
            s00 = 0.0
            s01 = 0.0
            s02 = 0.0
            s03 = 0.0
            s10 = 0.0
            s11 = 0.0
            s12 = 0.0
            s13 = 0.0
            for t in range(n):
                w0 = wv[t] * xp0[t]
                w1 = wv[t] * xp1[t]
                s00 += w0 * x0[t]
                s01 += w0 * x1[t]
                s02 += w0 * x2[t]
                s03 += w0 * x3[t]
                s10 += w1 * x0[t]
                s11 += w1 * x1[t]
                s12 += w1 * x2[t]
                s13 += w1 * x3[t]
            a[p, q] = s00
            a[p, q + 1] = s01
            a[p, q + 2] = s02
            a[p, q + 3] = s03
            a[p + 1, q] = s10
            a[p + 1, q + 1] = s11
            a[p + 1, q + 2] = s12
            a[p + 1, q + 3] = s13
            q += 4
        if q <= p:  # the diagonal block
            x0, x1 = xt[q], xt[q + 1]
            s00 = 0.0
            s01 = 0.0
            s10 = 0.0
            s11 = 0.0
            for t in range(n):
                w0 = wv[t] * xp0[t]
                w1 = wv[t] * xp1[t]
                s00 += w0 * x0[t]
                s01 += w0 * x1[t]
                s10 += w1 * x0[t]
                s11 += w1 * x1[t]
            a[p, q] = s00
            a[p, q + 1] = s01
            a[p + 1, q] = s10
            a[p + 1, q + 1] = s11
    nc = yt.shape[0]
    for p in range(0, de, 2):
        xp0, xp1 = xt[p], xt[p + 1]
        c = 0
        while c + 2 < nc:
            y0, y1, y2 = yt[c], yt[c + 1], yt[c + 2]
            s00 = 0.0
            s01 = 0.0
            s02 = 0.0
            s10 = 0.0
            s11 = 0.0
            s12 = 0.0
            for t in range(n):
                w0 = wv[t] * xp0[t]
                w1 = wv[t] * xp1[t]
                s00 += w0 * y0[t]
                s01 += w0 * y1[t]
                s02 += w0 * y2[t]
                s10 += w1 * y0[t]
                s11 += w1 * y1[t]
                s12 += w1 * y2[t]
            bm[p, c] = s00
            bm[p, c + 1] = s01
            bm[p, c + 2] = s02
            if p + 1 < d:
                bm[p + 1, c] = s10
                bm[p + 1, c + 1] = s11
                bm[p + 1, c + 2] = s12
            c += 3
        while c < nc:
            yc = yt[c]
            s0 = 0.0
            s1 = 0.0
            for t in range(n):
                w0 = wv[t] * xp0[t]
                w1 = wv[t] * xp1[t]
                s0 += w0 * yc[t]
                s1 += w1 * yc[t]
            bm[p, c] = s0
            if p + 1 < d:
                bm[p + 1, c] = s1
            c += 1


#: Window positions per block of :func:`_leverages`: its scratch (d x this many float64, 12 KiB at d = 12)
#: stays in L1 beside the window's design, and a pass over the block is long enough to run at full speed.
LEVERAGE_BLOCK = 128


@numba.njit(cache=True, nogil=True, error_model="numpy", fastmath={"contract"})
def _leverages(chol, xt, zt, lev, d, n):
    """lev[t] = x_t^T A^-1 x_t over the window, from the Cholesky factor L of A (lower triangle of ``chol``):
    z = L^-1 x_t by forward substitution, for a block of t at once (loops along the block), lev = |z|^2.

    The prediction of pixel t by this window moves by ``w_t lev[t]`` per unit of y_t (d beta = A^-1 x_t
    w_t dy_t), so summed over the windows covering a pixel, weighted as the collaborative average weighs
    them, it is the filter's derivative at the pixel itself: Stein's estimate needs nothing else.
    Blocks of :data:`LEVERAGE_BLOCK` positions keep the scratch ``zt`` (d, block) in L1 (the whole
    window's would not be, and the pass would wait on memory); each lev[t] is the same arithmetic in the
    same order whatever the block.  The substitution subtracts four earlier rows per pass over the block
    (the same subtractions in the same order as one row per pass): the running z_i[t] then stays in a
    register for four products instead of a load and a store per product."""
    nb = zt.shape[1]
    for t0 in range(0, n, nb):
        m = min(nb, n - t0)
        lv = lev[t0:t0 + m]
        for t in range(m):
            lv[t] = 0.0
        for i in range(d):
            zi, xi = zt[i, :m], xt[i, t0:t0 + m]
            for t in range(m):
                zi[t] = xi[t]
            k = 0
            while k + 3 < i:  # four earlier rows per pass: z_i[t] is loaded and stored once for four products
                l0, l1, l2, l3 = chol[i, k], chol[i, k + 1], chol[i, k + 2], chol[i, k + 3]
                z0, z1, z2, z3 = zt[k, :m], zt[k + 1, :m], zt[k + 2, :m], zt[k + 3, :m]
                for t in range(m):
                    zi[t] = (((zi[t] - l0 * z0[t]) - l1 * z1[t]) - l2 * z2[t]) - l3 * z3[t]
                k += 4
            while k < i:
                lik = chol[i, k]
                zk = zt[k, :m]
                for t in range(m):
                    zi[t] -= lik * zk[t]
                k += 1
            inv = 1.0 / chol[i, i]
            for t in range(m):
                zi[t] *= inv
                lv[t] += zi[t] * zi[t]


@numba.njit(cache=True, nogil=True, error_model="numpy", fastmath={"contract"})
def _predict(xt, beta, yp, d, n):
    """yp[c, t] = x_t^T beta[:, c] over the window: the columns added two at a time,
    ``((0 + (b0 x0 + b1 x1)) + (b2 x2 + b3 x3)) + ...``, up to four pairs per pass along the window (one load
    and one store of yp[c, t] for eight columns' products instead of one per pair: the pass is bound by
    memory, not by the multiplies).  Each yp[c, t] is that sum in that order whatever the pass width."""
    nc = yp.shape[0]
    for c in range(nc):
        yc = yp[c]
        for t in range(n):
            yc[t] = 0.0
        p = 0
        while p + 7 < d:
            b0, b1, b2, b3 = beta[p, c], beta[p + 1, c], beta[p + 2, c], beta[p + 3, c]
            b4, b5, b6, b7 = beta[p + 4, c], beta[p + 5, c], beta[p + 6, c], beta[p + 7, c]
            x0, x1, x2, x3 = xt[p], xt[p + 1], xt[p + 2], xt[p + 3]
            x4, x5, x6, x7 = xt[p + 4], xt[p + 5], xt[p + 6], xt[p + 7]
            for t in range(n):
                yc[t] = (((yc[t] + (b0 * x0[t] + b1 * x1[t])) + (b2 * x2[t] + b3 * x3[t]))
                         + (b4 * x4[t] + b5 * x5[t])) + (b6 * x6[t] + b7 * x7[t])
            p += 8
        while p + 3 < d:
            b0, b1, b2, b3 = beta[p, c], beta[p + 1, c], beta[p + 2, c], beta[p + 3, c]
            x0, x1, x2, x3 = xt[p], xt[p + 1], xt[p + 2], xt[p + 3]
            for t in range(n):
                yc[t] = (yc[t] + (b0 * x0[t] + b1 * x1[t])) + (b2 * x2[t] + b3 * x3[t])
            p += 4
        while p + 1 < d:
            b0, b1 = beta[p, c], beta[p + 1, c]
            x0, x1 = xt[p], xt[p + 1]
            for t in range(n):
                yc[t] += b0 * x0[t] + b1 * x1[t]
            p += 2
        if p < d:
            b0 = beta[p, c]
            x0 = xt[p]
            for t in range(n):
                yc[t] += b0 * x0[t]

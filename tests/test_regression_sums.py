"""The regression's per-window sums and predictions, for every design width and number of colours.

``_normal_equations`` sums two rows by four columns a pass (two by two at the
diagonal) and two rows by three colours (the colours left over one at a
time), forming the weighted rows in the pass: every entry of the lower
triangle and of the right-hand sides must be sum_t w_t x_pt x_qt and
sum_t w_t x_pt y_ct for every number of columns d (whole four-column blocks,
the diagonal block, an odd d's zero row) and of colours, and zero-weight
padding positions must add nothing.  ``_predict`` adds up to eight columns a
pass: each prediction must be the sum of the column pairs in order,
``((0 + (b0 x0 + b1 x1)) + (b2 x2 + b3 x3)) + ...``, for every d.
"""

import numba
import numpy as np
import pytest

from mcrecon.filters.window_algebra import NE_PAD, _normal_equations, _predict


def _design(d, nc, n, npad, seed):
    rng = np.random.default_rng(seed)
    de = d + (d & 1)
    xt = np.zeros((de, npad))
    xt[:d, :n] = rng.standard_normal((d, n))
    yt = np.zeros((nc, npad))
    yt[:, :n] = rng.standard_normal((nc, n))
    wv = np.zeros(npad)
    wv[:n] = rng.uniform(0.0, 1.0, n)
    return de, xt, yt, wv


@pytest.mark.parametrize("d", [1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 14])
@pytest.mark.parametrize("nc", [1, 2, 3, 4, 6, 7])
def test_normal_equations_are_the_weighted_sums(d, nc):
    n = 361
    npad = (n + NE_PAD - 1) // NE_PAD * NE_PAD
    de, xt, yt, wv = _design(d, nc, n, npad, seed=d * 10 + nc)
    a = np.full((de, de), np.nan)
    bm = np.full((d, nc), np.nan)
    _normal_equations(xt, wv, yt, a, bm, d, de, npad)
    x, w, y = xt[:d, :n], wv[:n], yt[:, :n]
    want_a = (x * w) @ x.T
    want_b = (x * w) @ y.T
    tri = np.tril_indices(d)
    scale = np.abs(want_a).max()
    assert np.max(np.abs(a[:d, :d][tri] - want_a[tri])) <= 1e-13 * scale
    assert np.max(np.abs(bm - want_b)) <= 1e-13 * np.abs(want_b).max()
    # the padding (zero weights) adds nothing: the sums over the window alone are the same to rounding
    a2 = np.full((de, de), np.nan)
    bm2 = np.full((d, nc), np.nan)
    _normal_equations(xt[:, :n].copy(), wv[:n].copy(), yt[:, :n].copy(), a2, bm2, d, de, n)
    assert np.max(np.abs(a2[:d, :d][tri] - a[:d, :d][tri])) <= 1e-13 * scale


@numba.njit(fastmath={"contract"})
def _predict_by_pairs(xt, beta, yp, d, n):
    """One column pair a pass (the sum the kernel must equal bit for bit)."""
    for c in range(yp.shape[0]):
        for t in range(n):
            yp[c, t] = 0.0
        p = 0
        while p + 1 < d:
            for t in range(n):
                yp[c, t] += beta[p, c] * xt[p, t] + beta[p + 1, c] * xt[p + 1, t]
            p += 2
        if p < d:
            for t in range(n):
                yp[c, t] += beta[p, c] * xt[p, t]


@pytest.mark.parametrize("d", [1, 2, 3, 4, 5, 7, 8, 9, 10, 12, 17])
@pytest.mark.parametrize("nc", [1, 3, 6])
def test_predictions_sum_the_column_pairs_in_order(d, nc):
    n = 361
    rng = np.random.default_rng(d + 100 * nc)
    xt = rng.standard_normal((d + (d & 1), n))
    beta = rng.standard_normal((d, nc))
    yp = np.full((nc, n), np.nan)
    _predict(xt, beta, yp, d, n)
    exact = beta.T @ xt[:d]
    assert np.max(np.abs(yp - exact)) <= 1e-13 * np.abs(exact).max()
    want = np.full((nc, n), np.nan)
    _predict_by_pairs(xt, beta, want, d, n)
    assert np.array_equal(yp, want)

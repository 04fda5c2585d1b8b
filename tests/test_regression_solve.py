"""The regression's per-window solve and leverages x_t^T A^-1 x_t, for every design width.

``_solve_spd`` runs its loops over the independent entries innermost: the
coefficients must be those of A^-1 b for every number of columns and of
right-hand sides, and a column without weight must still be dropped.
``_leverages`` runs the forward substitution four earlier rows per pass and
the window in blocks of positions: the value must be x_t^T A^-1 x_t for every
number of columns d (the four-row passes and the rows left over) and every
window length (whole blocks and a partial one), and each position's value must
not depend on the block it was computed in.
"""

import numpy as np
import pytest

from mcrecon.filters.window_algebra import LEVERAGE_BLOCK, _leverages, _solve_spd


def _system(d, n, seed):
    rng = np.random.default_rng(seed)
    de = d + (d & 1)
    xt = np.zeros((de, n))
    xt[:d] = rng.standard_normal((d, n))
    a = xt[:d] @ (xt[:d] * rng.uniform(0.1, 1.0, n)).T + 1e-3 * np.eye(d)
    chol = np.zeros((de, de))
    chol[:d, :d] = np.linalg.cholesky(a)
    return a, chol, xt


@pytest.mark.parametrize("d", [1, 2, 3, 4, 5, 7, 8, 9, 11, 14])
@pytest.mark.parametrize("n", [1, 5, LEVERAGE_BLOCK, LEVERAGE_BLOCK + 3, 361])
def test_leverages_are_the_quadratic_form_of_the_inverse(d, n):
    a, chol, xt = _system(d, n, seed=d * 1000 + n)
    lev = np.full(n, np.nan)
    _leverages(chol, xt, np.zeros((xt.shape[0], LEVERAGE_BLOCK)), lev, d, n)
    want = np.einsum("tn,tn->n", xt[:d], np.linalg.solve(a, xt[:d]))
    np.testing.assert_allclose(lev, want, rtol=1e-9, atol=0)


@pytest.mark.parametrize("d", [3, 6, 11])
def test_leverages_do_not_depend_on_the_block(d):
    n = 361
    _, chol, xt = _system(d, n, seed=d)
    levs = []
    for block in (1, 7, 48, LEVERAGE_BLOCK, 400):
        lev = np.zeros(n)
        _leverages(chol, xt, np.zeros((xt.shape[0], block)), lev, d, n)
        levs.append(lev)
    for lev in levs[1:]:
        assert np.array_equal(lev, levs[0])


@pytest.mark.parametrize("d", [1, 2, 3, 5, 8, 11, 14])
@pytest.mark.parametrize("nc", [1, 3, 6])
def test_solve_is_the_inverse_times_the_right_hand_sides(d, nc):
    a, _, _ = _system(d, 50, seed=7 * d + nc)
    b = np.random.default_rng(d).standard_normal((d, nc))
    x = b.copy()
    _solve_spd(a.copy(), x, d, nc, np.zeros(max(d, nc)))
    np.testing.assert_allclose(x, np.linalg.solve(a, b), rtol=1e-9, atol=1e-12)


def test_solve_drops_a_column_without_weight():
    a, _, _ = _system(6, 50, seed=3)
    a[2, :] = 0.0
    a[:, 2] = 0.0
    b = np.random.default_rng(3).standard_normal((6, 3))
    x = b.copy()
    _solve_spd(a.copy(), x, 6, 3, np.zeros(6))
    keep = [0, 1, 3, 4, 5]
    assert np.all(x[2] == 0.0)
    np.testing.assert_allclose(x[keep], np.linalg.solve(a[np.ix_(keep, keep)], b[keep]), rtol=1e-9, atol=1e-12)


def test_solve_drops_a_column_the_earlier_ones_span():
    """A column that is a combination of earlier ones (grey albedo's three channels; the ridge below the
    rounding) can leave a non-positive pivot while its row of L holds the earlier columns' weights: the dropped
    column's coefficients are still 0 and the others those of the system without it, and its leverage adds
    nothing."""
    rng = np.random.default_rng(11)
    n = 40
    x = np.ones((4, n))
    x[1] = rng.standard_normal(n)
    x[2] = rng.standard_normal(n)
    x[3] = 2.0 * x[1] - x[2]                  # spanned by columns 1 and 2
    w = rng.uniform(0.2, 1.0, n)
    a = x @ (x * w).T
    a[3, 3] -= 1e-9 * a[3, 3]                 # its pivot below 0: the rounding of a ridge-free fit
    b = rng.standard_normal((4, 3))
    sol = b.copy()
    chol = a.copy()
    _solve_spd(chol, sol, 4, 3, np.zeros(4))
    keep = [0, 1, 2]
    assert np.all(sol[3] == 0.0)
    np.testing.assert_allclose(sol[keep], np.linalg.solve(a[np.ix_(keep, keep)], b[keep]), rtol=1e-9, atol=1e-12)
    lev = np.zeros(n)
    _leverages(chol, x, np.zeros((4, LEVERAGE_BLOCK)), lev, 4, n)
    want = np.einsum("tn,tn->n", x[keep], np.linalg.solve(a[np.ix_(keep, keep)], x[keep]))
    np.testing.assert_allclose(lev, want, rtol=1e-9, atol=1e-12)

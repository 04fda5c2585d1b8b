"""The regression's windows fitted on a grid of centres (``stride``): brute force, coverage, bit-identity."""

import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(__file__))

import mcrecon  # noqa: E402
from mcrecon.errors import InputError  # noqa: E402
from mcrecon.filters.regression import collaborative_regression, collaborative_regressions  # noqa: E402
from test_nfor import _brute_weights_and_features, _fit_window, _tiny  # noqa: E402


@pytest.mark.parametrize("stride,min_weight", [(2, "median"), (3, "median"), (2, 0.0)])
def test_strided_regression_matches_brute_force_grid_and_fallback_windows(stride, min_weight):
    """Windows at every stride-th pixel and row, and at every pixel whose own weights of the grid pixels in
    its window sum below ``min_weight``; each pixel averages the windows covering it."""
    y, guide, var, feats = _tiny(3, h=11, w=10)
    r, f, k = 2, 1, 0.8
    h, w, _ = y.shape
    wts, fs = _brute_weights_and_features(y, guide, var, feats, r, f, k)
    num, den = np.zeros_like(y), np.zeros((h, w))

    def add(i, j):
        win, wv, pred = _fit_window(y, fs, wts, r, i, j)
        for (qi, qj), wt, p in zip(win, wv, pred):
            num[qi, qj] += wt * p
            den[qi, qj] += wt

    grid = {(i, j) for i in range(0, h, stride) for j in range(0, w, stride)}
    own = {(i, j): sum(wt for (pi, pj, qi, qj), wt in wts.items() if (pi, pj) == (i, j) and (qi, qj) in grid)
           for i in range(h) for j in range(w)}
    if min_weight == "median":  # half the pixels off the grid fit their own windows
        min_weight = float(np.median([v for q, v in own.items() if q not in grid]))
    fits = [(i, j) for i in range(h) for j in range(w) if (i, j) in grid or own[i, j] < min_weight]
    assert len(grid) < len(fits) < h * w or min_weight == 0.0
    for i, j in fits:
        add(i, j)
    got, got_den = collaborative_regression(y, guide, var, feats, radius=r, patch=f, k=k, return_weights=True,
                                            stride=stride, min_weight=min_weight)
    np.testing.assert_allclose(got_den, den, rtol=2e-5)
    np.testing.assert_allclose(got, num / den[..., None], rtol=1e-4, atol=1e-6)
    assert np.isfinite(got).all()


def test_strided_bandwidths_in_one_pass_equal_separate_calls_and_any_thread_count():
    y, guide, var, feats = _tiny(4, h=23, w=19)
    kw = dict(radius=3, patch=1, stride=2)
    both = collaborative_regressions(y, guide, var, feats, ks=(0.5, 1.0), **kw)
    for k, got in zip((0.5, 1.0), both):
        np.testing.assert_array_equal(got, collaborative_regression(y, guide, var, feats, k=k, **kw))
    np.testing.assert_array_equal(collaborative_regression(y, guide, var, feats, threads=1, **kw),
                                  collaborative_regression(y, guide, var, feats, threads=2, **kw))


def test_stride_one_is_the_default_kernel_bit_for_bit():
    y, guide, var, feats = _tiny(5, h=17, w=21)
    np.testing.assert_array_equal(collaborative_regression(y, guide, var, feats, radius=3, patch=1),
                                  collaborative_regression(y, guide, var, feats, radius=3, patch=1, stride=1))


def test_an_exactly_linear_image_is_reproduced_with_a_stride():
    """Every window's fit of an image linear in its features is exact, so any average of them is."""
    rng = np.random.default_rng(6)
    feats = rng.uniform(0, 1, size=(20, 18, 2))
    y = np.stack([1.0 + 2.0 * feats[..., 0] - feats[..., 1], 0.5 + feats[..., 1], 3.0 + 0 * feats[..., 0]], axis=2)
    var = np.full_like(y, 0.01)
    got = collaborative_regression(y, y, var, feats, radius=4, patch=1, stride=3)
    np.testing.assert_allclose(got, y, rtol=1e-6)


def test_a_stride_beyond_the_window_is_refused():
    y, guide, var, feats = _tiny(7)
    with pytest.raises(ValueError, match="stride"):
        collaborative_regression(y, guide, var, feats, radius=2, stride=4)
    with pytest.raises(InputError, match="stride"):
        mcrecon.get_method("nfor", radius=2, stride=4)

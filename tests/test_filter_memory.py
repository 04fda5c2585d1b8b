"""The feature-guided filters' memory grows by few bytes per pixel.

A 1080p frame goes through the regression four or five times: what each
call holds beside its inputs and its result is what a frame's peak is made
of.  The growth per added pixel (two heights, the same width and one thread,
so the bands' fixed scratch cancels) of the numpy memory traced while a call
runs stays below a bound written from the arrays the call needs at once: the
padded colour and features, the sums, and the guide and its variance in
float32 -- not an unpadded copy beside each padded one nor a quotient image
beside the sums.
"""

import tracemalloc

import numpy as np
import pytest

from mcrecon.filters.nlmeans import nlmeans_filter
from mcrecon.filters.regression import collaborative_regression
from mcrecon.methods.auto.nlmeans import nlmeans_cross

W = 96


def _inputs(h, seed=0):
    rng = np.random.default_rng(seed)
    return (rng.random((h, W, 6)), rng.random((h, W, 3)), rng.random((h, W, 3)) * 0.01, rng.random((h, W, 8)))


def _peak(fn, h):
    args = _inputs(h)
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        res = fn(*args)
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    del res
    return peak


def _growth_per_pixel(fn):
    fn(*_inputs(16))  # compiled first: the compiler's own allocations are not the filter's
    return (_peak(fn, 128) - _peak(fn, 64)) / (64 * W)


def test_regression_holds_the_padded_planes_and_the_sums_only():
    # 6 channels, 8 features, the centre weights: padded colour 48 + features 64 (x (W + 18) / W), sums
    # 8 planes 64, guide and variance 24 bytes per pixel: about 221 (unpadded copies beside them: 333)
    per_px = _growth_per_pixel(lambda y, g, v, f: collaborative_regression(
        y, g, v, f, return_centre_weight=True, return_weights=True, threads=1))
    assert per_px < 260, per_px


def test_nlmeans_filter_divides_in_place():
    # planes 24, guide and variance 24, numerator and denominator 48 bytes per pixel: 96 (a quotient
    # image beside them: 120)
    per_px = _growth_per_pixel(lambda y, g, v, f: nlmeans_filter(y[..., :3], g, v, radius=3, patch=1, k=1.0,
                                                                 threads=1))
    assert per_px < 105, per_px


def test_nlmeans_cross_divides_in_place():
    def run(y, g, v, f):
        count = np.full(y.shape[:2], 4)
        return nlmeans_cross(y[..., :3], v, count, g, v, count, radius=3, patch=1, threads=1)
    # two halves' planes 48, their float32 copies and variances 48, masks 14, sums 64, centre weights and
    # their temporaries 33 bytes per pixel: about 208 (a quotient pair beside the sums: 256)
    per_px = _growth_per_pixel(run)
    assert per_px < 225, per_px


@pytest.mark.parametrize("centre", [False, True])
def test_regression_results_are_plain_arrays(centre):
    y, g, v, f = _inputs(20)
    res = collaborative_regression(y, g, v, f, return_centre_weight=centre, return_weights=True, threads=1)
    assert res[0].shape == (20, W, 6) and all(r.shape == (20, W) for r in res[1:])
    assert all(np.isfinite(r).all() for r in res)

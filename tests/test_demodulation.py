"""Albedo demodulation (mcrecon.filters.demodulation): invariants and the texture it keeps."""

import numpy as np
import pytest

from mcrecon.filters.demodulation import ALBEDO_FLOOR, demodulated_nlmeans, demodulation_divisor
from mcrecon.filters.nlmeans import nlmeans_filter

OPTS = dict(radius=5, patch=2, k=0.45)


def _noisy(shape, seed, level=1.0, sd=0.1):
    rng = np.random.default_rng(seed)
    y = level + sd * rng.standard_normal(shape)
    return y, np.full(shape, sd * sd)


def test_a_constant_albedo_changes_nothing():
    """The patch distance is normalised by the variance: dividing colour and variance by a constant a
    (variance by a^2) and multiplying back by a is the filter of the colour itself (to the float32 guide
    the weights are computed from, and the distance's eps: measured 1.2e-5 relative at most)."""
    y, v = _noisy((20, 24, 3), 0)
    for a in (0.05, 0.5, 3.0):
        np.testing.assert_allclose(demodulated_nlmeans(y, v, np.full((20, 24, 3), a), **OPTS),
                                   nlmeans_filter(y, y, v, **OPTS), rtol=1e-4, atol=1e-9)


def test_an_albedo_of_zero_everywhere_is_the_colour_filter():
    """Albedo 0 (metal, glass, emitters) everywhere: the divisor is the floor, a constant: the colour filter."""
    y, v = _noisy((16, 16, 3), 1)
    np.testing.assert_allclose(demodulated_nlmeans(y, v, np.zeros((16, 16, 3)), **OPTS),
                               nlmeans_filter(y, y, v, **OPTS), rtol=1e-4, atol=1e-9)


def test_a_checkerboard_under_smooth_light_keeps_its_edges():
    """colour = albedo x irradiance, the albedo a checkerboard of 4-px squares (0.3 / 0.9), the irradiance
    a smooth ramp, noise of s.e. 0.05 on each pixel mean.  The quotient is the ramp plus noise, so the
    demodulated filter's error is far below the noise (measured 0.082 of the pixel mean's MSE) while
    the colour's own NL-means stops at every edge (measured 0.39)."""
    h = w = 48
    yy, xx = np.mgrid[0:h, 0:w]
    alb = np.where(((yy // 4) + (xx // 4)) % 2 == 0, 0.9, 0.3)[..., None] * np.ones(3)
    irr = (1.0 + 0.5 * xx / w)[..., None] * np.ones(3)
    truth = alb * irr
    rng = np.random.default_rng(2)
    y = truth + 0.05 * rng.standard_normal(truth.shape)
    v = np.full(y.shape, 0.05 ** 2)
    e_mean = np.mean((y - truth) ** 2)
    e_demod = np.mean((demodulated_nlmeans(y, v, alb, **OPTS) - truth) ** 2)
    e_colour = np.mean((nlmeans_filter(y, y, v, **OPTS) - truth) ** 2)
    assert e_demod < 0.095 * e_mean, e_demod / e_mean  # measured 0.082; 15 % margin
    assert e_demod < 0.24 * e_colour, (e_demod / e_mean, e_colour / e_mean)  # measured 0.210


def test_the_filter_is_scale_free():
    """Colour x c (variance x c^2) gives the image x c, for a dim and a bright image alike: the quotient is
    filtered in units of its mean magnitude (with the NL-means distance's absolute eps, a checkerboard
    scaled by 1e-3 lost three quarters of the filter's gain)."""
    h = w = 32
    yy, xx = np.mgrid[0:h, 0:w]
    alb = np.where(((yy // 4) + (xx // 4)) % 2 == 0, 0.9, 0.3)[..., None] * np.ones(3)
    rng = np.random.default_rng(5)
    y = alb * (1.0 + 0.5 * xx / w)[..., None] + 0.05 * rng.standard_normal((h, w, 3))
    v = np.full(y.shape, 0.05 ** 2)
    base = demodulated_nlmeans(y, v, alb, **OPTS)
    for c in (1e-6, 1e-3, 1e4):
        np.testing.assert_allclose(demodulated_nlmeans(c * y, c * c * v, alb, **OPTS), c * base, rtol=1e-4,
                                   atol=1e-12 * c)


def test_the_divisor():
    """Per channel when the albedo has the image's channels, their mean otherwise; NaN and values below
    the floor (negative ones too) become the floor."""
    a = np.array([[[0.5, 0.01, np.nan]], [[np.inf, -np.inf, 2.0]]])
    np.testing.assert_array_equal(demodulation_divisor(a, 3), [[[0.5, ALBEDO_FLOOR, ALBEDO_FLOOR]],
                                                               [[ALBEDO_FLOOR, ALBEDO_FLOOR, 2.0]]])
    np.testing.assert_allclose(demodulation_divisor(np.array([[[0.2, 0.4, 0.6]]]), 1), [[[0.4]]])
    np.testing.assert_allclose(demodulation_divisor(np.array([[0.3]]), 2), [[[0.3, 0.3]]])
    np.testing.assert_array_equal(demodulation_divisor(np.array([[[-1.0]]]), 1, floor=0.1), [[[0.1]]])


def test_shapes_are_checked():
    y, v = _noisy((8, 8, 3), 3)
    with pytest.raises(ValueError, match="albedo .* does not match image"):
        demodulated_nlmeans(y, v, np.ones((8, 9, 3)))
    with pytest.raises(ValueError, match="variance .* does not match image"):
        demodulated_nlmeans(y, v[..., :1], np.ones((8, 8, 3)))
    with pytest.raises(ValueError, match=r"must be \(H, W, C\)"):
        demodulated_nlmeans(y[..., 0], v[..., 0], np.ones((8, 8)))


def test_the_docstring_example_runs():
    import doctest

    import mcrecon.filters.demodulation as mod

    res = doctest.testmod(mod)
    assert res.failed == 0 and res.attempted > 0

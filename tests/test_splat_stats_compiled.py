"""The default splat's per-round pixel statistics in compiled code give the bits of the array expressions.

The references below are the numpy expressions the compiled passes replace, kept here verbatim so
that any change of the arithmetic's order shows up as a failed comparison.
"""

from __future__ import annotations

import numpy as np
import pytest

from mcrecon.methods.splat.consistent import edge_radius, pixel_moments, width_coefs
from mcrecon.methods.splat.outliers import _excess_width


def _pixel_moments_reference(counts, s1, s2):
    n = counts.astype(np.float64)[:, :, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(n > 0, s1 / np.maximum(n, 1.0), 0.0)
        var = np.maximum(s2 / np.maximum(n, 1.0) - mean * mean, 0.0) * n / np.maximum(n - 1.0, 1.0)
        ok = n >= 2
        se2 = np.where(ok, var / np.maximum(n, 1.0), np.inf)
        lv = np.where(ok, np.log(var), 0.0)
        tv = np.broadcast_to(np.where(ok, 2.0 / np.maximum(n - 1.0, 1.0), np.inf), mean.shape)
    return np.ascontiguousarray(np.stack([mean, se2, lv, tv], axis=-1))


def _edge_radius_reference(stats, k):
    mean, se2 = stats[..., 0], stats[..., 1]
    m = np.pad(mean, ((1, 1), (1, 1), (0, 0)), mode="symmetric")
    v = np.pad(np.where(np.isfinite(se2), se2, 0.0), ((1, 1), (1, 1), (0, 0)), mode="symmetric")
    dx, vx = m[:, 2:] - m[:, :-2], v[:, 2:] + v[:, :-2]
    dy, vy = m[2:] - m[:-2], v[2:] + v[:-2]
    gx = (dx[:-2] + 2.0 * dx[1:-1] + dx[2:]) / 8.0
    gy = (dy[:, :-2] + 2.0 * dy[:, 1:-1] + dy[:, 2:]) / 8.0
    var_g = (vx[:-2] + 4.0 * vx[1:-1] + vx[2:] + vy[:, :-2] + 4.0 * vy[:, 1:-1] + vy[:, 2:]) / 64.0
    se = np.sqrt(se2)
    g = np.sqrt(np.maximum(gx * gx + gy * gy - var_g, 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.where(g > 0, k * se / g, np.inf)
    r = np.where(np.isfinite(se) & (se > 0), r, 0.0)
    return np.ascontiguousarray(r.min(axis=2))


def _sums(rng, h, w, c):
    """Per-pixel sums of random samples with 0, 1, 2 and many samples, equal samples (variance 0), an edge
    and HDR values."""
    counts = rng.integers(0, 40, size=(h, w))
    counts.flat[:3] = [0, 1, 2][:counts.size]
    s1 = np.zeros((h, w, c))
    s2 = np.zeros((h, w, c))
    for y in range(h):
        for x in range(w):
            scale = 1e4 if x > w // 2 else 1.0
            v = rng.exponential(scale, size=(counts[y, x], c))
            if (y + x) % 7 == 0:
                v[:] = 0.25  # no spread
            s1[y, x] = v.sum(0)
            s2[y, x] = (v * v).sum(0)
    return counts, s1, s2


@pytest.mark.parametrize("shape", [(13, 17, 3), (1, 9, 3), (7, 1, 1), (1, 1, 3)])
def test_pixel_moments_and_edge_radius_equal_the_array_expressions(shape):
    rng = np.random.default_rng(5)
    counts, s1, s2 = _sums(rng, *shape)
    st = pixel_moments(counts, s1, s2)
    ref = _pixel_moments_reference(counts, s1, s2)
    assert st.shape == ref.shape
    np.testing.assert_array_equal(st, ref)
    for k in (2.64, 1.0):
        np.testing.assert_array_equal(edge_radius(st, k), _edge_radius_reference(ref, k))


def test_width_factors_give_eq8_widths_bit_for_bit():
    """Eq. 8's diameter from the per-pixel factors (C N^-alpha, sqrt f) equals the per-sample expression."""
    from mcrecon.methods.splat.consistent import _width_of

    rng = np.random.default_rng(2)
    f = np.concatenate([rng.exponential(1.0, 60), [0.0, np.inf, 1e-300, 5e-324, 1e300]]).reshape(5, 13)
    n = rng.integers(1, 200, size=f.shape).astype(np.float64)
    for c, alpha in ((2.0, 0.5), (8.0, 0.3)):
        coef, sf = width_coefs(f, n, c, alpha)
        for g in (1e-12, 0.3, 2.0, 7e5):
            for y in range(f.shape[0]):
                for x in range(f.shape[1]):
                    ref = _excess_width(g, 0.0, f[y, x], n[y, x], c, alpha, 1.0, 32.0)
                    got = _width_of(g - 0.0, coef[y, x], sf[y, x], 32.0)
                    assert got == ref, (g, f[y, x], n[y, x])

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


def test_round_sums_equal_the_separate_passes():
    """The one pass over a round (counts, G moments, channel sums, every feature's sums) gives the bits of
    the separate passes of the streamed path, over rounds whose first sets the features' shifts, with
    float32 and float64 features, a NaN feature and one and two threads."""
    from mcrecon.methods.splat.consistent import FeatureSums, channel_sums, round_sums
    from mcrecon.methods.splat.bands import in_bands
    from mcrecon.methods.splat.outliers import _count_and_moments
    from mcrecon.filters.luminance import LUMINANCE_WEIGHTS

    rng = np.random.default_rng(4)
    w, h, n = 23, 19, 70000  # above bands.BAND_MIN: two bands on two threads
    a, b = FeatureSums(w, h), FeatureSums(w, h)
    for r in range(2):
        pos = rng.uniform(0, 1, (n, 2)) * [w, h]
        if r:
            pos = pos[np.lexsort((pos[:, 0], np.floor(pos[:, 1])))]  # rows never decrease: bands visit their own
        val = rng.exponential(1.0, (n, 3))  # float64, as positions: the library passes the pair in one dtype
        feats = {"albedo": rng.uniform(0, 1, (n, 3)).astype(np.float32), "depth": 1000 + rng.normal(0, 0.01, n)}
        feats["albedo"][5, 1] = np.nan
        from mcrecon.methods.splat.bands import rows_sorted

        srt = rows_sorted(pos, h)
        for threads in ("1", "2"):
            import os
            os.environ["MCRECON_THREADS"] = threads
            try:
                got = round_sums(pos, val, w, h, 0, LUMINANCE_WEIGHTS.copy(), a if threads == "2" else None, feats,
                                 "test", srt)
            finally:
                os.environ.pop("MCRECON_THREADS")
            counts = np.zeros((h, w), np.int64)
            s1, s2 = np.zeros((h, w)), np.zeros((h, w))
            in_bands(_count_and_moments, (pos, val, 0, LUMINANCE_WEIGHTS.copy(), counts, s1, s2), pos, h)
            c1, c2 = channel_sums(pos, val, w, h)
            for x, y in zip(got, (counts, s1, s2, c1, c2)):
                np.testing.assert_array_equal(x, y)
        b.add(pos, feats, "test")
        for x, y in ((a.n, b.n), (a.shift, b.shift), (a.s1, b.s1), (a.s2, b.s2)):
            np.testing.assert_array_equal(x, y)


def test_gate_answers_as_the_full_feature_test():
    """The feature test's shortcut (means within the spreads pass without the slopes' term) answers as the
    full expression, on random pixel pairs near and at the boundary, with infinite variances."""
    import numba

    from mcrecon.methods.splat.kernels import _same_pixel_stats

    @numba.njit(cache=False)
    def gate(gs, fs, k2, pairs, out):
        for m in range(pairs.shape[0]):
            out[m] = _same_pixel_stats(gs, fs, pairs[m, 0], pairs[m, 1], pairs[m, 2], pairs[m, 3], k2)

    def full(fs, pairs, k2):  # the test without the shortcut, in array form: every pair, every component
        p, q = fs[pairs[:, 0], pairs[:, 1]], fs[pairs[:, 2], pairs[:, 3]]
        ax = np.abs(pairs[:, 3] - pairs[:, 1]).astype(float)[:, None]
        ay = np.abs(pairs[:, 2] - pairs[:, 0]).astype(float)[:, None]
        noise = k2 * (2.0 + 0.5 * (ax * ax + ay * ay))
        d = q[..., 0] - p[..., 0]
        t = ax * np.maximum(np.abs(p[..., 2]), np.abs(q[..., 2])) + ay * np.maximum(np.abs(p[..., 3]),
                                                                                   np.abs(q[..., 3]))
        t = t + np.sqrt(noise * np.maximum(p[..., 4], q[..., 4]))
        same = (pairs[:, 0] == pairs[:, 2]) & (pairs[:, 1] == pairs[:, 3])
        return same | (d * d <= k2 * (p[..., 1] + q[..., 1]) + t * t).all(axis=1)

    rng = np.random.default_rng(6)
    h, w, nf = 12, 14, 4
    fs = np.empty((h, w, nf, 5))
    fs[..., 0] = rng.normal(0, 1, (h, w, nf)) * rng.choice([0.0, 0.05, 1.0], (h, w, nf))
    fs[..., 1] = rng.exponential(0.01, (h, w, nf))
    fs[..., 2:4] = rng.normal(0, 0.1, (h, w, nf, 2))
    fs[..., 4] = fs[..., 1] / rng.integers(2, 40, (h, w, nf))
    fs[0, :4, 0, 1] = np.inf  # below two samples: nothing known
    fs[0, :4, 0, 4] = np.inf
    gs = np.zeros((h, w, 0, 4))  # the colour passes: only the features decide
    jj, ii = np.mgrid[:h, :w]
    pairs = np.array([(pj, pi, qj, qi) for pj, pi in zip(jj.ravel(), ii.ravel())
                      for qj in range(max(pj - 2, 0), min(pj + 3, h)) for qi in range(max(pi - 2, 0), min(pi + 3, w))],
                     np.int64)
    out = np.zeros(len(pairs), np.bool_)
    gate(gs, fs, 2.64 ** 2, pairs, out)
    np.testing.assert_array_equal(out, full(fs, pairs, 2.64 ** 2))
    assert 0.05 < out.mean() < 0.95  # both answers occur

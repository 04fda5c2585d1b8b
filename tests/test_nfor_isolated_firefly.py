"""nfor's default leaves out a brightness that rests on one sample no neighbour's sample confirms.

A lone firefly (one sample of 32 worth 10^4 times its neighbours') finds no
matching patch for the NL-means weights, so the regression keeps the pixel's
own value, and the confidence clamp around the pixel's mean keeps it too
(the pixel's own variance is the firefly's).  Seen on a Mitsuba scene: 1.87
where the reference is 0.007.
"""

from __future__ import annotations

import warnings

import numpy as np

import mcrecon
from mcrecon.core.samples import SampleSet
from mcrecon.core.stats import PixelStats
from mcrecon.methods.nfor.firefly import isolated_sample_bounds, leave_out_isolated

W, H, SPP = 22, 20, 32


def _dim_floor(seed=2, bright=None, highlight=None):
    """A dim grey floor (0.007 U[0.5, 1.5)) on a checker albedo, 32 spp; ``bright``: (row, col, value) of
    one sample; ``highlight``: (row, col) of a pixel whose every sample is 800 U[0.75, 1.25)."""
    rng = np.random.default_rng(seed)
    pos = np.repeat(np.stack(np.meshgrid(np.arange(W), np.arange(H)), -1).reshape(-1, 2), SPP, axis=0) \
        + rng.random((W * H * SPP, 2))
    n = pos.shape[0]
    px, py = np.floor(pos[:, 0]).astype(int), np.floor(pos[:, 1]).astype(int)
    albedo = np.where(((px // 3 + py // 3) % 2 == 0)[:, None], [0.7, 0.6, 0.5], [0.3, 0.35, 0.4])
    val = 0.01 * albedo * (0.5 + rng.random((n, 1)))
    normal = np.tile([0.0, 1.0, 0.0], (n, 1))
    if bright is not None:  # on a small object of its own (the pixel's normal differs from its neighbours')
        r, c, v = bright
        k = (py == r) & (px == c)
        val[np.flatnonzero(k)[5]] = v
        normal[k] = [0.6, 0.8, 0.0]
    if highlight is not None:
        r, c = highlight
        k = (py == r) & (px == c)
        val[k] = 800.0 * (0.75 + 0.5 * rng.random((int(k.sum()), 1)))
    feats = {"albedo": albedo, "normal": normal, "depth": 2.0 + 0.01 * pos[:, :1]}
    return SampleSet(pos, val, width=W, height=H, features=feats)


def _nfor(ss, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return mcrecon.reconstruct(ss, method=mcrecon.get_method("nfor", **kw))


def _clamped_without_the_bound(ss, paper):
    """The default's confidence clamp alone (tests/test_nfor.py's bit-for-bit recipe)."""
    from mcrecon.core.fill import mean_variance_policy
    from mcrecon.core.halves import split_halves
    from mcrecon.core.safeguard import albedo_divisor, confidence_clamp, safeguard_variance, sample_range_bounds
    from mcrecon.methods.nfor.method import channel_floor

    h = split_halves(ss, features="all")
    st = h.a.copy().merge(h.b)
    lo, hi = sample_range_bounds(st)
    d = albedo_divisor(st)
    v = safeguard_variance(channel_floor(mean_variance_policy(st), d), st.count, d)
    return confidence_clamp(paper, st.mean, v, 4.0, lo, hi)


def test_a_lone_firefly_that_no_neighbour_confirms_does_not_stay():
    ss = _dim_floor(bright=(9, 11, 70.0))
    paper = _nfor(ss, variant="paper")
    img = _nfor(ss)
    clamped = _clamped_without_the_bound(ss, paper)
    # the regression (no patch like the pixel's) and the clamp around its own mean keep most of it
    mean = PixelStats.from_samples(ss.positions, ss.values, width=W, height=H).mean[9, 11]
    assert (clamped[9, 11] > 0.5 * mean).all(), (clamped[9, 11], mean)
    # the default: at most the largest sample of its 8 neighbours (all below 0.0105)
    assert img[9, 11].max() <= 0.0105, img[9, 11]
    # nothing else moves
    other = np.ones((H, W), bool)
    other[9, 11] = False
    np.testing.assert_array_equal(img[other], clamped[other])
    np.testing.assert_array_equal(img, leave_out_isolated(clamped.copy(), PixelStats.from_samples(
        ss.positions, ss.values, width=W, height=H), 4.0))


def test_a_result_pooled_from_a_wide_window_stays_though_its_3x3_samples_missed():
    """A rare bright component (one sample in 80 worth 200) the pixel's 3 x 3 neighbours missed: a result
    that keeps at most half of the pixel's excess, or lies above its mean, comes from elsewhere and stays."""
    st = PixelStats.from_samples(*[np.array(a, float) for a in ([[0.5, 0.5], [0.5, 0.5], [0.5, 0.5],
                                                                  [1.5, 0.5], [1.5, 0.5], [1.5, 0.5]],
                                                                 [[200.0] * 3, [0.1] * 3, [0.12] * 3,
                                                                  [0.1] * 3, [0.11] * 3, [0.12] * 3])],
                                 width=2, height=1)
    # pixel 0: mean 66.74, its bound max(0.12, 0.11 + 4 se) = 0.17
    for value, moved in ((60.0, True), (30.0, False), (70.0, False)):
        img = np.zeros((1, 2, 3)) + 0.11
        img[0, 0] = value
        out = leave_out_isolated(img.copy(), st, 4.0)
        assert (out[0, 0] < 1.0).all() == moved, (value, out[0, 0])
        np.testing.assert_array_equal(out[0, 1], img[0, 1])


def test_a_one_pixel_highlight_whose_samples_agree_keeps_its_value():
    ss = _dim_floor(highlight=(9, 11))
    st = PixelStats.from_samples(ss.positions, ss.values, width=W, height=H)
    img = _nfor(ss)
    lo, hi = isolated_sample_bounds(st, 4.0)
    assert (hi[9, 11] > st.mean[9, 11]).all()  # the mean of its other samples + 4 se covers its mean
    np.testing.assert_array_equal(np.clip(img, lo, hi), img)  # the bound moves nothing in this image


def test_isolated_sample_bounds_equal_leaving_the_extreme_sample_out_by_brute_force():
    rng = np.random.default_rng(4)
    w, h = 7, 5
    pos = rng.uniform(0, [w, h], size=(w * h * 6, 2))
    pos = pos[~((pos[:, 0] >= 3) & (pos[:, 0] < 4) & (pos[:, 1] < 1))]  # one empty pixel
    val = rng.lognormal(0.0, 1.5, size=(pos.shape[0], 3))
    st = PixelStats.from_samples(pos, val, width=w, height=h)
    lo, hi = isolated_sample_bounds(st, 3.0)
    px, py = np.floor(pos[:, 0]).astype(int), np.floor(pos[:, 1]).astype(int)
    for i in range(h):
        for j in range(w):
            v = val[(py == i) & (px == j)]
            nb = (np.abs(py - i) <= 1) & (np.abs(px - j) <= 1) & ~((py == i) & (px == j))
            if len(v) < 3 or not nb.any():
                assert np.isinf(hi[i, j]).all() and np.isinf(lo[i, j]).all()
                continue
            for c in range(3):
                x = np.sort(v[:, c])
                for rest, sign, got, nbx in ((x[:-1], 1, hi, val[nb, c].max()), (x[1:], -1, lo, val[nb, c].min())):
                    own = rest.mean() + sign * 3.0 * rest.std(ddof=1) / np.sqrt(len(rest))
                    want = max(nbx, own) if sign > 0 else min(nbx, own)
                    np.testing.assert_allclose(got[i, j, c], want, rtol=1e-9)

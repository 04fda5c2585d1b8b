"""The planners' compiled kernels against the scipy/numpy formulas they replace, bit for bit.

mcrecon.filters.box (scipy's uniform_filter and a maximum filter's threshold), the
rare-component mask and neighbourhood variance of mcrecon.core.safeguard and the
stratification gain of mcrecon.core.strata, fill_lowest's level search (mcrecon.core.nets): the adaptive plans read them every
round, so a last-bit difference would move which samples a pinned run draws.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from mcrecon.core.safeguard import (RARE_EPS, neighbourhood_mean_variance, rare_component_mask,
                                    rare_component_variance)
from mcrecon.filters.box import box_any, box_mean


def _same(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and np.array_equal(a.view(np.uint8), b.view(np.uint8))


def _planes(rng, h, w, c):
    a = rng.standard_normal((h, w, c)) * 10.0 ** rng.integers(-6, 6, (h, w, c))
    a[rng.random(a.shape) < 0.2] = 0.0
    return a


@pytest.mark.parametrize("mode", ["constant", "nearest"])
def test_box_mean_is_scipys_uniform_filter(mode):
    rng = np.random.default_rng(3)
    for h, w, c in [(1, 1, 1), (1, 7, 3), (9, 1, 2), (4, 6, 3), (23, 31, 3), (40, 17, 1)]:
        a = _planes(rng, h, w, c)
        for r in (1, 2, 3):
            size = 2 * r + 1
            assert _same(box_mean(a, r, mode), ndimage.uniform_filter(a, size=(size, size, 1), mode=mode))
            assert _same(box_mean(a[..., 0], r, mode), ndimage.uniform_filter(a[..., 0], size=size, mode=mode))
    flags = rng.random((12, 9, 3)) < 0.4        # a boolean plane is read as 0 / 1
    assert _same(box_mean(flags, 2, mode), ndimage.uniform_filter(flags.astype(np.float64), size=(5, 5, 1), mode=mode))
    with pytest.raises(ValueError, match="mode"):
        box_mean(flags, 2, "reflect")


@pytest.mark.parametrize("box", [box_mean, box_any])
def test_box_refuses_a_negative_radius_and_a_line(box):
    """A negative half-size would sum an empty window (box_mean: -0 everywhere, box_any: nothing set) and a
    line has no film axes: both refused, naming the function."""
    with pytest.raises(ValueError, match=f"{box.__name__}: radius -1"):
        box(np.ones((4, 5)) > 0, -1)
    with pytest.raises(ValueError, match=rf"{box.__name__}: \(H, W\)"):
        box(np.ones(5) > 0, 1)
    assert np.array_equal(box(np.eye(4) > 0, 0), np.eye(4))     # radius 0: each pixel alone


def test_box_any_is_the_maximum_filter_over_the_threshold():
    rng = np.random.default_rng(4)
    for h, w, c in [(1, 1, 1), (1, 9, 2), (8, 1, 3), (30, 21, 3)]:
        x = rng.standard_normal((h, w, c))
        x[rng.random(x.shape) < 0.1] = np.inf
        for r in (1, 2, 4):
            ref = ndimage.maximum_filter(x, size=(2 * r + 1, 2 * r + 1, 1), mode="nearest") > 1.7
            assert np.array_equal(box_any(x > 1.7, r), ref)
            assert np.array_equal(box_any(x[..., 0] > 1.7, r), ref[..., 0])


# ---- the numpy formulas the compiled ones replaced (the reference)

def _nmv_reference(var_mean, count, radius=2, divisor=None):
    v = np.asarray(var_mean, dtype=np.float64)
    d2 = 1.0 if divisor is None else np.asarray(divisor, dtype=np.float64) ** 2
    n = count.astype(np.float64)[..., None]
    has = n > 0
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        per_sample = np.where(has & np.isfinite(v), v * n / d2, 0.0)
    size = (2 * radius + 1, 2 * radius + 1, 1)
    num = ndimage.uniform_filter(per_sample, size=size, mode="constant")
    den = ndimage.uniform_filter(np.broadcast_to(has & np.isfinite(v), v.shape).astype(np.float64), size=size,
                                 mode="constant")
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        pooled = num / den * d2 / n
    return np.where(has & (den > 0), np.maximum(pooled, 0.0), v)


def _mask_reference(var_mean, mean, count, radius=2, threshold=5.0):
    v = np.asarray(var_mean, dtype=np.float64)
    m = np.asarray(mean, dtype=np.float64)
    n = count.astype(np.float64)[..., None]
    with np.errstate(invalid="ignore", over="ignore"):
        rel = np.where((n > 0) & np.isfinite(v) & np.isfinite(m), v * n / (m * m + RARE_EPS), 0.0)
    return ndimage.maximum_filter(rel, size=(2 * radius + 1, 2 * radius + 1, 1), mode="nearest") > threshold


def _film(rng, h, w, c=3, *, holes=0.1, bad=0.02):
    count = rng.integers(0, 9, (h, w))
    count[rng.random((h, w)) < holes] = 0
    mean = rng.gamma(0.5, 1.0, (h, w, c))
    mean[rng.random((h, w, c)) < 0.2] = 0.0
    var = rng.gamma(0.3, 1.0, (h, w, c)) ** 3 / np.maximum(count, 1)[..., None]
    var[rng.random(var.shape) < 0.1] = 0.0
    var[rng.random(var.shape) < bad] = np.inf
    var[rng.random(var.shape) < bad] = np.nan
    return var, mean, count


def test_neighbourhood_mean_variance_bit_for_bit():
    rng = np.random.default_rng(5)
    for h, w in [(1, 1), (3, 40), (37, 29), (64, 64)]:
        var, mean, count = _film(rng, h, w)
        for r in (1, 2):
            assert _same(neighbourhood_mean_variance(var, count, radius=r), _nmv_reference(var, count, r))
        div = rng.uniform(0.05, 2.0, (h, w, 3))
        assert _same(neighbourhood_mean_variance(var, count, divisor=div), _nmv_reference(var, count, divisor=div))
    var, _, count = _film(rng, 8, 8)
    with pytest.raises(ValueError, match="neighbourhood_mean_variance"):
        neighbourhood_mean_variance(var[..., 0], count)


def test_rare_component_mask_and_variance_bit_for_bit():
    rng = np.random.default_rng(6)
    for h, w in [(1, 1), (2, 33), (41, 27), (64, 64)]:
        var, mean, count = _film(rng, h, w)
        for thr in (3.0, 5.0):
            got = rare_component_mask(var, mean, count, threshold=thr)
            assert np.array_equal(got, _mask_reference(var, mean, count, threshold=thr))
            assert got.any() and not got.all()
            ref = np.where(got, np.maximum(var, _nmv_reference(var, count)), var)
            assert _same(rare_component_variance(var, mean, count, threshold=thr), ref)
    # a ratio inf / inf (values near the float64 range) is NaN: the maximum filter's answer is kept
    var, mean, count = _film(rng, 16, 16, bad=0.0)
    var[3, 4, 1], mean[3, 4, 1], count[3, 4] = 1e308, 1e200, 4
    assert np.array_equal(rare_component_mask(var, mean, count), _mask_reference(var, mean, count))


def _gain_reference(mean_a, mean_b, n_a, n_b, sample_variance, radius=2, floor=1.0 / 32.0):
    ok = (n_a > 0) & (n_b > 0)
    inv = np.where(ok, 1.0 / np.maximum(n_a, 1) + 1.0 / np.maximum(n_b, 1), 0.0)
    d2 = np.where(ok, np.sum((0.5 * (mean_a - mean_b)) ** 2, axis=2), 0.0)
    ref = np.sum(np.asarray(sample_variance, dtype=np.float64), axis=2) * inv * 0.25
    size = 2 * int(radius) + 1
    num = ndimage.uniform_filter(d2, size=size, mode="constant")
    den = ndimage.uniform_filter(ref, size=size, mode="constant")
    den2 = ndimage.uniform_filter(ref * ref, size=size, mode="constant")
    known = den > 1e-300
    g = np.divide(num, den, out=np.ones_like(num), where=known)
    rel_sd = np.divide(np.sqrt(2.0 * np.maximum(den2, 0.0) / (size * size)), den, out=np.zeros_like(den),
                       where=known)
    return np.clip(g * (1.0 + 2.0 * rel_sd), floor, 1.0)


def test_prefix_halves_and_gain_bit_for_bit():
    from mcrecon.core.strata import PrefixHalves, halves_gain

    rng = np.random.default_rng(7)
    for h, w, c in [(1, 1, 3), (5, 33, 3), (40, 31, 3), (24, 24, 1)]:
        ph = PrefixHalves(w, h, c)
        var = np.zeros((h, w, c))
        for spp in (1, 1, 2, 3, 4, 5):          # uneven rounds: powers of two and the counts between
            n = rng.integers(0, spp + 1, h * w)
            pix = np.repeat(np.arange(h * w), n)
            pos = np.stack([pix % w + rng.random(pix.size), pix // w + rng.random(pix.size)], 1)
            val = rng.gamma(0.4, 1.0, (pix.size, c)) * (rng.random((pix.size, 1)) < 0.3)
            ph.add(pos, val)
        mean_a, mean_b, n_a, n_b = ph.halves()
        # the numpy formulas of the halves
        k = ph.counter
        pow2 = (k >= 2) & ((k & (k - 1)) == 0)
        s, cnt = ph._sums, ph._counts
        na = np.where(pow2, cnt[0] + cnt[1], cnt[0])
        nb = np.where(pow2, cnt[2], cnt[1])
        ma = np.where(pow2[:, None], s[0] + s[1], s[0]) / np.maximum(na, 1)[:, None]
        mb = np.where(pow2[:, None], s[2], s[1]) / np.maximum(nb, 1)[:, None]
        assert _same(mean_a, ma.reshape(h, w, c)) and _same(mean_b, mb.reshape(h, w, c))
        assert _same(n_a, na.reshape(h, w)) and _same(n_b, nb.reshape(h, w))
        var = rng.gamma(0.5, 1.0, (h, w, c)) * (rng.random((h, w, 1)) < 0.8)
        assert ((n_a > 0) & (n_b > 0)).any()
        for r, floor in ((2, 1.0 / 32.0), (1, 0.1)):
            got = halves_gain(mean_a, mean_b, n_a, n_b, var, radius=r, floor=floor)
            assert _same(got, _gain_reference(mean_a, mean_b, n_a, n_b, var, r, floor))
            assert _same(ph.gain(var, radius=r, floor=floor), got)
        # float counts (core.halves hands its halves' counts as they are)
        assert _same(halves_gain(mean_a, mean_b, n_a.astype(float), n_b.astype(float), var),
                     _gain_reference(mean_a, mean_b, n_a.astype(float), n_b.astype(float), var))


def test_gain_refuses_planes_of_other_shapes():
    """The compiled pass reads every plane at the means' indices: a variance of one channel for three-channel
    means, or counts of another film, would be read past its end (numba checks no bounds)."""
    from mcrecon.core.strata import halves_gain

    m = np.ones((6, 5, 3))
    n = np.full((6, 5), 2)
    none = m[..., :0]
    for args in ((m, m, n, n, m[..., :1]), (m, m[:, :4], n, n, m), (m, m, n[:5], n, m), (none, none, n, n, none)):
        with pytest.raises(ValueError, match="halves_gain"):
            halves_gain(*args)
    assert _same(halves_gain(m, m, n, n, m), _gain_reference(m, m, n, n, m))


@pytest.mark.parametrize("h, w", [(0, 5), (5, 0)])
def test_prefix_halves_of_an_empty_film(h, w):
    """A film without pixels has halves (H, W, C) and (H, W) and a gain (H, W), as the other plan planes
    (a reshape to an unknown channel count of no elements failed)."""
    from mcrecon.core.strata import PrefixHalves

    ph = PrefixHalves(w, h, 3)
    mean_a, mean_b, n_a, n_b = ph.halves()
    assert mean_a.shape == mean_b.shape == (h, w, 3) and n_a.shape == n_b.shape == (h, w)
    assert ph.gain(np.zeros((h, w, 3))).shape == (h, w)


def test_fill_lowest_level_search():
    from mcrecon.core.nets import _given_sum, fill_lowest

    rng = np.random.default_rng(8)
    for _ in range(20):
        c = rng.integers(0, 40, 500)
        cap = c + rng.integers(0, 9, 500)
        room = np.maximum(cap - c, 0)
        for t in (-3, 0, 7, 25, 41, 60):
            assert _given_sum(c, room, t) == int(np.minimum(np.maximum(t - c, 0), room).sum())
        n = int(rng.integers(0, room.sum() + 1))
        for top in (cap, None):
            got = fill_lowest(c.reshape(20, 25), n, np.random.default_rng(1),
                              cap=None if top is None else top.reshape(20, 25)).ravel()
            rm = np.maximum((np.full(c.size, np.iinfo(np.int64).max // 4) if top is None else top) - c, 0)
            # brute force: the highest level whose fill fits, by a scan; the rest one each at that level
            level = int(c.min())
            while int(np.minimum(np.maximum(level + 1 - c, 0), rm).sum()) <= n:
                level += 1
            fill = np.minimum(np.maximum(level - c, 0), rm)
            extra = got - fill
            assert got.sum() == n and set(np.unique(extra)) <= {0, 1}
            assert ((c + fill)[extra == 1] == level).all() and (fill[extra == 1] < rm[extra == 1]).all()

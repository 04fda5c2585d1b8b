"""Per-pixel error estimates without a reference (mcrecon.methods.auto.estimates): SURE and dual buffers.

The accuracy statistic of every test is the ratio
``R = sum_pixels(estimated MSE) / sum_pixels(true squared error)`` of one
seed; its mean over seeds must be 1 (the estimators are unbiased), to
within a tolerance derived from the spread of R over seeds.
"""

from __future__ import annotations

import numpy as np
import pytest

from mcrecon import McreconWarning, PixelStats, SampleSet
from mcrecon.methods.auto.estimates import (cross_validation_mse, dual_buffer_mse, dual_buffer_variance,
    gaussian_centre_weights, relative_denominator, sure, sure_filter_bank)
from mcrecon.core.halves import split_halves, split_labels
from mcrecon.methods.gem import filter_bank, final_sigmas
from mcrecon.core.fill import mean_variance_policy
from mcrecon.renderers.scenes import reference_image, render_uniform


# ------------------------------------------------------------------ exactness
def _stats_by_copies(src):
    """The reference split: labels, then each half's samples (features with them) copied into its own
    statistics."""
    from mcrecon.core.halves import Halves
    from mcrecon.core.features import usable_layout
    h = Halves.empty(src.width, src.height, tuple(src.channels), features=usable_layout(src.features) or None)
    for ch in src.iter_chunks(with_round=False, chunk_size=97, features=src.feature_names):
        h._add_by_copies(ch.positions, ch.values, features=ch.features)
    return h


@pytest.mark.parametrize("order", ["pixel", "shuffled", "interleaved"])
def test_one_pass_split_is_bit_identical_to_splitting_by_copies(order, monkeypatch):
    """The compiled one-pass split (labels and both halves' Welford/Chan statistics at once, pixel
    ranges merged in parallel) gives the statistics, bit for bit, of labelling the stream and adding
    each half's samples with PixelStats.add -- for a renderer's pixel-by-pixel order, a shuffled
    stream (runs of one) and two pixels interleaved (a half's run spanning the other pixel), chunk
    boundaries included, for 1 and 3 threads and the runs found in blocks of any size; the features
    (of other dtypes and widths) split with the colour's runs."""
    from mcrecon import SampleSet
    rng = np.random.default_rng(4)
    w, h, spp = 13, 7, 9
    pix = np.repeat(np.arange(w * h), spp)
    if order == "shuffled":
        pix = rng.permutation(pix)
    elif order == "interleaved":
        pix = np.stack([pix[: pix.size // 2], pix[pix.size // 2:][: pix.size // 2]], axis=1).ravel()
    pos = np.stack([pix % w + rng.random(pix.size) * 0.99, pix // w + rng.random(pix.size) * 0.99], axis=1)
    val = rng.standard_normal((pix.size, 3)) * 1e3 + 1e6  # Welford territory
    feats = {"albedo": rng.random((pix.size, 3)).astype(np.float32), "depth": rng.random(pix.size) * 1e3 + 1e6}
    ss = SampleSet(pos.astype(np.float32), val.astype(np.float32), width=w, height=h, features=feats)
    ref = _stats_by_copies(ss)
    from mcrecon.core.halves import Halves
    monkeypatch.setattr("mcrecon.core.halves._PARALLEL_MIN_SAMPLES", 0)  # pixel ranges in parallel at any size
    for threads, block in (("1", 1 << 16), ("3", 1 << 16), ("3", 5), ("1", 1)):
        monkeypatch.setenv("MCRECON_THREADS", threads)
        monkeypatch.setattr("mcrecon.core.halves._RUN_BLOCK", block)  # a batch's runs found in blocks
        new = Halves.empty(w, h, ss.channels, features={"albedo": 3, "depth": 1})
        for ch in ss.iter_chunks(with_round=False, chunk_size=97, features=ss.feature_names):
            new.add(ch.positions, ch.values, features=ch.features)
        for a, b in ((ref.a, new.a), (ref.b, new.b)):
            for x, y in [(a, b)] + [(a.features[k], b.features[k]) for k in feats]:
                for f in ("count", "mean", "m2", "min", "max"):
                    np.testing.assert_array_equal(getattr(x, f), getattr(y, f), err_msg=f)
                assert x.dtype == y.dtype
        np.testing.assert_array_equal(ref.counter, new.counter)


def test_split_with_non_finite_values_applies_the_policy_per_half():
    rng = np.random.default_rng(5)
    pos = rng.random((400, 2)) * [5, 4]
    val = rng.random((400, 2))
    val[::37, 1] = np.nan
    ss = SampleSet(pos, val, width=5, height=4)
    with pytest.warns(McreconWarning, match=r"11 sample\(s\) with NaN or Inf dropped"):
        hv = split_halves(ss)
    with pytest.warns(McreconWarning, match="dropped"):  # the reference path drops them per chunk and half
        ref = _stats_by_copies(ss)
    np.testing.assert_array_equal(hv.a.mean, ref.a.mean)
    assert hv.a.n_dropped + hv.b.n_dropped == 11


def test_sure_filter_bank_values_and_weights_are_gems_filter_bank():
    """sure_filter_bank filters only what SURE needs, by the same jobs: bit-identical values and
    weights to mcrecon.methods.gem.filter_bank (full and masked images)."""
    rng = np.random.default_rng(6)
    for empty in (0.0, 0.15):
        y = rng.random((23, 31, 3)) ** 3
        v = rng.random((23, 31, 3)) * 0.01
        count = (rng.random((23, 31)) >= empty).astype(np.int64) * 3
        y[count == 0] = 0.0
        v[count == 0] = 0.0
        sb = sure_filter_bank(y, v, count, final_sigmas(5))
        fb = filter_bank(y, v, count, final_sigmas(5), per_channel=False)
        for k in range(fb.n_scales):
            np.testing.assert_array_equal(sb.values[k], fb.values[k])
            np.testing.assert_array_equal(sb.weight[k], fb.weight[k])
            s = sure(y, v, fb.values[k], sb.centre_weight[k])
            s = np.where((fb.weight[k] <= 0)[..., None], np.inf, np.where((count == 0)[..., None], np.nan, s))
            np.testing.assert_array_equal(sb.sure[k], s)


def test_relative_denominator_median_is_ndimages():
    from scipy import ndimage
    rng = np.random.default_rng(7)
    y = rng.standard_normal((21, 34, 3))
    y[rng.random(y.shape) < 0.3] = 0.5  # ties
    v = rng.random(y.shape) * 0.1
    q = np.maximum(y * y - v, 0.0)
    ref = np.maximum(ndimage.median_filter(q, size=(3, 3, 1), mode="nearest"), q) + 0.01
    np.testing.assert_array_equal(relative_denominator(y, v, eps=0.01), ref)
    from mcrecon.methods.auto.estimates import _excess_square
    y[0, 0], v[0, 1], v[0, 2] = np.nan, np.nan, y[0, 2, 0] ** 2
    np.testing.assert_array_equal(_excess_square(y, v), np.maximum(y * y - v, 0.0))


def test_leave_one_out_denominator_ignores_the_pixels_own_samples():
    from mcrecon.methods.auto.estimates import relative_denominator_loo
    rng = np.random.default_rng(8)
    y = rng.random((6, 7, 2))
    v = np.zeros_like(y)
    d = relative_denominator_loo(y, v, eps=0.01)
    y2 = y.copy()
    y2[3, 3] = 100.0
    d2 = relative_denominator_loo(y2, v, eps=0.01)
    assert np.array_equal(d[3, 3], d2[3, 3])
    nb = np.delete((y * y)[2:5, 2:5].reshape(9, 2), 4, axis=0)
    np.testing.assert_allclose(d[3, 3], np.median(nb, axis=0) + 0.01, rtol=1e-15)


def test_leave_one_out_denominator_equals_the_median_of_the_sorted_neighbours_by_brute_force():
    """Bit for bit: the median of the 8 edge-repeated neighbours with samples (their sorted order as
    the stable sort leaves it, NaN where it arrived), plus eps; ties, zeros, NaN and empty pixels, so both
    the network (full neighbourhoods without NaN) and the sort are exercised."""
    from mcrecon.methods.auto.estimates import relative_denominator_loo
    rng = np.random.default_rng(9)
    h, w = 23, 70  # two row blocks
    y = rng.standard_normal((h, w, 3))
    y[rng.random(y.shape) < 0.2] = 0.5  # ties
    y[rng.random(y.shape) < 0.01] = np.nan
    v = rng.random(y.shape) * 0.3
    count = rng.integers(0, 40, (h, w))
    q = np.maximum(y * y - v, 0.0)
    got = relative_denominator_loo(y, v, count, eps=0.01)
    assert (q == 0).any() and ((count > 0) & (np.roll(count, 1, 0) > 0)).any()
    for i in range(h):
        for j in range(w):
            for c in range(3):
                nb = []
                for di in (-1, 0, 1):
                    for dj in (-1, 0, 1):
                        a, b = min(max(i + di, 0), h - 1), min(max(j + dj, 0), w - 1)
                        if (di or dj) and count[a, b] > 0:
                            nb.append(q[a, b, c])
                s = []
                for x in nb:  # insertion sort: a NaN stops no comparison
                    k = len(s)
                    while k > 0 and s[k - 1] > x:
                        k -= 1
                    s.insert(k, x)
                n = len(s)
                m = 0.0 if n == 0 else s[n // 2] if n % 2 else 0.5 * (s[n // 2 - 1] + s[n // 2])
                np.testing.assert_array_equal(got[i, j, c], m + 0.01)


def test_centre_weights_are_the_filter_banks_own_weights():
    """w_ii from gaussian_centre_weights equals the response of filter_bank to a unit impulse at i
    (masking and renormalisation included): exact, not approximated."""
    rng = np.random.default_rng(0)
    h, w = 9, 11
    count = rng.integers(0, 3, (h, w))
    count[4, 5] = 2
    sig = final_sigmas(3)
    cw = gaussian_centre_weights(count, sig)
    for i, j in ((4, 5), (0, 0), (8, 10)):
        if count[i, j] == 0:
            continue
        e = np.zeros((h, w, 1))
        e[i, j] = 1.0
        bank = filter_bank(e, np.zeros((h, w, 1)), count, sig)
        for k in range(len(sig)):
            assert bank.values[k + 1][i, j, 0] == pytest.approx(cw[k][i, j], rel=1e-12, abs=1e-15)


def test_sure_of_the_pixel_filter_is_its_variance():
    y = np.random.default_rng(1).random((4, 5, 3))
    v = np.full((4, 5, 3), 0.3)
    np.testing.assert_allclose(sure(y, v, y, 1.0), v)


def test_dual_buffer_identity_is_exact():
    rng = np.random.default_rng(2)
    a, b, mu = rng.random(100), rng.random(100), rng.random(100)
    lhs = ((a + b) / 2 - mu) ** 2
    np.testing.assert_allclose(dual_buffer_mse(a, b, (a - mu) ** 2, (b - mu) ** 2), lhs, rtol=1e-12, atol=1e-15)


def test_split_alternates_within_pixels_and_is_stream_invariant():
    rng = np.random.default_rng(3)
    pos = rng.random((1000, 2)) * [7, 5]
    c1 = np.zeros(35, np.int64)
    whole = split_labels(pos, 7, 5, c1)
    c2 = np.zeros(35, np.int64)
    parts = np.concatenate([split_labels(pos[:123], 7, 5, c2), split_labels(pos[123:], 7, 5, c2)])
    np.testing.assert_array_equal(whole, parts)
    pix = np.floor(pos[:, 1]).astype(int) * 7 + np.floor(pos[:, 0]).astype(int)
    for p in range(35):
        lab = whole[pix == p]
        assert abs(int(lab.sum()) * 2 - lab.size) <= 1  # halves differ by at most one sample


def test_relative_denominator_keeps_a_dark_pixel_dark_beside_a_bright_edge():
    y = np.zeros((9, 9, 1))
    y[:, 5:] = 500.0
    den = relative_denominator(y, np.zeros_like(y), eps=0.01)
    assert den[4, 4, 0] == pytest.approx(0.01) and den[4, 5, 0] == pytest.approx(500.0 ** 2 + 0.01)


# ------------------------------------------------------------------ accuracy
def _stripes(w=64, h=48):
    """A procedural scene with an exact reference: smooth gradient, a sharp step, fine stripes.
    Samples: reference + Gaussian noise whose sigma varies over the image (heteroscedastic)."""
    x = (np.arange(w) + 0.5) / w
    yy = (np.arange(h) + 0.5) / h
    X, Y = np.meshgrid(x, yy)
    ref = 0.2 + 0.6 * X[..., None] * np.array([1.0, 0.8, 0.6])
    ref = ref + (X > 0.6)[..., None] * 0.5
    ref = ref + ((Y < 0.3) * (np.sin(40 * X) > 0))[..., None] * 0.3
    sigma = np.broadcast_to(0.1 + 0.5 * Y[..., None], ref.shape).copy()
    return ref, sigma


def _procedural_samples(ref, sigma, spp, seed):
    rng = np.random.default_rng(seed)
    h, w, c = ref.shape
    pix = np.repeat(np.arange(h * w), spp)
    pos = np.stack([pix % w + rng.random(pix.size), pix // w + rng.random(pix.size)], axis=1)
    val = ref.reshape(-1, c)[pix] + sigma.reshape(-1, c)[pix] * rng.standard_normal((pix.size, c))
    return pos, val


def _sure_ratios(make, seeds, sigmas):
    """Per seed and scale: sum of SURE / sum of the true squared error."""
    out = []
    for seed in seeds:
        pos, val, ref, w, h = make(seed)
        st = PixelStats.from_samples(pos, val, width=w, height=h)
        v = mean_variance_policy(st)
        sb = sure_filter_bank(st.mean, v, st.count, sigmas)
        out.append([float(np.sum(sb.sure[k]) / np.sum((sb.values[k] - ref) ** 2)) for k in range(len(sb.values))])
    return np.array(out)


def _make_procedural(spp):
    ref, sigma = _stripes()

    def make(seed):
        pos, val = _procedural_samples(ref, sigma, spp, seed)
        return pos, val, ref, ref.shape[1], ref.shape[0]
    return make


def _make_scene(name, size, spp):
    ref = reference_image(name, size, size)

    def make(seed):
        b = render_uniform(name, width=size, height=size, spp=spp, seed=seed)
        return b.positions, b.values, ref, size, size
    return make


def _check(ratios):
    """Mean over seeds within 10 % of 1 (the issue's target) and within 4 standard errors + 2 % of 1.

    The 2 % allows for what is not sampling noise: a ratio of sums is not the sum of ratios (its
    bias is O(spread^2 / seeds)), and the fill-in policy for pixels with < 2 samples."""
    mean = ratios.mean(axis=0)
    se = ratios.std(axis=0, ddof=1) / np.sqrt(ratios.shape[0])
    assert np.all(np.abs(mean - 1) <= 0.10), (mean, se)
    assert np.all(np.abs(mean - 1) <= 4 * se + 0.02), (mean, se)
    return mean, se


def test_sure_is_unbiased_on_a_procedural_scene_reduced():
    """Procedural stripes, 8 spp, 6 seeds, the box and 4 Gaussian scales.

    Measured spread of R over seeds (MCRECON_FULL run, 64 seeds): std 0.01-0.03 per scale,
    so the standard error of the 6-seed mean is <= 0.013 and a 10 % tolerance is > 7 standard
    errors; the test asserts |mean - 1| <= 0.10 and <= 4 standard errors + 2 % (see _check)."""
    _check(_sure_ratios(_make_procedural(8), range(6), final_sigmas(4)))


@pytest.mark.slow
def test_sure_is_unbiased_on_builtin_and_procedural_scenes(full_run):
    """SURE summed over the image against the true squared error, every scale of GEM's final bank.

    Scenes: the procedural stripes (Gaussian noise) and the built-in soft_shadow and depth_of_field
    (renderer noise, 16 spp, 48x48).  Measured spread of R (std over seeds): procedural 0.01-0.03,
    soft_shadow 0.02-0.08, depth_of_field 0.02-0.06 (the large scales, whose true error is mostly
    bias, have the smallest relative spread).  Full run: 64 seeds (standard error <= 0.01);
    reduced: 12 seeds (<= 0.025).  Asserted: |mean - 1| <= 10 % and <= 4 standard errors + 2 % (measured means 0.99-1.01)."""
    n = 64 if full_run else 12
    for make in (_make_procedural(8), _make_scene("soft_shadow", 48, 16), _make_scene("depth_of_field", 48, 16)):
        _check(_sure_ratios(make, range(n), final_sigmas(8)))


def _dual_ratios(make, seeds):
    """Per seed: [variance part / true var of the half-average, CV estimate / true error] for the box
    filter of the halves (unbiased: E[A] = E[B] = mu, so all its error is variance)."""
    out = []
    for seed in seeds:
        pos, val, ref, w, h = make(seed)
        hv = split_halves(SampleSet(pos, val, width=w, height=h))
        a, b = hv.a.mean, hv.b.mean
        true = np.sum(((a + b) / 2 - ref) ** 2)
        var = np.sum(dual_buffer_variance(a, b))
        cv = np.sum(dual_buffer_mse(a, b, cross_validation_mse(a, b, mean_variance_policy(hv.b)),
                                    cross_validation_mse(b, a, mean_variance_policy(hv.a))))
        out.append([var / true, cv / true])
    return np.array(out)


def test_dual_buffer_variance_part_is_unbiased_reduced():
    """Unbiased reconstruction (the pixel mean of each half): the variance part (A-B)^2/4 and the
    bias-inclusive cross-validation estimate against the true error, procedural scene, 8 spp, 8 seeds.
    Measured spread of R: std 0.02 (variance part), 0.03 (CV); tolerance 10 % (> 9 standard errors)."""
    _check(_dual_ratios(_make_procedural(8), range(8)))


@pytest.mark.slow
def test_dual_buffer_variance_part_is_unbiased_on_scenes(full_run):
    """As above on soft_shadow (48x48, 16 spp).  Spread of R: std ~0.03; full 64 seeds, reduced 12.
    What the variance part misses: a biased reconstruction's E[F] - mu (tested in test_auto:
    a blur's (A-B)^2/4 is far below its true error, the cross-validation estimate is not)."""
    n = 64 if full_run else 12
    _check(_dual_ratios(_make_scene("soft_shadow", 48, 16), range(n)))


def test_variance_part_misses_the_bias_and_cross_validation_sees_it():
    """A strong blur of each half: (A-B)^2/4 sees only the variance; the cross-validation
    estimate (A - y_B)^2 - v_B sees bias too (sum within 15 % over 4 seeds: bias dominates)."""
    from scipy import ndimage
    ref, sigma = _stripes()
    r_var, r_cv = [], []
    for seed in range(4):
        pos, val = _procedural_samples(ref, sigma, 8, seed)
        hv = split_halves(SampleSet(pos, val, width=ref.shape[1], height=ref.shape[0]))
        blur = lambda x: ndimage.gaussian_filter(x, (4, 4, 0), mode="nearest")  # noqa: E731
        a, b = blur(hv.a.mean), blur(hv.b.mean)
        true = np.sum(((a + b) / 2 - ref) ** 2)
        r_var.append(np.sum(dual_buffer_variance(a, b)) / true)
        cv = dual_buffer_mse(a, b, cross_validation_mse(a, hv.b.mean, mean_variance_policy(hv.b)),
                             cross_validation_mse(b, hv.a.mean, mean_variance_policy(hv.a)))
        r_cv.append(np.sum(cv) / true)
    assert np.mean(r_var) < 0.2
    assert abs(np.mean(r_cv) - 1) < 0.15


def test_median_networks_sort_every_zero_one_input():
    """The 0-1 principle: a compare-exchange network that selects correctly on every input of zeros and
    ones does so on every input; median9 and middle8 (mcrecon.filters.order) checked on all of them."""
    import itertools
    import numba
    from mcrecon.filters.order import median9, middle8

    @numba.njit
    def both(a):
        return median9(a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7], a[8]), \
            middle8(a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7])

    for bits in itertools.product((0.0, 1.0), repeat=9):
        a = np.array(bits)
        m9, m8 = both(a)
        s9, s8 = np.sort(a), np.sort(a[:8])
        assert m9 == s9[4] and m8 == (s8[3], s8[4]), bits

"""auto's heavy vote (mcrecon/methods/auto/onesided.py): where most pixels vote with one-sided tails of their
own (a light that about a sample in ten finds), the global prior reads the vote as thin; exponential noise
on a texture, Gaussian noise about a dark mean and a ring of rare samples on exact zeros do not trigger it."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import mcrecon
from mcrecon.core.metrics import relative_mse
from mcrecon.core.samples import SampleSet
from mcrecon.core.stats import PixelStats
from mcrecon.errors import McreconWarning
from mcrecon.methods.auto import onesided
from mcrecon.methods.auto.onesided import HEAVY_VOTE, ONE_SIDED, heavy_vote, one_sided, threshold

from test_auto import _caustic_ring_samples, _samples, _scene_blobs
from test_auto_regression_proxy import _scene as _textured_exponential
from test_auto_thin_vote import _inputs


def test_one_sided_is_its_numpy_statement_per_pixel_and_channel():
    rng = np.random.default_rng(3)
    st = PixelStats.from_source(SampleSet(np.repeat(np.stack([np.arange(6) + 0.5, np.full(6, 0.5)], 1), 8, 0),
                                          rng.exponential(size=(48, 3)) ** 3, width=6, height=1))
    lo, hi, y = st.min, st.max, st.mean
    want = np.array([[any(hi[0, j, c] - y[0, j, c] > ONE_SIDED * (y[0, j, c] - lo[0, j, c]) and y[0, j, c] > lo[0, j, c]
                          for c in range(3)) for j in range(6)]])
    assert want.any() and not want.all()
    np.testing.assert_array_equal(one_sided(st), want)
    assert one_sided(PixelStats.from_moments(y, st.mean_variance(), st.count)) is None


def test_equal_samples_are_not_one_sided_where_their_mean_rounds_below_them():
    """Every sample of a pixel the same: the running mean can round below the minimum, and ``max - mean`` then
    exceeds ``ONE_SIDED (mean - min)`` < 0 (half of an hdr scene's dim background counted, and its vote read as
    heavy: auto 0.36 -> 169 x the pixel mean's error on the tuning hdr-13)."""
    vals = np.repeat([[0.7, 0.7, 2.2e-4], [1.0 / 3.0, 0.3, 0.1]], [32, 16], axis=0)
    pos = np.repeat([[0.5, 0.5], [1.5, 0.5]], [32, 16], axis=0)
    st = PixelStats.from_source(SampleSet(pos, vals, width=2, height=1))
    assert (st.mean < st.min).any()  # the case: a mean rounded below its equal samples
    assert not one_sided(st).any()


def test_the_threshold_scales_as_the_exponential_ratio_above_32_samples():
    """``ONE_SIDED`` at 32 samples and fewer (the same bits there), ``ONE_SIDED r(n) / r(32)`` above, ``r(n) =
    (H_n - 1) / (1 - 1 / n)`` against the harmonic numbers summed, and ``r`` against ``E[max - mean] / E[mean -
    min]`` of Exp(1) samples drawn (20000 pixels of 128 samples)."""
    h = np.cumsum(1.0 / np.arange(1, 5001))
    n = np.array([[0, 1, 8, 32], [33, 64, 512, 5000]])
    r = (h[np.maximum(n, 32) - 1] - 1.0) / (1.0 - 1.0 / np.maximum(n, 32))
    np.testing.assert_allclose(threshold(n), ONE_SIDED * r / r[0, 3], rtol=1e-8)
    assert (threshold(n[0]) == ONE_SIDED).all()
    x = np.random.default_rng(0).exponential(size=(20000, 128))
    m = x.mean(1)
    ratio = (x.max(1) - m).mean() / (m - x.min(1)).mean()
    assert abs(ratio - (h[127] - 1.0) / (1.0 - 1.0 / 128)) < 0.05  # 4.47, its standard error about 0.01


@pytest.mark.parametrize("p, spp", [(0.1, 32), (0.1, 64), (0.05, 32), (0.1, 128)])
def test_a_base_plus_rare_hits_is_one_sided_whatever_the_base(p, spp):
    """(max - mean) / (mean - min) of a base plus h with probability p is (n - k) / k for k hits among n,
    whatever the base and h (about (1 - p) / p: 9 at p = 0.1): the share of pixels above the threshold t is
    P(1 <= k < n / (1 + t)) under Binomial(n, p) (0.75 at p = 0.1, 32 spp; 0.60 at 128, where t = 8.49), to
    within its standard error over 2000 pixels (a base spread of 5 % moves the ratio by a few per cent)."""
    from scipy.stats import binom

    rng = np.random.default_rng(0)
    n_pix = 2000
    pix = np.repeat(np.arange(n_pix), spp)
    base = rng.uniform(0.01, 1.0, n_pix)[pix]
    h = rng.uniform(1.0, 50.0, n_pix)[pix]
    vals = base * (1.0 + 0.05 * rng.random(pix.size)) + h * (rng.random(pix.size) < p)
    pos = np.stack([pix % 50 + 0.5, pix // 50 + 0.5], 1)
    st = PixelStats.from_source(SampleSet(pos, np.repeat(vals[:, None], 3, 1), width=50, height=40))
    k_max = int(np.ceil(spp / (1.0 + float(threshold(np.array(spp)))))) - 1
    want = binom.cdf(k_max, spp, p) - binom.pmf(0, spp, p)
    assert abs(one_sided(st).mean() - want) < 4.0 * np.sqrt(want * (1 - want) / n_pix) + 0.01


@pytest.mark.parametrize("spp", [8, 16, 32])
def test_exponential_noise_on_a_texture_is_not_a_heavy_vote(spp):
    """The regression proxy's linear textured film (colour x Exp(1) samples): measured 0.003-0.020 of the
    pixels one-sided over seeds 0-2 at 8-32 spp, against HEAVY_VOTE 0.45 (a 3 x 3 maximum's test counted
    45-61 % there)."""
    for seed in range(3):
        st = _textured_exponential("linear", seed=seed, spp=spp).merged()
        heavy = one_sided(st)
        assert heavy.mean() < 0.05
        assert not heavy_vote(np.ones_like(heavy), heavy, st.count)


def test_exponential_noise_on_a_texture_is_not_a_heavy_vote_at_thousands_of_samples():
    """A 16^2 texture x Exp(1) samples at 2048 spp, seeds 0-1: the maximum of n exponential samples grows as
    H_n, and the constant threshold 6 counted 0.85 of such pixels one-sided (the regression proxy's film, 48^2,
    seeds 0-2: 0.10 at 128 spp, 0.38 at 512, 0.85 at 2048); the count's threshold 0.000-0.008 from 128 to 4096
    spp."""
    side, spp = 16, 2048
    for seed in range(2):
        rng = np.random.default_rng(seed)
        pix = np.repeat(np.arange(side * side), spp)
        colour = (0.1 + 2.0 * (rng.random((side * side, 3)) * 0.8 + 0.1))[pix]
        pos = np.stack([pix % side + rng.random(pix.size), pix // side + rng.random(pix.size)], 1)
        st = PixelStats.from_source(SampleSet(pos, colour * rng.exponential(size=(pix.size, 1)), width=side,
                                              height=side))
        heavy = one_sided(st)
        assert heavy.mean() < 0.1
        assert not heavy_vote(np.ones_like(heavy), heavy, st.count)


def test_gaussian_noise_and_a_ring_on_zeros_are_not_a_heavy_vote():
    """The procedural blobs (Gaussian noise about a dark mean, 8 spp): 0.000-0.001 one-sided; the ring of
    rare samples on exact zeros: nearly every voter is one-sided, 0.04-0.07 of the pixels with samples."""
    ref, sigma = _scene_blobs()
    for seed in range(2):
        st = PixelStats.from_source(_samples(ref, sigma, 8, seed))
        assert one_sided(st).mean() < 0.01
        ss, _, _ = _caustic_ring_samples(seed)
        st = PixelStats.from_source(ss)
        heavy = one_sided(st)
        assert heavy.mean() < 0.1
        assert not heavy_vote(np.ones_like(heavy), heavy, st.count)


@pytest.mark.parametrize("share, thin", [(0.40, False), (0.50, True)])
def test_a_heavy_vote_makes_the_least_black_box_the_default(share, thin):
    """A full vote whose black box's lead lies within its guard (tests/test_auto_thin_vote.py): with more than
    HEAVY_VOTE of the pixels one-sided among the voters the black box is the default, below it the guard
    stands."""
    from mcrecon.methods.auto.selection import _global_prior

    cands, raw, y, v, count, bounds = _inputs(False)
    heavy = np.zeros(y.shape[:2], bool)
    heavy.flat[: int(share * heavy.size)] = True
    info = {}
    _global_prior(cands, raw.__getitem__, np.stack(raw), np.ones(y.shape[:2], np.int64), y, v, count, bounds, 2.0,
                  3.0, None, guarded={2: 1.0}, steady=[2], blend=False, info=info, heavy=heavy)
    assert info["thin"] is thin and info["g"] == (2 if thin else 1)
    assert HEAVY_VOTE == 0.45


def _spot_light_wall(size, seed):
    """The tuning checker_spot-7's parameters (a light one sample in ten finds) at ``size``^2, 32 spp."""
    from mcrecon.renderers import scenes as S

    sc = S.get_scene("checker_spot", dict(contrast=0.597, exposure=2.52, hit_probability=0.0971, light_power=0.536,
                                          light_size=1.54, sky=0.0109, spot_size=0.627, texture_scale=1.48))
    b = S.render_uniform(sc, width=size, height=size, spp=32, seed=seed, features=True)
    return SampleSet(b.positions, b.values, width=size, height=size, features=b.features), \
        S.reference_image(sc, size, size)


def test_a_rare_bright_light_on_a_texture_takes_a_black_box_default():
    """checker_spot-7's light at 96^2, seed 0: relMSE / the pixel mean's 0.0210 with the heavy vote (OIDN + albedo +
    normal on the halves the default), 0.0271 without (NFOR the default: the capped sums lose their positive
    tails); bound 0.024.  An adaptive round reads the same vote (thin_vote_shown)."""
    from mcrecon.core.halves import split_halves
    from mcrecon.methods.auto.thinvote import thin_vote_shown

    ss, ref = _spot_light_wall(96, 0)
    st = PixelStats.from_source(ss)
    assert heavy_vote(np.ones(st.count.shape, bool), one_sided(st), st.count)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", McreconWarning)
        img = mcrecon.reconstruct(ss, method="auto")
    assert relative_mse(img, ref) / relative_mse(st.mean, ref) < 0.024
    assert thin_vote_shown(st, split_halves(ss), 4.0)
    assert onesided.HEAVY_VOTE == HEAVY_VOTE

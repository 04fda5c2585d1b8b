"""Samples cleaned before any filter (mcrecon.core.cleaning): energy kept, firefly-free input untouched,
a small highlight many samples see left in place, halves dealt as the raw ones."""

from __future__ import annotations

import numpy as np
import pytest

import mcrecon
from mcrecon.core.cleaning import clean_samples
from mcrecon.core.halves import split_halves, split_labels
from mcrecon.errors import InputError


def _uniform(w, h, spp, seed, base=0.1):
    rng = np.random.default_rng(seed)
    pos = (np.repeat(np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 2), spp, axis=0)
           + rng.random((w * h * spp, 2)))
    val = base * (0.5 + rng.random((pos.shape[0], 1))) * np.array([1.0, 0.8, 0.6])
    return pos, val, rng


def test_fireflies_move_and_the_image_energy_is_kept_to_round_off():
    pos, val, rng = _uniform(40, 30, 16, 0)
    idx = rng.choice(pos.shape[0], 25, replace=False)
    val[idx] = rng.uniform(50, 400, (25, 1)) * np.array([1.0, 0.9, 0.7])
    idx_corner = np.flatnonzero((pos[:, 0] < 1) & (pos[:, 1] < 1))[:1]  # one in the film's corner too
    val[idx_corner] = 300.0
    c = clean_samples(mcrecon.SampleSet(pos, val, width=40, height=30))
    assert c.outliers.sum() >= 20 and c.moved_fraction > 0.5
    np.testing.assert_allclose(c.mean.sum(axis=(0, 1)), c.raw_mean.sum(axis=(0, 1)), rtol=1e-12)
    assert c.mean.max() < 0.5 * c.raw_mean.max()  # the dots are lower: their energy is spread
    assert c.mean.min() >= 0.0  # moved, never clipped away or made negative


def test_firefly_free_samples_come_back_bit_for_bit():
    pos, val, _ = _uniform(32, 24, 8, 1)
    c = clean_samples(mcrecon.SampleSet(pos, val, width=32, height=24))
    assert not c.outliers.any() and c.moved_fraction == 0.0
    assert np.array_equal(c.samples.values, val) and np.array_equal(c.mean, c.raw_mean)
    assert np.all(c.excess == 0.0)


def test_a_small_highlight_that_many_samples_see_is_not_cleaned():
    # a 2 x 2 px highlight (HDR: 800 over a 0.1 floor), every sample of it bright: legitimate signal
    pos, val, _ = _uniform(32, 32, 16, 2)
    hi = (pos[:, 0] >= 15) & (pos[:, 0] < 17) & (pos[:, 1] >= 15) & (pos[:, 1] < 17)
    val[hi] = 800.0
    c = clean_samples(mcrecon.SampleSet(pos, val, width=32, height=32))
    assert not c.outliers.any()
    assert np.array_equal(c.mean, c.raw_mean)
    assert c.mean.max() == 800.0  # HDR kept, not clipped


def test_a_highlight_stays_while_a_lone_firefly_beside_it_moves():
    pos, val, _ = _uniform(32, 32, 16, 3)
    hi = (pos[:, 0] >= 4) & (pos[:, 0] < 6) & (pos[:, 1] >= 4) & (pos[:, 1] < 6)
    val[hi] = 800.0
    lone = np.flatnonzero((np.floor(pos[:, 0]) == 24) & (np.floor(pos[:, 1]) == 20))[0]
    val[lone] = 800.0
    c = clean_samples(mcrecon.SampleSet(pos, val, width=32, height=32))
    assert not c.outliers[hi].any() and c.outliers[lone]
    np.testing.assert_array_equal(c.mean[4:6, 4:6], c.raw_mean[4:6, 4:6])
    assert c.mean[20, 24].max() < 0.5 * c.raw_mean[20, 24].max()
    np.testing.assert_allclose(c.mean.sum(), c.raw_mean.sum(), rtol=1e-12)


def test_each_half_is_cleaned_on_its_own_keeping_its_energy_and_its_independence():
    pos, val, rng = _uniform(24, 24, 8, 4)
    val[rng.choice(pos.shape[0], 10, replace=False)] = 250.0
    feats = {"albedo": np.full((pos.shape[0], 3), 0.5)}
    raw = mcrecon.SampleSet(pos, val, width=24, height=24, features=feats)
    c = clean_samples(raw)
    ha, hc = split_halves(raw, features="all"), c.halves(features="all")
    for r, k in ((ha.a, hc.a), (ha.b, hc.b)):
        np.testing.assert_array_equal(r.count, k.count)  # dealt as the raw samples are
        np.testing.assert_allclose((k.mean * k.count[..., None]).sum() / k.count.sum(),
                                   (r.mean * r.count[..., None]).sum() / r.count.sum(), rtol=1e-12)
        assert "albedo" in k.features
        assert k.mean.max() < 0.7 * r.mean.max()  # moved, partly: the pixel that saw it keeps the largest share
    # a firefly added to half A's samples changes nothing in half B
    lab = split_labels(raw.positions, 24, 24, np.zeros(24 * 24, np.int64))
    val2 = val.copy()
    val2[np.flatnonzero(lab == 0)[1234]] = 900.0
    c2 = clean_samples(mcrecon.SampleSet(pos, val2, width=24, height=24))
    hb, hb2 = c.halves().b, c2.halves().b
    np.testing.assert_array_equal(hb.mean, hb2.mean)
    np.testing.assert_array_equal(hb.m2, hb2.m2)


def test_pixel_statistics_and_bad_options_are_refused_in_one_line():
    pos, val, _ = _uniform(8, 8, 4, 5)
    ss = mcrecon.SampleSet(pos, val, width=8, height=8)
    with pytest.raises(InputError, match="cleaning: source"):
        clean_samples(split_halves(ss).merged())
    with pytest.raises(InputError, match="k_min"):
        clean_samples(ss, k_min=0)
    with pytest.raises(InputError, match="nonfinite"):
        clean_samples(ss, nonfinite="ignore")


def test_nonfinite_samples_get_the_policy_first():
    pos, val, _ = _uniform(8, 8, 4, 6)
    val[3] = np.nan
    c = clean_samples(mcrecon.SampleSet(pos, val, width=8, height=8))
    assert c.samples.n_samples == pos.shape[0] - 1 and np.isfinite(c.mean).all()
    with pytest.raises(InputError, match="NaN"):
        clean_samples(mcrecon.SampleSet(pos, val, width=8, height=8), nonfinite="raise")

"""The prefix halves' estimate of a stratified pixel mean's error (mcrecon.core.strata), against brute force."""

from __future__ import annotations

import numpy as np
import pytest

from mcrecon.core.halves import Halves
from mcrecon.core.strata import GAIN_FLOOR, PrefixHalves
from mcrecon.renderers.scenes.sobol import sobol_points

#: replicates: one pixel each, every pixel its own Owen scramble (independent randomizations)
_R = 3000


def _edge(p):
    return (p[:, 0] + 0.37 * p[:, 1] > 0.61).astype(float)


def _smooth(p):
    return np.exp(p[:, 0]) * np.sin(2.0 + p[:, 1])


def _sobol_replicates(f, n, *, dims=2, seed=0):
    """Values (R, n) of ``f`` at the first ``n`` Sobol points of ``_R`` pixels, and their halves' estimate."""
    pix = np.repeat(np.arange(_R, dtype=np.int64), n)
    idx = np.tile(np.arange(n, dtype=np.int64), _R)
    v = f(sobol_points(pix, idx, dims, seed=seed))
    ph = PrefixHalves(_R, 1, 1)
    ph.add(np.stack([pix + 0.5, np.full(pix.size, 0.5)], 1), v[:, None])
    a, b, na, nb = ph.halves()
    return v.reshape(_R, n), (0.5 * (a - b))[0, :, 0] ** 2


@pytest.mark.parametrize("f", [_edge, _smooth])
@pytest.mark.parametrize("n", [16, 32])
def test_halves_bound_the_stratified_variance_far_below_s2_over_n(f, n):
    # the mean of the prefix halves' squared half-difference against the measured variance of the
    # stratified mean over independent scrambles: never below it (within the replicates' noise),
    # and far closer than s^2 / n, which the allocation used to read
    v, d2 = _sobol_replicates(f, n)
    var_mean = v.mean(axis=1).var()
    s2n = (v.var(axis=1, ddof=1) / n).mean()
    est = d2.mean()
    assert est >= 0.85 * var_mean
    assert est <= 12.0 * var_mean
    assert s2n >= 2.5 * est  # s^2 / n overstates more than the halves do


def test_alternating_halves_measure_the_pixel_not_the_noise():
    # the per-sample alternating halves (core.halves) put samples 2j and 2j+1 of a Sobol sequence in
    # opposite halves of the pixel: on an edge their squared half-difference is many times the error
    n = 32
    pix = np.repeat(np.arange(_R, dtype=np.int64), n)
    idx = np.tile(np.arange(n, dtype=np.int64), _R)
    v = _edge(sobol_points(pix, idx, 2, seed=0))
    pos = np.stack([pix + 0.5, np.full(pix.size, 0.5)], 1)
    h = Halves.empty(_R, 1, ("Y",))
    h.add(pos, v[:, None])
    alt = (0.5 * (h.a.mean - h.b.mean))[0, :, 0] ** 2
    _, d2 = _sobol_replicates(_edge, n)
    var_mean = v.reshape(_R, n).mean(axis=1).var()
    assert alt.mean() > 4.0 * var_mean
    assert d2.mean() < 2.5 * var_mean


def test_independent_samples_estimate_is_unbiased():
    rng = np.random.default_rng(1)
    n = 16
    v = rng.exponential(size=(_R, n))
    ph = PrefixHalves(_R, 1, 1)
    pix = np.repeat(np.arange(_R), n)
    ph.add(np.stack([pix + 0.5, np.full(pix.size, 0.5)], 1), v.reshape(-1, 1))
    a, b, _, _ = ph.halves()
    est = ((0.5 * (a - b)) ** 2).mean()
    assert est == pytest.approx(1.0 / n, rel=0.1)  # Var of the 16-sample mean of Exp(1)


def test_prefix_follows_the_stream_in_any_chunking():
    # halves of the longest power-of-two prefix: n = 8 -> [0, 4) | [4, 8); n = 13 -> the same
    # prefix; chunked arrival gives the same sums as one batch
    vals = np.arange(13, dtype=float)[:, None]
    pos = np.full((13, 2), 0.5)
    for chunks in ([13], [1, 2, 3, 7], [8, 5]):
        ph = PrefixHalves(1, 1, 1)
        k = 0
        for c in chunks:
            ph.add(pos[k:k + c], vals[k:k + c])
            k += c
        a, b, na, nb = ph.halves()
        assert (int(na[0, 0]), int(nb[0, 0])) == (4, 4)
        assert (a[0, 0, 0], b[0, 0, 0]) == (1.5, 5.5)
    ph = PrefixHalves(1, 1, 1)
    ph.add(pos[:8], vals[:8])
    a, b, na, nb = ph.halves()
    assert (a[0, 0, 0], b[0, 0, 0], int(na[0, 0])) == (1.5, 5.5, 4)
    ph = PrefixHalves(1, 1, 1)
    ph.add(pos[:3], np.array([[1.0], [np.nan], [2.0]]))  # a NaN takes its index, not a place
    a, b, na, nb = ph.halves()
    assert (a[0, 0, 0], int(na[0, 0]), int(nb[0, 0])) == (1.0, 1, 0)


def test_gain_low_for_a_stratified_smooth_film_and_one_for_independent_samples():
    w = h = 16
    n = 16
    pix = np.repeat(np.arange(w * h, dtype=np.int64), n)
    idx = np.tile(np.arange(n, dtype=np.int64), w * h)
    off = sobol_points(pix, idx, 2, seed=3)
    pos = np.stack([pix % w, pix // w], 1) + off
    smooth = np.exp(pos[:, 0] / 4.0 % 1.0)[:, None]  # smooth within every pixel
    ph = PrefixHalves(w, h, 1)
    ph.add(pos, smooth)
    var = smooth.reshape(w * h, n).var(axis=1, ddof=1).reshape(h, w, 1)
    g = ph.gain(var)
    assert g.shape == (h, w)
    assert np.median(g) < 0.2 and g.min() >= GAIN_FLOOR
    rng = np.random.default_rng(0)
    noise = rng.normal(1.0, 0.3, (pix.size, 1))
    ph = PrefixHalves(w, h, 1)
    ph.add(pos, noise)
    g = ph.gain(noise.reshape(w * h, n).var(axis=1, ddof=1).reshape(h, w, 1))
    # chance dips of the ratio below 1 are no gain: independent samples keep s^2 / n almost everywhere
    assert np.mean(g == 1.0) > 0.9 and g.max() <= 1.0
    assert np.all(PrefixHalves(w, h, 1).gain(np.zeros((h, w, 1))) == 1.0)  # nothing known: s^2 / n

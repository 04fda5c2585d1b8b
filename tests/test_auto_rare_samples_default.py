"""auto's black box on all the samples takes the pixels with rare huge samples around, whatever the global
default is: the whole-image sums leave those pixels out and every per-pixel estimate there rests on one
sample."""

from __future__ import annotations

import numpy as np

from mcrecon.methods.auto.features import Candidate
from mcrecon.methods.auto.method import _all_samples_box
from mcrecon.methods.auto.selection import _global_prior


def _inputs(h=12, w=14):
    rng = np.random.default_rng(0)
    y = rng.uniform(0.4, 0.6, size=(h, w, 3))
    v = np.full((h, w, 3), 0.01)
    count = np.full((h, w), 16)
    flat = np.full((h, w, 3), 0.5)
    cands = [Candidate("box", y.copy(), v.copy()), Candidate("gauss1", flat.copy(), np.full((h, w, 3), 0.005)),
             Candidate("oidn_halves", flat + 0.01, np.full((h, w, 3), 0.004)),
             Candidate("oidn", flat - 0.01, np.full((h, w, 3), 0.02))]
    raw = [c.mse.mean(axis=2) / 0.26 for c in cands]
    hi = y.copy()
    hi[3, 4] = hi[8, 9] = 100.0  # rare huge samples around two pixels
    return cands, raw, y, v, count, (y.copy(), hi)


def _prior(cands, raw, y, v, count, bounds, **kw):
    plain = np.zeros(y.shape[:2], np.int64)
    return _global_prior(cands, raw.__getitem__, np.stack(raw), plain, y, v, count, bounds, 2.0, 3.0, None, **kw)


def test_the_all_samples_black_box_takes_the_rare_sample_pixels_under_a_linear_default():
    """The default is the Gaussian (the black boxes' sums are higher); the pixels with rare huge samples
    around take OIDN on all the samples and count as the default's; the rest keep the Gaussian."""
    cands, raw, y, v, count, bounds = _inputs()
    cands = cands[:2] + cands[3:]
    raw = raw[:2] + raw[3:]
    info = {}
    got, held = _prior(cands, raw, y, v, count, bounds, steady=[2], rare=2, info=info)
    heavy = np.zeros(y.shape[:2], bool)
    heavy[3, 4] = heavy[8, 9] = True
    assert info["g"] == 1
    assert (got[heavy] == 2).all() and (got[~heavy] == 1).all()
    assert held.all()
    np.testing.assert_array_equal(info["rare"], heavy)
    got, _ = _prior(cands, raw, y, v, count, bounds, steady=[2])  # without it the Gaussian holds them
    assert (got == 1).all()


def test_the_all_samples_black_box_replaces_a_halves_default_at_the_rare_sample_pixels():
    """The halves' average is the steady default (least sum); at the rare-sample pixels it sees each rare
    sample at twice its weight, and OIDN on all the samples takes them."""
    cands, raw, y, v, count, bounds = _inputs()
    got, held = _prior(cands, raw, y, v, count, bounds, steady=[2, 3], rare=3, blend=False)
    assert got[3, 4] == 3 and got[8, 9] == 3
    assert (got == 2).sum() == got.size - 2 and held.all()


def test_the_all_samples_black_box_is_colour_only_oidn():
    """Not OIDN with the albedo: with features the heavy-tail test, in colour units, flags texture edges."""
    c = [Candidate(n, np.zeros((1, 1, 3)), np.zeros((1, 1, 3))) for n in ("box", "oidn_halves", "oidn_aux", "oidn")]
    assert _all_samples_box(c) == 3
    assert _all_samples_box(c[:3]) is None

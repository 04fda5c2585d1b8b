"""auto's global prior where the vote is thin (most pixels have rare huge samples around): a black box of least
summed estimate is the default without its guard's margin; with a full vote the margin stands."""

from __future__ import annotations

import numpy as np
import pytest

from mcrecon.methods.auto import selection
from mcrecon.methods.auto.features import Candidate
from mcrecon.methods.auto.selection import _global_prior, _summed, summed_estimates


def _inputs(thin: bool, h=48, w=64, seed=7):
    """A Gaussian (estimate 0.005 everywhere) and a black box whose noisy estimate is a little lower on
    average: its summed lead over the voters is below one standard error.  ``thin``: the left three
    quarters of the image have rare huge samples around (their 3 x 3 maximum 200x the means)."""
    rng = np.random.default_rng(seed)
    y = rng.uniform(0.4, 0.6, size=(h, w, 3))
    v = np.full((h, w, 3), 0.01)
    count = np.full((h, w), 16)
    flat = np.full((h, w, 3), 0.5)
    noise = rng.normal(0.0, 0.004, size=(h, w, 1)) * np.ones(3)
    cands = [Candidate("box", y.copy(), v.copy()), Candidate("gauss1", flat.copy(), np.full((h, w, 3), 0.005)),
             Candidate("oidn", flat + 0.001, 0.0049 + noise)]
    raw = [c.mse.mean(axis=2) / 0.26 for c in cands]
    hi = y.copy()
    if thin:
        hi[:, : 3 * w // 4] = 100.0
    return cands, raw, y, v, count, (y.copy(), hi)


def _default(thin, **kw):
    cands, raw, y, v, count, bounds = _inputs(thin)
    info = {}
    plain = np.ones(y.shape[:2], np.int64)
    _global_prior(cands, raw.__getitem__, np.stack(raw), plain, y, v, count, bounds, 2.0, 3.0, None,
                  guarded={2: 1.0}, steady=[2], blend=False, info=info, **kw)
    return info


@pytest.mark.parametrize("thin", [False, True])
def test_the_black_box_lead_lies_within_its_guard(thin):
    """The case the rule is for: the black box's sum is the least, by less than one standard error."""
    cands, raw, y, v, count, bounds = _inputs(thin)
    _, _, loo, apart, vote, sums = summed_estimates(cands, y, v, count, bounds[1], None)
    assert int(np.argmin(sums)) == 2
    total, se = _summed(np.where(vote, loo(2) - loo(1), 0.0))
    assert -1.0 * se < total < 0.0
    assert vote.mean() == pytest.approx(0.25 if thin else 1.0)


def test_a_thin_vote_makes_the_least_black_box_the_default():
    info = _default(True)
    assert info["g"] == 2 and info["thin"]


def test_a_full_vote_keeps_the_black_box_guard():
    info = _default(False)
    assert info["g"] == 1 and not info["thin"]


def test_without_the_rule_a_thin_vote_keeps_the_guard():
    info = _default(True, thin_vote=0.0)
    assert info["g"] == 1 and not info["thin"]
    # the module default is the rule's switch
    assert selection.THIN_VOTE == 0.6


def _raised(thin, extra=0.0003):
    """The black box's estimate raised above the Gaussian's (its sum no longer the least), and a second black box
    whose estimate is higher still."""
    cands, raw, y, v, count, bounds = _inputs(thin)
    cands[2] = Candidate("oidn", cands[2].image, cands[2].mse + extra)
    cands.append(Candidate("oidn_halves", cands[2].image + 0.001, cands[2].mse + 0.001))
    raw = [c.mse.mean(axis=2) / 0.26 for c in cands]
    info = {}
    _global_prior(cands, raw.__getitem__, np.stack(raw), np.ones(y.shape[:2], np.int64), y, v, count, bounds, 2.0,
                  3.0, None, guarded={2: 1.0, 3: 1.0}, steady=[2, 3], blend=False, info=info)
    _, _, _, _, _, sums = summed_estimates(cands, y, v, count, bounds[1], None)
    return info, sums


def test_a_thin_vote_compares_the_black_boxes_among_themselves():
    """In a thin vote the default is the black box of least sum even where a Gaussian's sum is lower (the
    voters' selection flatters it); with a full vote the Gaussian stays."""
    info, sums = _raised(True)
    assert sums[1] < sums[2] < sums[3]
    assert info["g"] == 2 and info["thin"]
    info, sums = _raised(False)
    assert sums[1] < sums[2]
    assert info["g"] == 1 and not info["thin"]


def test_a_thin_vote_without_a_black_box_keeps_the_least_sum():
    """No steady candidate: the thin vote changes nothing (the plain argmin of the sums)."""
    cands, raw, y, v, count, bounds = _inputs(True)
    info = {}
    _global_prior(cands[:2], raw.__getitem__, np.stack(raw[:2]), np.ones(y.shape[:2], np.int64), y, v, count,
                  bounds, 2.0, 3.0, None, blend=False, info=info)
    assert info["g"] == 1 and not info["thin"]


def test_exact_dark_pixels_do_not_make_a_vote_thin():
    """Three quarters of the image exact zeros (every sample 0: no variance, left out of the vote by the
    safeguard's pins, not by a rare light): the vote is not thin, the black box's guard stands; the pixels
    that could vote are the quarter with variance."""
    cands, raw, y, v, count, bounds = _inputs(False)
    w = y.shape[1]
    for arr in (y, v, bounds[0], bounds[1]):
        arr[:, : 3 * w // 4] = 0.0
    for c in cands:
        c.image[:, : 3 * w // 4] = 0.0
    assert selection._could_vote(v, count, 4.0) == v.shape[0] * (w // 4)
    assert selection._could_vote(v, count, None) == v.shape[0] * w
    info = {}
    _global_prior(cands, raw.__getitem__, np.stack(raw), np.ones(y.shape[:2], np.int64), y, v, count, bounds, 2.0,
                  3.0, 4.0, guarded={2: 1.0}, steady=[2], blend=False, info=info)
    assert not info["thin"]
    # counted over every pixel with samples (the zeros among them) the same vote would be thin
    _, _, _, _, vote, _ = summed_estimates(cands, y, v, count, bounds[1], 4.0)
    assert vote.sum() < selection.THIN_VOTE * np.count_nonzero(count > 0)


def test_the_thin_default_takes_the_least_crossed_vote_then_the_least_sum():
    """Two black boxes of one filter share a crossed vote; the family of least crossed vote is taken, the
    least sum within it; without crossed votes the least sum of all."""
    img = np.zeros((2, 2, 3))
    cands = [Candidate("gauss1", img, img), Candidate("oidn_halves", img, img, crossed=5.0),
             Candidate("oidn_aux", img, img, crossed=3.0), Candidate("oidn_aux_halves", img, img, crossed=3.0)]
    sums = [0.0, 1.0, 9.0, 8.0]
    assert selection._thin_default(cands, [1, 2, 3], sums) == 3
    for c in cands:
        c.crossed = None
    assert selection._thin_default(cands, [1, 2, 3], sums) == 1


def _rare_halves(seed, h=48, w=48, n=32, p=1 / 60):
    """Samples 1 + B / p (B ~ Bernoulli(p): a rare light, true mean 2 everywhere), split into halves."""
    from mcrecon.core.halves import mean_variances, split_halves
    from mcrecon.core.samples import SampleSet
    from mcrecon.core.stats import PixelStats

    rng = np.random.default_rng(seed)
    pix = np.repeat(np.arange(h * w), n)
    val = 1.0 + (rng.random(pix.size) < p) / p
    pos = np.stack([pix % w + rng.random(pix.size), pix // w + rng.random(pix.size)], axis=1)
    src = SampleSet(pos, np.repeat(val[:, None], 3, axis=1), width=w, height=h)
    st = PixelStats.from_source(src)
    hv = split_halves(src)
    return st, hv, mean_variances(st, hv)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_crossed_vote_ranks_a_filter_that_restores_the_rare_light_first(seed):
    """A filter at the truth and one that keeps each half's miss (a 1 px Gaussian of the half's means): the
    crossed vote (voters chosen by the half the filter read, scored against the other half) ranks the truth
    first, and it is the sum over each half's voters of the channel mean of its cross-validation over the
    relative denominator (recomputed here from the half's own rare-sample test)."""
    from scipy.ndimage import gaussian_filter

    from mcrecon.core.safeguard import sample_range_bounds
    from mcrecon.methods.auto.estimates import cross_validation_mse, relative_denominator_loo

    st, hv, (v, va, vb) = _rare_halves(seed)
    ha, hb = hv.a, hv.b
    den = relative_denominator_loo(st.mean, v, st.count, eps=0.01)
    truth = np.full(st.mean.shape, 2.0)
    filters = {"truth": (truth, truth), "miss": (gaussian_filter(ha.mean, (1, 1, 0)), gaussian_filter(hb.mean, (1, 1, 0)))}
    crossed = {}
    for k, (fa, fb) in filters.items():
        cva, cvb = cross_validation_mse(fa, hb.mean, vb), cross_validation_mse(fb, ha.mean, va)
        crossed[k] = selection.crossed_sum(cva, cvb, ha, hb, va, vb, den)
        ref = 0.0
        for cv, h, vh in ((cva, ha, va), (cvb, hb, vb)):
            dh = relative_denominator_loo(h.mean, vh, h.count, eps=0.01)
            votes = ~selection._apart(h.mean, vh, sample_range_bounds(h)[1], dh, True)
            assert 0.05 < votes.mean() < 0.95  # the rare light leaves part of each half out
            ref += float(np.nansum((cv / den).mean(axis=2)[votes]))
        assert crossed[k] == pytest.approx(ref, rel=1e-12)
    assert crossed["truth"] < crossed["miss"]

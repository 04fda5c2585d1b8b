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

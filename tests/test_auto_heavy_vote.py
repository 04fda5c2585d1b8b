"""auto's global prior where the vote is heavy (many voters have rare huge samples around at HEAVY_TAIL, under the
vote's own HEAVY_PRIOR): the black box of least crossed vote, then least sum, is the default without its guard,
as in a thin vote; below the share the guard stands."""

from __future__ import annotations

import numpy as np
import pytest

from mcrecon.methods.auto import heavyvote
from mcrecon.methods.auto.firefly import HEAVY_TAIL
from mcrecon.methods.auto.heavyvote import HEAVY_VOTE, _heavy_vote
from mcrecon.methods.auto.selection import HEAVY_PRIOR, _global_prior, _summed, summed_estimates

from helpers import prior_inputs


def _inputs(heavy_share, h=48, w=64):
    """A Gaussian and a black box whose summed lead lies within its guard (:func:`helpers.prior_inputs`).  The
    left ``heavy_share`` of the columns have rare huge samples around: their 3 x 3 sample maximum 15x the
    means, above HEAVY_TAIL (10) and under the vote's HEAVY_PRIOR (30), so every pixel still votes."""
    cands, raw, y, v, count = prior_inputs(h, w)
    hi = y.copy()
    hi[:, : int(round(heavy_share * w))] *= 15.0
    return cands, raw, y, v, count, (y.copy(), hi)


def _default(heavy_share):
    cands, raw, y, v, count, bounds = _inputs(heavy_share)
    info = {}
    _global_prior(cands, raw.__getitem__, np.stack(raw), np.ones(y.shape[:2], np.int64), y, v, count, bounds, 2.0,
                  3.0, None, guarded={2: 1.0}, steady=[2], blend=False, info=info)
    return info


def test_the_case_votes_in_full_within_the_black_box_guard():
    """Every pixel votes (15x is under HEAVY_PRIOR), and the black box's lead is below one standard error."""
    assert HEAVY_TAIL < 15.0 < HEAVY_PRIOR
    cands, raw, y, v, count, bounds = _inputs(0.75)
    _, _, loo, _, vote, sums = summed_estimates(cands, y, v, count, bounds[1], None)
    assert vote.all()
    assert int(np.argmin(sums)) == 2
    total, se = _summed(np.where(vote, loo(2) - loo(1), 0.0))
    assert -1.0 * se < total < 0.0


def test_a_heavy_vote_makes_the_least_black_box_the_default():
    info = _default(0.75)
    assert info["g"] == 2 and info["thin"]


def test_without_the_rule_a_heavy_vote_keeps_the_guard(monkeypatch):
    monkeypatch.setattr(heavyvote, "HEAVY_VOTE", None)
    info = _default(0.75)
    assert info["g"] == 1 and not info["thin"]


def test_a_light_share_keeps_the_guard():
    """A quarter of the pixels heavy voters (the corpus's other scenes: at most 0.17): the guard stands."""
    info = _default(0.25)
    assert info["g"] == 1 and not info["thin"]


def _shares(n_heavy, n_vote=50, side=10):
    """Means 1 on a side x side image, the first ``n_vote`` pixels voting, the first ``n_heavy`` of them with
    a one-sided tail in one channel (3 x 3 maximum 11, minimum 1); the non-voters heavy too."""
    y = np.ones((side, side, 3))
    lo, hi = y.copy(), y.copy()
    hi.reshape(-1, 3)[:n_heavy, 2] = 11.0
    hi.reshape(-1, 3)[n_vote:, 0] = 100.0  # not voters: not counted
    vote = np.zeros((side, side), bool)
    vote.reshape(-1)[:n_vote] = True
    return vote, y, (lo, hi), np.full((side, side), 8)


@pytest.mark.parametrize("n, want", [(35, False), (36, True)])
def test_the_share_is_of_the_pixels_with_samples_and_strict(n, want):
    """Heavy voters counted against every pixel with samples (100 here, 50 voting), above HEAVY_VOTE, not at
    it; empty pixels do not count."""
    assert HEAVY_VOTE == 0.35
    vote, y, bounds, count = _shares(n)
    assert _heavy_vote(vote, y, bounds, count) is want
    count.reshape(-1)[90:] = 0  # 90 pixels with samples: 0.35 of them is 31.5
    assert _heavy_vote(vote, y, bounds, count) is (n > 31.5)
    assert not _heavy_vote(vote, y, bounds, np.zeros_like(count))


def test_a_ring_of_heavy_voters_on_exact_zeros_is_not_a_heavy_vote():
    """Every voter heavy, but the voters a tenth of the pixels with samples (a ring of rare samples on exact
    zeros, which the safeguard's pins leave out of the vote)."""
    vote, y, bounds, count = _shares(10, n_vote=10)
    assert not _heavy_vote(vote, y, bounds, count)


def test_symmetric_noise_near_zero_is_not_a_heavy_tail():
    """Means near 0 with a 3 x 3 maximum far above them but a minimum as far below (Gaussian samples on a dark
    background): the maximum exceeds 10x the mean, the tail is not one-sided."""
    vote, y, (lo, hi), count = _shares(80, n_vote=100)
    y[:] = 0.05
    lo[:] = -1.0
    hi[:] = 1.0
    assert not _heavy_vote(vote, y, (lo, hi), count)
    lo[:] = 0.0
    assert _heavy_vote(vote, y, (lo, hi), count)

"""auto's global prior where the vote is heavy (most voters have rare huge samples around at HEAVY_TAIL, under the
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
    """A quarter of the voters heavy (the corpus's caustics and Mitsuba spheres: 0.21-0.27): the guard stands."""
    info = _default(0.25)
    assert info["g"] == 1 and not info["thin"]


@pytest.mark.parametrize("share, want", [(0.45, False), (0.55, True)])
def test_the_share_is_of_the_voters_and_strict(share, want):
    """The heavy pixels counted among the voters only, any channel; above HEAVY_VOTE, not at it."""
    assert HEAVY_VOTE == 0.5
    y = np.ones((10, 10, 3))
    hi = y.copy()
    n = int(round(share * 50))
    hi.reshape(100, 3)[:n, 2] = 11.0  # one channel of n pixels among the first 50 (the voters)
    vote = np.zeros((10, 10), bool)
    vote.reshape(100)[:50] = True
    hi.reshape(100, 3)[50:, 0] = 100.0  # non-voters heavy: not counted
    assert _heavy_vote(vote, y, hi) is want
    hi.reshape(100, 3)[:25, 2] = 1.0
    hi.reshape(100, 3)[:25, 1] = 11.0
    assert _heavy_vote(vote, y, hi) is want
    # exactly half: not heavy
    hi = y.copy()
    hi.reshape(100, 3)[:25, 0] = 11.0
    assert not _heavy_vote(vote, y, hi)
    assert not _heavy_vote(np.zeros((10, 10), bool), y, hi)

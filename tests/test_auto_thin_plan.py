"""auto's adaptive rounds under a thin vote (:meth:`mcrecon.methods.auto.method.AutoMethod.plan`): where the committed
samples make the global prior's vote thin (:func:`mcrecon.methods.auto.thinvote.thin_vote_shown`), the final default is
a black box that neither GEM's estimates nor the net gate score, and a round in whole nets is the even one
(:func:`mcrecon.core.nets.even_round`; docs/adaptive.md, the tuning spotlit texture)."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest

from mcrecon.core.halves import Halves
from mcrecon.core.nets import even_round
from mcrecon.core.stats import PixelStats
from mcrecon.methods import get_method
from mcrecon.methods.auto.method import AutoMethod
from mcrecon.methods.auto import thinvote
from mcrecon.methods.auto.thinvote import PLAN_THIN_VOTE, THIN_VOTE, thin_vote_shown
from mcrecon.methods.base import AdaptiveState

H = W = 16


def _state(rare: bool, sampler: str = "sobol"):
    """16 samples at each pixel of a 16 x 16 film, 0.5 +- 0.1; with ``rare`` one sample of 100 at every third pixel of
    every third row (a rare light most pixels' 3 x 3 neighbourhoods found), else at four pixels only.  No prefix
    halves: the rounds in whole nets go without the net gate."""
    rng = np.random.default_rng(3)
    values = rng.uniform(0.4, 0.6, (H, W, 16, 3))
    if rare:
        values[1::3, 1::3, 7] = 100.0
    else:
        values[[2, 2, 12, 12], [3, 11, 3, 11], 7] = 100.0
    pix = np.repeat(np.arange(H * W), 16)
    pos = np.stack([pix % W + 0.5, pix // W + 0.5], axis=1)
    values = values.reshape(-1, 3)
    st = PixelStats(W, H)
    st.add(pos, values)
    halves = Halves.empty(W, H, ("R", "G", "B"))
    halves.add(pos, values)
    state = AdaptiveState(st, 2, 32 * H * W, 16 * H * W, np.random.default_rng(0), iteration=1,
                          sampler=sampler)
    return state, halves


@pytest.mark.parametrize("rare, thin", [(True, True), (False, False)])
def test_thin_vote_shown_reads_the_share_of_pixels_left_to_vote(rare, thin):
    """Rare huge samples in most pixels' 3 x 3 neighbourhoods leave fewer than 60 % of them to vote; four such
    pixels leave most."""
    state, halves = _state(rare)
    assert thin_vote_shown(state.stats, halves, 4.0) is thin
    assert not thin_vote_shown(state.stats, None, 4.0)  # no halves, no black box scored from them


def test_the_rounds_read_the_vote_thin_by_a_margin(monkeypatch):
    """An adaptive round reads the vote as thin below PLAN_THIN_VOTE of the pixels, under the final selection's
    THIN_VOTE (a share near that threshold moves with the seed and the round); the share is the voters' over the
    pixels that could vote."""
    assert PLAN_THIN_VOTE < THIN_VOTE
    state, halves = _state(True)
    voters = _voters(state, halves)
    assert thin_vote_shown(state.stats, halves, 4.0, share=voters + 1e-9)
    assert not thin_vote_shown(state.stats, halves, 4.0, share=voters - 1e-9)
    monkeypatch.setattr(thinvote, "PLAN_THIN_VOTE", voters - 1e-9)
    assert not thin_vote_shown(state.stats, halves, 4.0)


def _voters(state, halves):
    from mcrecon.core.halves import mean_variances
    from mcrecon.core.safeguard import sample_range_bounds
    from mcrecon.methods.auto.estimates import relative_denominator_loo
    from mcrecon.methods.auto.selection import _apart

    st = state.stats
    v = mean_variances(st, halves)[0]
    apart = _apart(st.mean, v, sample_range_bounds(st)[1], relative_denominator_loo(st.mean, v, st.count, eps=0.01),
                   True)
    return (~apart).sum() / thinvote._could_vote(v, st.count, 4.0)


def _plan(state, halves, monkeypatch, on):
    monkeypatch.setattr(AutoMethod, "thin_even", on)
    m = get_method("auto")
    run = m.start(W, H)
    run.halves = halves
    return m.plan(run, dataclasses.replace(state, rng=copy.deepcopy(state.rng))).counts


def test_a_thin_vote_gives_the_even_round(monkeypatch):
    """Under the thin vote a round in whole nets is the even round's counts (whole nets lowest first), whereas GEM's
    half of the round chases the rare samples' pixels."""
    state, halves = _state(True)
    n = get_method("auto").round_size(state)
    even = even_round(dataclasses.replace(state, rng=copy.deepcopy(state.rng)), n)
    on, off = _plan(state, halves, monkeypatch, True), _plan(state, halves, monkeypatch, False)
    assert np.array_equal(on, even) and on.sum() == n
    assert not np.array_equal(off, even) and off.sum() == n


def test_rounds_of_independent_samples_keep_the_allocation(monkeypatch):
    """With independent samples the rule does not apply (the default checker_spot: 1.00 with even rounds against
    0.82, docs/adaptive.md)."""
    state, halves = _state(True, "independent")
    on = _plan(state, halves, monkeypatch, True)
    assert np.array_equal(on, _plan(state, halves, monkeypatch, False)) and np.ptp(on) > 4


def test_a_full_vote_keeps_the_allocation(monkeypatch):
    state, halves = _state(False)
    assert np.array_equal(_plan(state, halves, monkeypatch, True), _plan(state, halves, monkeypatch, False))

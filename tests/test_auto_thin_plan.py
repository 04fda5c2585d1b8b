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
from mcrecon.core.strata import PrefixHalves
from mcrecon.methods import get_method
from mcrecon.methods.auto.method import AutoMethod
from mcrecon.methods.auto import method as auto_method
from mcrecon.methods.auto import thinvote
from mcrecon.methods.auto.thinvote import PLAN_THIN_VOTE, THIN_VOTE, thin_vote_shown
from mcrecon.methods.base import AdaptiveState, Method

H = W = 16


def _state(rare: bool, sampler: str = "sobol"):
    """16 samples at each pixel of a 16 x 16 film, 0.5 +- 0.1; with ``rare`` one sample of 100 at every third pixel of
    every third row (a rare light most pixels' 3 x 3 neighbourhoods found), else at four pixels only: a rare
    component shows either way, so the net gate leaves a round in whole nets to the plan."""
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
    strata = PrefixHalves(W, H, 3)
    strata.add(pos, values)
    state = AdaptiveState(st, 2, 32 * H * W, 16 * H * W, np.random.default_rng(0), iteration=1, strata=strata,
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
    from mcrecon.methods.auto.apart import left_out

    st = state.stats
    v = mean_variances(st, halves)[0]
    apart = left_out(st.mean, v, st.count, sample_range_bounds(st)[1], True)[1]
    return (~apart).sum() / thinvote._could_vote(v, st.count, 4.0)


def _plan(state, halves, monkeypatch, on):
    monkeypatch.setattr(AutoMethod, "thin_even", on)
    m = get_method("auto")
    run = m.start(W, H)
    run.halves = halves
    return m.plan(run, dataclasses.replace(state, rng=copy.deepcopy(state.rng))).counts


def _auto(state, halves, monkeypatch, on):
    monkeypatch.setattr(AutoMethod, "thin_even", on)
    m = get_method("auto")
    run = m.start(W, H)
    run.halves = halves
    return m, run


@pytest.mark.parametrize("rare, even", [(True, True), (False, False)])
def test_a_thin_vote_makes_a_round_the_gate_leaves_even(rare, even, monkeypatch):
    """Where a rare component shows (both states) the net gate leaves the round to the plan; auto's
    even_under_rare then makes it the even round under a thin vote (rare samples in most neighbourhoods), not
    under a full one (four rare samples), and not with the rule off."""
    state, halves = _state(rare)
    m, run = _auto(state, halves, monkeypatch, True)
    assert m.even_under_rare(run, state) is even
    m, run = _auto(state, halves, monkeypatch, False)
    assert m.even_under_rare(run, state) is False
    # the rule on: without colour OIDN, and without an albedo for oidn_aux (listed among the feature
    # candidates, run only where the samples carry one), no black box can be the default
    monkeypatch.setattr(AutoMethod, "thin_even", True)
    no_oidn = get_method("auto", candidates="box,gauss")
    assert "oidn_aux" in no_oidn._feature_names and "albedo" not in state.stats.features
    run = no_oidn.start(W, H)
    run.halves = halves
    assert no_oidn.even_under_rare(run, state) is False


def test_auto_plans_the_even_round_under_a_thin_vote(monkeypatch):
    """auto's round in whole nets under the thin vote is net_plan's even round (every pixel's next net, lowest
    first): a net up at 85 pixels and 5 samples at one more, where the plan without the rule differs."""
    state, halves = _state(True)
    on, off = _plan(state, halves, monkeypatch, True), _plan(state, halves, monkeypatch, False)
    n = get_method("auto").round_size(state)
    assert on.sum() == off.sum() == n
    assert (on == 16).sum() == n // 16 and (on % 16 == 0).sum() == on.size - 1
    assert not np.array_equal(on, off)


class _Planner(Method):
    """A method in whole nets that wants its samples in the film's first four rows (no rule of its own)."""
    name = "planner"

    def round_size(self, state):
        return 16 * 64

    def place(self, run, state, n):
        wish = np.zeros((H, W), np.int64)
        wish[:4] = n // 64
        return wish


class _EvenPlanner(_Planner):
    def even_under_rare(self, run, state):
        return True


def test_the_net_gate_asks_the_method_where_a_rare_component_shows():
    """net_plan leaves a round where a rare component shows to the plan, unless the method's even_under_rare says
    otherwise; Method.even_under_rare (the contract net_plan calls) says no."""
    from mcrecon.core.nets import net_plan

    state, _ = _state(True)
    assert Method.even_under_rare(_Planner(), None, state) is False
    assert get_method("gem").even_under_rare(None, state) is False
    plan = net_plan(_Planner(), None, dataclasses.replace(state, rng=copy.deepcopy(state.rng))).counts
    even = net_plan(_EvenPlanner(), None, dataclasses.replace(state, rng=copy.deepcopy(state.rng))).counts
    assert (plan[:4] == 16).all() and not plan[4:].any()
    # the even round: every pixel's next net, lowest first, ties at random (64 pixels step from 16 to 32)
    assert (even == 16).sum() == 64 and not even[(even != 0) & (even != 16)].any()
    assert not (even[:4] == 16).all()


def test_rounds_of_independent_samples_keep_the_allocation(monkeypatch):
    """With independent samples the rule does not apply (the default checker_spot: 1.00 with even rounds against
    0.82, docs/adaptive.md); the rare floor's cover rule, which makes this film's round even, is off here
    (tests/test_auto_rare_floor.py)."""
    monkeypatch.setattr(auto_method, "covered_even_plan", lambda *a, **k: None)
    state, halves = _state(True, "independent")
    on = _plan(state, halves, monkeypatch, True)
    assert np.array_equal(on, _plan(state, halves, monkeypatch, False)) and np.ptp(on) > 4


def test_a_full_vote_keeps_the_allocation(monkeypatch):
    state, halves = _state(False)
    assert np.array_equal(_plan(state, halves, monkeypatch, True), _plan(state, halves, monkeypatch, False))

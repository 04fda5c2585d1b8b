"""gem's uniform share fills the pixels of fewest samples first (option ``uniform_fill``)."""

from __future__ import annotations

import numpy as np
import pytest

from mcrecon.core.stats import PixelStats
from mcrecon.errors import InputError
from mcrecon.methods import get_method
from mcrecon.methods.base import AdaptiveState
from mcrecon.core.nets import fill_lowest


@pytest.mark.parametrize("seed", range(20))
def test_fill_lowest_raises_the_lowest_pixels_to_a_common_level(seed):
    rng = np.random.default_rng(seed)
    cur = rng.integers(0, 12, size=(int(rng.integers(1, 7)), int(rng.integers(1, 7))))
    n = int(rng.integers(0, 150))
    add = fill_lowest(cur, n, rng)
    assert add.shape == cur.shape and add.dtype == np.int64
    assert add.sum() == n and (add >= 0).all()
    raised = add > 0
    if raised.any():
        new = cur + add
        # the raised pixels end within one sample of each other, and no pixel left alone lies below them
        assert new[raised].max() - new[raised].min() <= 1
        assert (cur[~raised] >= new[raised].max() - 1).all()


def test_fill_lowest_tops_up_before_it_spreads():
    cur = np.array([[4, 4, 20, 20]])
    np.testing.assert_array_equal(fill_lowest(cur, 10, np.random.default_rng(0)), [[5, 5, 0, 0]])
    # enough for everyone: a common level everywhere
    np.testing.assert_array_equal(fill_lowest(cur, 40, np.random.default_rng(0)) + cur, [[22, 22, 22, 22]])


def _state(per_pixel, sampler="independent"):
    """Statistics of constant samples, ``per_pixel[y, x]`` of them in each pixel, and a round's state."""
    h, w = per_pixel.shape
    ys, xs = np.nonzero(per_pixel >= 0)
    reps = per_pixel[ys, xs]
    pos = np.stack([np.repeat(xs + 0.5, reps), np.repeat(ys + 0.5, reps)], axis=1)
    st = PixelStats(w, h, subpixels=0)
    st.add(pos, np.full((pos.shape[0], 3), 0.5))
    budget = int(per_pixel.sum()) + 8 * w * h
    return AdaptiveState(st, 1, budget, st.n_samples, np.random.default_rng(0), iteration=7, sampler=sampler)


@pytest.fixture(autouse=True)
def _plans_read_the_estimates(monkeypatch):
    # these states hold one value everywhere: the structure test would make every round uniform
    # (tests/test_uniform_without_structure.py); here the share and the floors are under test
    from mcrecon.methods.base import Method
    monkeypatch.setattr(Method, "structure_test", False)


def test_gem_share_goes_to_the_pixels_left_behind():
    per_pixel = np.full((8, 8), 20)
    per_pixel[:, :4] = 4                        # the left half fell behind
    m = get_method("gem", uniform_share=1.0)    # the whole round is the share (independent: from the bottom)
    counts = m.plan(m.start(8, 8), _state(per_pixel)).counts
    assert counts.sum() == 8 * 64
    assert counts[:, 4:].sum() == 0 and (counts[:, :4] == 16).all()
    # spread evenly, the share gives every pixel the same and leaves the left half behind
    even = get_method("gem", uniform_share=1.0, uniform_fill="even")
    assert (even.plan(even.start(8, 8), _state(per_pixel)).counts == 8).all()
    # a stratified sampler's share stays even by default: a level between two nets buys little
    assert (m.plan(m.start(8, 8), _state(per_pixel, "sobol")).counts == 8).all()


def test_uniform_fill_is_validated():
    with pytest.raises(InputError, match="uniform_fill"):
        get_method("gem", uniform_fill="top")


# ----------------------------------------------------------------------------
# a stratified pixel's rare-component floor (option rare_nets)
# ----------------------------------------------------------------------------

def test_rare_net_floor_is_the_net_that_holds_the_component():
    from mcrecon.core.nets import rare_net_floor
    h, w = 12, 24
    count = np.full((h, w), 4)
    mean = np.full((h, w, 3), 0.05)
    var = np.full((h, w, 3), 1e-6)               # edges and texture: a relative variance far below the gate
    var[:, :8] = 10.0 * 0.05 ** 2 / 4            # a rare component: per-sample relative variance ~ 10
    fl = rare_net_floor(var, mean, count, cap=32, threshold=5.0)
    assert (fl[:, :6] == 32).all()               # 2 r = 20: the net of 32
    assert (fl[:, 11:] == 0).all()               # no neighbour shows the component
    assert (rare_net_floor(var, mean, count, cap=16, threshold=5.0)[:, :6] == 16).all()
    assert not rare_net_floor(var, mean, count, cap=32, threshold=20.0).any()


def _rare_state(sampler, iteration):
    """8 x 8 pixels of 8 samples, one of which found a rare light (relative variance 8), budget 32 spp."""
    h = w = 8
    xs, ys = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    pos = np.repeat(np.stack([xs.ravel(), ys.ravel()], axis=1), 8, axis=0)
    val = np.zeros((pos.shape[0], 3))
    val[::8] = 1.0
    st = PixelStats(w, h, subpixels=0)
    st.add(pos, val)
    return AdaptiveState(st, 1, 32 * w * h, st.n_samples, np.random.default_rng(0), iteration=iteration,
                         sampler=sampler)


@pytest.mark.parametrize("sampler", ["sobol", "independent"])
def test_pixels_are_raised_to_the_rare_components_floor_first(sampler):
    m = get_method("gem")
    # the round (192 samples) is smaller than the floors' 8 more per pixel: it goes to them, evenly
    counts = m.plan(m.start(8, 8), _rare_state(sampler, 0)).counts
    assert counts.sum() == 192 and (counts == 3).all()
    # the last round: every pixel reaches its floor of 16; past it a stratified pixel's greedy counts go
    # in whole nets, independent ones as they fall
    counts = m.plan(m.start(8, 8), _rare_state(sampler, 7)).counts
    total = 8 + counts
    assert counts.sum() == 32 * 64 - 8 * 64 and total.min() >= 16
    pow2 = np.mean((total & (total - 1)) == 0)
    assert pow2 > 0.95 if sampler == "sobol" else pow2 < 0.9
    # without the floor the greedy distribution places the round by its filters' error
    off = get_method("gem", rare_nets=0)
    assert np.ptp(off.plan(off.start(8, 8), _rare_state(sampler, 0)).counts) > 3
    # -1: the floor only where the renderer declares a stratified sampler
    strat = get_method("gem", rare_nets=-1)
    counts = strat.plan(strat.start(8, 8), _rare_state(sampler, 0)).counts
    assert (counts == 3).all() if sampler == "sobol" else np.ptp(counts) > 3


def _half_lit_state(sampler):
    """8 x 40 pixels: the left 16 columns under a rare light (one sample in 8 finds it), the rest dim and
    even (8 samples each, four pixels behind at 4); budget 32 spp, the first adaptive round."""
    h, w = 8, 40
    per_pixel = np.full((h, w), 8)
    per_pixel[2:6, 30] = 4
    ys, xs = np.nonzero(per_pixel > 0)
    reps = per_pixel[ys, xs]
    pos = np.stack([np.repeat(xs + 0.5, reps), np.repeat(ys + 0.5, reps)], axis=1)
    val = np.full((pos.shape[0], 3), 0.05)
    lit = np.flatnonzero(pos[:, 0] < 16)
    val[lit] = 0.0
    val[lit[::8]] = 1.0
    st = PixelStats(w, h, subpixels=0)
    st.add(pos, val)
    return AdaptiveState(st, 1, 32 * w * h, st.n_samples, np.random.default_rng(0), iteration=0, sampler=sampler)


@pytest.mark.parametrize("sampler", ["sobol", "independent"])
def test_pixels_no_floor_holds_keep_a_part_of_the_share(sampler):
    """With a stratified sampler a round the floors' deficit exceeds still gives the pixels no floor holds
    UNHELD_SHARE of their part of the uniform share, from their lowest counts: without it their statistics
    never change and the floor cannot reach a pixel whose first samples missed the light.  Independent
    samples' rounds go to the floors alone (there it is a trade: docs/adaptive.md)."""
    from mcrecon.core.nets import state_rare_net_floor
    from mcrecon.methods.gem.method import UNHELD_SHARE

    m = get_method("gem")
    state = _half_lit_state(sampler)
    floor = state_rare_net_floor(state, threshold=m.rare_gate(state))
    held = floor > 0
    assert held[:, :16].all() and not held[:, 20:].any()
    current = state.stats.count
    n = m.round_size(state)
    assert np.maximum(floor - current, 0).sum() > n            # the floors alone would take the round
    counts = m.plan(m.start(40, 8), state).counts
    k = int(round(UNHELD_SHARE * m.params["uniform_share"] * n * np.mean(~held))) if sampler == "sobol" else 0
    assert counts.sum() == n and counts[~held].sum() == k      # the unheld pixels' part, no more
    if sampler == "sobol":
        behind = counts[2:6, 30]                                # the four behind first, toward the common level
        assert k > 0 and behind.sum() == min(k, 16) and np.ptp(behind) <= 1
    assert counts[held].sum() == n - k and (current + counts <= np.maximum(floor, current))[held].all()


def test_awr_batch_gives_what_is_owed_first():
    from mcrecon.methods.awr.sampling import plan_awr_positions
    st = _rare_state("sobol", 0).stats
    owed = np.full((8, 8), 8)
    owed[0, 0] = 0
    small, _ = plan_awr_positions(st, 100, np.random.default_rng(0), per_coefficient=4, as_counts=True, owed=owed)
    assert small.sum() == 100 and small[0, 0] == 0 and small.max() <= 2     # from the bottom, within what is owed
    big, _ = plan_awr_positions(st, 1000, np.random.default_rng(0), per_coefficient=4, as_counts=True, owed=owed)
    assert big.sum() == 1000 and (big >= owed).all()


@pytest.mark.parametrize("sampler", ["sobol", "independent"])
def test_awr_round_raises_the_rare_components_net_first(sampler):
    # left: a rare light (one sample in 8); right: pixels of larger variance without a rare component.
    # Independent samples: the light in rows 0, 3 and 6 only, so that the left half's samples find it at
    # -ln(1 - 24/80) / 8 = 0.045 a sample, below awr's EVEN_HIT_RATE (their floor still covers most of the film)
    h, w = 8, 16
    xs, ys = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    pos = np.repeat(np.stack([xs.ravel(), ys.ravel()], axis=1), 8, axis=0)
    val = np.zeros((pos.shape[0], 3))
    left = pos[:, 0] < 8
    if sampler == "independent":
        left &= np.isin(np.floor(pos[:, 1]), (0, 3, 6))
    val[left & (np.arange(pos.shape[0]) % 8 == 0)] = 1.0
    left = pos[:, 0] < 8
    # (independent: a per-sample relative variance below 1 on the right, which does not read as the light found)
    lo, hi = (0.5, 1.5) if sampler == "independent" else (0.0, 2.0)
    val[~left] = np.where(np.arange(pos.shape[0])[~left] % 2 == 0, lo, hi)[:, None]
    st = PixelStats(w, h, subpixels=0)
    st.add(pos, val)
    counts = {}
    for floor in (1, 0):
        m = get_method("awr", rare_light_floor=floor)
        state = AdaptiveState(st, 1, 32 * w * h, st.n_samples, np.random.default_rng(0), sampler=sampler)
        counts[floor] = m.plan(m.start(w, h), state).counts
    assert (counts[1][:, :6] >= 8).all()         # the net of 16 that holds the light, first
    assert (counts[0][:, :6] == 0).any()         # without it the larger variance on the right comes first


def test_awr_rounds_are_even_where_a_covering_light_is_found_often():
    from mcrecon.core.nets import hit_rate
    from mcrecon.methods.awr.method import EVEN_HIT_RATE
    # a light found by one sample in 8 at every pixel of the left 12 of 16 columns (its floor covers the
    # film); independent samples find it at 1/8 (every pixel: an infinite estimate), a stratified sampler's
    # round is the floor's
    h, w = 8, 16
    xs, ys = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    pos = np.repeat(np.stack([xs.ravel(), ys.ravel()], axis=1), 8, axis=0)
    val = np.full((pos.shape[0], 3), 0.1)
    val[(pos[:, 0] < 12) & (np.arange(pos.shape[0]) % 8 == 0)] = 20.0
    st = PixelStats(w, h, subpixels=0)
    st.add(pos, val)
    for sampler in ("independent", "sobol"):
        m = get_method("awr")
        state = AdaptiveState(st, 1, 32 * w * h, st.n_samples, np.random.default_rng(0), sampler=sampler)
        counts = m.plan(m.start(w, h), state).counts
        assert (np.ptp(counts) == 0) == (sampler == "independent"), sampler
    # every lit pixel found it: over the lit columns the estimate is infinite, over the film -ln(1 - 12/16) / 8
    assert hit_rate(state, xs < 12) == np.inf
    assert hit_rate(state, np.ones((h, w), bool)) == pytest.approx(np.log(4) / 8) and np.log(4) / 8 > EVEN_HIT_RATE


@pytest.mark.parametrize("p", [0.02, 0.075, 0.2])
def test_awr_hit_rate_reads_the_chance_to_find_the_light(p):
    from mcrecon.core.nets import hit_rate
    # 4000 pixels of 16 samples: a pixel shows the light (a relative variance far above 1) where one of its
    # samples found it, which happens at 1 - (1 - p)^16; the estimate's spread is the binomial share's
    n, k = 16, 4000
    rng = np.random.default_rng(1)
    hits = rng.random((k, n)) < p
    pos = np.repeat(np.stack([np.arange(k) % 80 + 0.5, np.arange(k) // 80 + 0.5], axis=1), n, axis=0)
    val = np.where(hits.ravel(), 50.0, 0.2)[:, None] * np.ones(3)
    st = PixelStats(80, 50, subpixels=0)
    st.add(pos, val)
    state = AdaptiveState(st, 1, 32 * k, st.n_samples, rng, sampler="independent")
    q = 1 - (1 - p) ** n
    se = np.sqrt(q * (1 - q) / k) / ((1 - q) * n)    # the delta method on -ln(1 - s) / n
    assert abs(hit_rate(state, np.ones((50, 80), bool)) - p) < 4 * se


def test_independent_rounds_pay_the_floor_only_where_the_component_covers_most_of_the_film():
    from mcrecon.core.nets import RARE_COVER, rare_net_deficit
    from mcrecon.core.safeguard import RARE_THRESHOLD
    # a rare light (one sample in 8) over the left `lit` columns of 32
    h, w = 8, 32
    xs, ys = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    pos = np.repeat(np.stack([xs.ravel(), ys.ravel()], axis=1), 8, axis=0)
    for lit, covers in ((2, False), (24, True)):
        val = np.zeros((pos.shape[0], 3))
        val[(pos[:, 0] < lit) & (np.arange(pos.shape[0]) % 8 == 0)] = 1.0
        st = PixelStats(w, h, subpixels=0)
        st.add(pos, val)
        state = AdaptiveState(st, 1, 32 * w * h, st.n_samples, np.random.default_rng(0), sampler="independent")
        owed = rare_net_deficit(state, threshold=RARE_THRESHOLD, min_cover=RARE_COVER)
        assert (owed is not None) == covers
        # a stratified sampler's floor applies however little of the film it covers
        owed = rare_net_deficit(state, threshold=RARE_THRESHOLD)
        assert (owed[:, :lit] > 0).all() and not owed[:, lit + 2:].any()

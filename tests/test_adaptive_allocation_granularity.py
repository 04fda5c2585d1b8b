"""How finely an adaptive round hands out samples: awr's pops sized by the budget, counts in whole nets.

awr's sampler with the paper's 64 samples per popped pixel at 32 spp puts
twice the budget's average into each pixel one noisy estimate ranks high,
and leaves the rest at their initial samples (adaptive over uniform 2.4 on
caustic and checker_spot with Sobol samples, docs/adaptive.md).  Its
default pops a quarter of the average spp, as often as the paper's 64 allow.
:mod:`mcrecon.core.nets` rounds a round's counts so that every pixel's total
is a power of two: a full net of a stratified sampler's sequence.
"""

from __future__ import annotations

import numpy as np
import pytest

from mcrecon import adapt
from mcrecon.core.metrics import relative_mse
from mcrecon.core.nets import net_counts, net_round
from mcrecon.core.stats import PixelStats
from mcrecon.methods import get_method
from mcrecon.methods.awr.sampling import plan_awr_positions
from mcrecon.renderers.scenes import SceneRenderer, reference_image


def _pow2(t):
    return (t > 0) & ((t & (t - 1)) == 0)


def test_net_counts_keep_the_round_and_complete_nets():
    rng = np.random.default_rng(3)
    current = rng.choice([4, 8, 16, 16, 32], size=(20, 24))
    desired = rng.integers(0, 12, size=(20, 24)) * (rng.random((20, 24)) < 0.6)
    new = net_counts(desired, current)
    assert new.sum() == desired.sum() and new.min() >= 0
    assert not new[desired == 0].any()                       # no wish, no samples
    stepped = new > 0
    # every stepped pixel ends on a power of two but the one that takes the remainder
    assert (~_pow2(current + new)[stepped]).sum() <= 1


def test_net_counts_step_up_the_pixels_wished_most():
    current = np.full((1, 4), 16)
    new = net_counts(np.array([[12, 4, 0, 0]]), current)
    assert new.tolist() == [[16, 0, 0, 0]]                   # 16 + 12 rounds up to 32; 16 + 4 keeps its net


def test_net_round_spends_the_defensive_share_on_the_fewest_samples_first():
    current = np.array([[4, 8, 16, 4]])
    new = net_round(np.zeros((1, 4), np.int64), current, 8, np.random.default_rng(0))
    assert new.tolist() == [[4, 0, 0, 4]]


def test_awr_pops_a_pixel_of_huge_variance_as_often_as_the_paper_would_fill_it():
    """One pixel of enormous variance: one pop per batch gives it 8 samples, pops up to the paper's 64 give 64."""
    rng = np.random.default_rng(1)
    h = w = 32
    n = 16
    vals = rng.normal(0.5, 0.01, size=(h, w, n, 1))
    vals[5, 7] = rng.normal(0.5, 30.0, size=(n, 1))
    pos = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1)[:, :, None, :] + 0.5
    pos = np.broadcast_to(pos, (h, w, n, 2)).reshape(-1, 2)
    st = PixelStats.from_samples(pos, np.repeat(vals.reshape(-1, 1), 3, axis=1), width=w, height=h)
    kw = dict(per_coefficient=8, as_counts=True, levels=0)
    once, _ = plan_awr_positions(st, 4 * h * w, np.random.default_rng(0), **kw)
    many, _ = plan_awr_positions(st, 4 * h * w, np.random.default_rng(0), pixel_pops=8, **kw)
    assert once[5, 7] == 8 and many[5, 7] == 64
    assert once.sum() == many.sum() == 4 * h * w


def test_awr_default_pops_a_quarter_of_the_budget_and_paper_keeps_64():
    assert get_method("awr").params["per_coefficient"] == 0
    assert get_method("awr", variant="paper").params["per_coefficient"] == 64
    left = {}
    for pc in (0, 64):
        res = adapt(SceneRenderer("soft_shadow", width=24, height=24, seed=0), get_method("awr", per_coefficient=pc),
                    spp=32, seed=0, progress=False, track_error=False)
        assert int(res.stats.count.sum()) == 32 * 24 * 24
        left[pc] = float((res.stats.count == 16).mean())        # pixels that kept only the initial pass
    print(left)
    assert left[0] < 0.5 * left[64]


def test_net_counts_give_flat_sobol_pixels_their_full_nets(monkeypatch):
    """A constant-per-pixel integrand is exact on a full net: gem's adaptive counts rounded to nets
    keep it exact, counts between powers of two do not (the allocation, planned even where the samples
    show no structure)."""
    from mcrecon.methods.base import Method

    monkeypatch.setattr(Method, "structure_test", False)
    w = h = 24
    ref = reference_image("flat", w, h)
    err = {}
    for net in (0, 1):
        res = adapt(SceneRenderer("flat", width=w, height=h, seed=0, sampler="sobol"),
                    get_method("gem", net_counts=net), spp=16, seed=0, progress=False, track_error=False)
        c = res.stats.count
        if net:
            assert _pow2(c).mean() > 0.95
        err[net] = relative_mse(res.image, ref)
    assert err[1] < 0.5 * err[0]                              # measured 0.26 (8.6e-7 against 3.4e-6)


@pytest.mark.slow
def test_awr_sobol_caustic_adaptive_within_reach_of_uniform():
    """128^2, 32 spp, Sobol, seed 0: adaptive over uniform 2.2 with the paper's 64 per pop, 1.2 now."""
    from mcrecon import reconstruct
    from mcrecon.core.requests import SampleRequest
    from mcrecon.core.samples import SampleSet

    w = h = 128
    ref = reference_image("caustic", w, h)
    b = SceneRenderer("caustic", width=w, height=h, seed=0, sampler="sobol").render(
        SampleRequest(w, h, counts=np.full((h, w), 32)))
    uni = relative_mse(reconstruct(SampleSet(b.positions, b.values, width=w, height=h), method="awr"), ref)
    res = adapt(SceneRenderer("caustic", width=w, height=h, seed=0, sampler="sobol"), get_method("awr"), spp=32,
                seed=0, progress=False, track_error=False)
    assert relative_mse(res.image, ref) / uni < 1.5


def test_net_counts_complete_the_lowest_nets_first():
    """A step from 16 to 32 stratified samples pays more than one from 32 to 64: the pixel wished at 16
    steps up first, though the one at 32 wishes a larger fraction of its step."""
    new = net_counts(np.array([[8, 0, 24]]), np.array([[16, 16, 32]]))
    assert new.tolist() == [[16, 0, 16]]                     # by the fraction alone: [[0, 0, 32]]

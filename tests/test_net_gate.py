"""The net gate (:func:`mcrecon.core.nets.net_plan`): a round in whole nets is the even round
(:func:`~mcrecon.core.nets.even_round`) unless its planned totals are predicted to err less.

In whole Sobol nets an allocation that raises one pixel from 32 to 64 samples leaves two at 16, where a
reconstruction errs 1.7x its error at 32 (awr on depth_of_field-1: adaptive 1.12x the uniform render's
relMSE, docs/adaptive.md).  The prediction is each pixel's error of the method's own reconstruction of its
prefix halves (:func:`~mcrecon.core.nets.halves_error`), scaled as ``(n / t)^NET_RATE``
(:func:`~mcrecon.core.nets.beats_even`)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import uniform_filter

from mcrecon import adapt
from mcrecon.core.metrics import relative_mse
from mcrecon.core.nets import NET_RATE, beats_even, halves_error, net_plan
from mcrecon.core.stats import PixelStats
from mcrecon.core.strata import PrefixHalves
from mcrecon.methods import get_method
from mcrecon.methods.base import AdaptiveState, Method
from mcrecon.renderers.scenes import SceneRenderer, get_scene, reference_image


def test_beats_even_prices_two_pixels_left_behind_against_one_raised():
    """Four pixels at 16 samples, 32 more to give: the plan raises pixel 0 to 48 (a net of 32 plus part of the
    next is priced as its total), the even round pixels 0 and 1 to 32.  Plan: e0 (16/48)^r + e1; even:
    (e0 + e1) (1/2)^r; the plan wins only where e0 exceeds e1 by the factor where the two are equal."""
    n = np.full((1, 4), 16.0)
    cur = np.full((1, 4), 16)
    plan, even = cur + np.array([[32, 0, 0, 0]]), cur + np.array([[16, 16, 0, 0]])
    r = NET_RATE
    equal = (1 - 0.5 ** r) / (0.5 ** r - (1 / 3) ** r)      # e0 / e1 where the predictions are equal
    for ratio, wins in ((equal * 1.05, True), (equal * 0.95, False), (1.0, False)):
        e = np.array([[ratio, 1.0, 1.0, 1.0]])
        assert beats_even((e, n), plan, even) is wins, ratio
    # an allocation serving uniform errors never beats the even round's counts
    assert not beats_even((np.ones((1, 4)), n), cur + np.array([[16, 16, 0, 0]]), even)


def _state(values, counts, budget):
    """An adaptive state of samples ``values[p]`` (in each pixel's sequence order) at pixels of a 16x16 film."""
    h = w = 16
    pix = np.repeat(np.arange(h * w), counts.ravel())
    pos = np.stack([pix % w + 0.5, pix // w + 0.5], axis=1)
    st = PixelStats(w, h)
    st.add(pos, values)
    strata = PrefixHalves(w, h, 3)
    strata.add(pos, values)
    return AdaptiveState(st, 1, budget, int(counts.sum()), np.random.default_rng(0), strata=strata,
                         sampler="sobol"), pix


def test_halves_error_of_the_pixel_mean_is_the_smoothed_squared_half_difference():
    """box reconstructs the pixel means: its error is ((m_A - m_B) / 2)^2 over the squared 5x5 mean + 0.01,
    averaged over the channels and the 5x5 box, at the prefix's count (16 of 24 samples: the last net)."""
    rng = np.random.default_rng(4)
    counts = np.full((16, 16), 24)
    values = rng.uniform(0.0, 1.0, (int(counts.sum()), 3)) * np.array([1.0, 2.0, 0.5])
    state, pix = _state(values, counts, 32 * 256)
    e, n = halves_error(get_method("box"), None, state)
    assert np.array_equal(n, np.full((16, 16), 16.0))
    v = values.reshape(256, 24, 3)
    d = ((v[:, :8].mean(axis=1) - v[:, 8:16].mean(axis=1)) / 2).reshape(16, 16, 3)
    mu = uniform_filter(v.mean(axis=1).reshape(16, 16, 3), size=(5, 5, 1), mode="nearest")
    want = uniform_filter((d ** 2 / (mu ** 2 + 0.01)).mean(axis=2), size=5, mode="nearest")
    np.testing.assert_allclose(e, want, rtol=1e-12)


class _Planner:
    """A method whose allocation wishes 16 more samples on the top four rows and reconstructs the pixel means."""
    net_gate = True
    params = {"uniform_share": 0.0}

    def round_size(self, state):
        return 4 * 256

    def place(self, run, state, n):
        wish = np.zeros((16, 16), np.int64)
        wish[:4] = n // 64
        return wish

    def reconstruct_run(self, run, inputs):
        return inputs.stats.mean.copy()

    def even_under_rare(self, run, state):   # Method's default: a rare component keeps the plan's round
        return False


@pytest.mark.parametrize("rare", [False, True])
def test_net_plan_gives_the_even_round_unless_a_rare_component_shows(rare):
    """The plan raises the four rows of least noise, so the even round (every pixel's next net, lowest first,
    ties at random: 64 pixels step from 16 to 32) is predicted to err less and is the round.  Where a
    neighbourhood shows a rare bright component (one sample in 16 a hundred times the rest) the halves miss
    it as the pixels' samples do, so the plan stands (the four rows step to 32)."""
    rng = np.random.default_rng(2)
    counts = np.full((16, 16), 16)
    values = rng.uniform(0.4, 0.6, (16, 16, 16, 3))
    values[:4] = rng.uniform(0.49, 0.51, (4, 16, 16, 3))
    values = values.reshape(-1, 3)
    if rare:
        values.reshape(16, 16, 16, 3)[10:13, 10:13, 5] = 50.0
    state, _ = _state(values, counts, 32 * 256)
    new = net_plan(_Planner(), None, state).counts
    assert new.sum() == 4 * 256 and set(np.unique(new)) == {0, 16}
    assert bool((new[:4] == 16).all()) == rare


sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))


def _dof1():
    """The corpus's held-out depth_of_field-1 lens (aperture 1.21, focus band 0.094) at 48x48."""
    import corpus

    e = next(x for x in corpus.scenes("all", None) if x.name == "builtin-depth_of_field-1")
    return get_scene(e.family, e.params)


def _run(scene, gate, seed, monkeypatch, size=48):
    monkeypatch.setattr(Method, "net_gate", gate)
    return adapt(SceneRenderer(scene, width=size, height=size, seed=seed, sampler="sobol"), get_method("awr"),
                 spp=32, seed=seed, progress=False, track_error=False)


@pytest.mark.parametrize("seed", [0, 1])
def test_awr_on_a_wide_defocus_ends_at_uniform_counts(seed, monkeypatch):
    """depth_of_field-1, Sobol: the allocation's preference is weak, so the gate gives even rounds and every
    pixel ends at 32 (a uniform render's counts); without it a fifth of the pixels stay at 16 and the image errs
    more (seeds 0 and 1: 0.000788 and 0.000770 against 0.000775 and 0.000758)."""
    scene = _dof1()
    ref = reference_image(scene, 48, 48)
    on, off = _run(scene, True, seed, monkeypatch), _run(scene, False, seed, monkeypatch)
    assert np.array_equal(on.stats.count, np.full((48, 48), 32))
    assert (off.stats.count == 16).mean() > 0.15
    assert relative_mse(on.image, ref) < relative_mse(off.image, ref)


def test_awr_keeps_an_allocation_that_serves_far_larger_errors(monkeypatch):
    """checker_dof, Sobol: the pixels awr raises err far more than those it leaves, and the gate lets it."""
    on, off = _run("checker_dof", True, 0, monkeypatch), _run("checker_dof", False, 0, monkeypatch)
    assert np.array_equal(on.stats.count, off.stats.count)
    assert np.ptp(on.stats.count) > 0


def test_the_paper_variant_plans_without_the_gate(monkeypatch):
    counts = []
    for gate in (True, False):
        monkeypatch.setattr(Method, "net_gate", gate)
        res = adapt(SceneRenderer(_dof1(), width=32, height=32, seed=0, sampler="sobol"),
                    get_method("awr", variant="paper", net_counts=1), spp=32, seed=0, progress=False,
                    track_error=False)
        counts.append(res.stats.count)
    assert np.array_equal(*counts)

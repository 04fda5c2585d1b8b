"""Adaptive allocation reads the stratification gain of the committed samples (AdaptiveState.strata)."""

from __future__ import annotations

import numpy as np

from mcrecon import adapt
from mcrecon.methods import get_method
from mcrecon.core.strata import stratified_gain
from mcrecon.methods.gem.method import GEMMethod
from mcrecon.renderers.scenes import SceneRenderer

_W = _H = 32


def _states(monkeypatch, cls, sampler, **opts):
    seen = []
    place = cls.place

    def spy(self, run, state, n):
        seen.append((state.stats.count.copy(), None if state.strata is None else state.strata.counter.copy(),
                     stratified_gain(state)))
        return place(self, run, state, n)

    with monkeypatch.context() as m:
        m.setattr(cls, "place", spy)
        res = adapt(SceneRenderer("checker_wall", width=_W, height=_H, seed=0, sampler=sampler), get_method(cls.name, **opts), spp=32,
                    seed=0, track_error=False, progress=False)
    return seen, res


def test_plans_see_the_committed_samples_prefix_halves(monkeypatch):
    seen, _ = _states(monkeypatch, GEMMethod, "sobol")
    assert seen
    for count, counter, gain in seen:
        assert np.array_equal(counter.reshape(count.shape), count)  # every committed sample, in its pixel
        assert gain.shape == count.shape and np.all((gain > 0) & (gain <= 1))


def test_gain_tells_stratified_from_independent_samples(monkeypatch):
    sob, _ = _states(monkeypatch, GEMMethod, "sobol")
    ind, _ = _states(monkeypatch, GEMMethod, "independent")
    # checker_wall's edges: a net resolves them, so its pixel means err far below s^2 / n
    assert np.median(sob[-1][2]) < 0.5
    assert np.median(ind[-1][2]) > 0.7


def test_allocation_uses_the_gain_and_the_paper_does_not(monkeypatch):
    _, on = _states(monkeypatch, GEMMethod, "sobol")
    _, off = _states(monkeypatch, GEMMethod, "sobol", stratified_gain=0)
    _, paper = _states(monkeypatch, GEMMethod, "sobol", variant="paper")
    assert not np.array_equal(on.counts, off.counts)
    assert paper.method.params["stratified_gain"] == 0


def test_only_methods_reading_the_gain_keep_the_prefix_halves(monkeypatch):
    seen, _ = _states(monkeypatch, GEMMethod, "sobol", variant="paper")
    assert seen and all(counter is None and gain is None for _, counter, gain in seen)

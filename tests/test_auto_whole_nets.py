"""auto's adaptive rounds (GEM's placement) follow the renderer's sampler as awr's do: whole nets where it
declares a stratified sampler (``net_counts=-1``, the default), the counts as they fall for independent
samples; an explicit ``net_counts`` wins."""

from __future__ import annotations

import numpy as np

import mcrecon
from mcrecon.methods import get_method
from mcrecon.methods.base import Method

from helpers import jittered_renderer

W = H = 16


def _film(sampler):
    """A cheap renderer: an edge and noise, the declared ``sampler``."""
    film = jittered_renderer(lambda pos, rng, req: np.where(pos[:, :1] < W / 2, 0.2, 1.0)
                             * rng.uniform(0.5, 1.5, (len(pos), 3)), width=W, height=H)
    film.sampler = sampler
    return film


def _counts(sampler, **opts):
    m = get_method("auto", candidates="box,gauss", **opts)
    return mcrecon.adapt(_film(sampler), m, spp=24, seed=1, progress=False, track_error=False).stats.count


def _pow2_share(counts):
    c = counts.ravel()
    return float(((c & (c - 1)) == 0).mean())


def test_auto_spends_whole_nets_for_a_stratified_renderer(monkeypatch):
    # the allocation's own counts: the net gate (tests/test_net_gate.py) would make this noisy edge's rounds even
    monkeypatch.setattr(Method, "net_gate", False)
    sobol, indep = _counts("sobol"), _counts("independent")
    assert sobol.sum() == indep.sum() == 24 * W * H
    assert _pow2_share(sobol) > 0.9
    assert _pow2_share(indep) < 0.7
    assert np.array_equal(_counts("sobol", net_counts=0), indep)
    assert np.array_equal(_counts("independent", net_counts=1), sobol)

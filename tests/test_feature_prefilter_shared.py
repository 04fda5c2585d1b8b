"""A half's prefiltered features are computed once and shared by the regression candidates and OIDN's aux."""

from __future__ import annotations

import numpy as np
from mcrecon.core.fill import mean_variance_policy
from mcrecon.filters import nlmeans as nlm
from mcrecon.methods.auto import blackbox, features
from mcrecon.renderers import scenes

from helpers import checker_wall_halves

N = 40


def _halves(seed=0):
    return checker_wall_halves(N, seed)


def _own_aux(st):
    """OIDN's aux as prefiltered on their own: albedo and normal only (the reference the shared planes match)."""
    f = np.concatenate([features._filled(st.features[n].mean, st.features[n].count) for n in ("albedo", "normal")],
                       axis=2)
    v = np.concatenate([mean_variance_policy(st.features[n]) for n in ("albedo", "normal")], axis=2)
    pf = nlm.nlmeans_filter(f, f, v, radius=5, patch=3, k=0.5)
    return pf[..., :3], pf[..., 3:]


def test_the_prefilter_weighs_each_channel_alone_so_a_subset_of_planes_is_bit_identical():
    rng = np.random.default_rng(3)
    f = rng.random((24, 20, 5))
    v = rng.random((24, 20, 5)) * 0.01
    whole = nlm.nlmeans_filter(f, f, v, radius=5, patch=3, k=0.5)
    part = nlm.nlmeans_filter(f[..., 1:4], f[..., 1:4], v[..., 1:4], radius=5, patch=3, k=0.5)
    assert np.array_equal(whole[..., 1:4], part)


def test_oidn_aux_of_a_half_reads_the_feature_candidates_planes_bit_identically():
    hv = _halves()
    st = hv.a
    ref = _own_aux(st)
    assert features.prefiltered_features(st, stored_only=True) is None
    fresh = blackbox.oidn_aux(st)                       # nothing stored yet: its own prefilter
    pf = features.prefiltered_features(st)              # the feature candidates' (every feature)
    assert pf.shape[2] == sum(st.features[n].mean.shape[2] for n in st.feature_names) > 6
    shared = blackbox.oidn_aux(st)
    for a, b, c in zip(ref, fresh, shared):
        assert np.array_equal(a, b) and np.array_equal(a, c)


def test_a_buffer_is_prefiltered_once_for_auto(monkeypatch):
    hv = _halves(seed=1)
    calls = []
    real = nlm.nlmeans_filter

    def counting(image, *a, **k):
        calls.append(np.shape(image))
        return real(image, *a, **k)

    monkeypatch.setattr(nlm, "nlmeans_filter", counting)
    features.feature_candidates(("nfor", "nfor_own"), hv.a, hv.b)
    n_after_candidates = len(calls)
    assert n_after_candidates == 2        # one prefilter per half
    blackbox.oidn_aux(hv.a)
    blackbox.oidn_aux(hv.b)
    assert len(calls) == n_after_candidates


def test_stored_planes_go_stale_when_the_buffer_takes_more_samples():
    hv = _halves(seed=2)
    st = hv.a
    features.prefiltered_features(st)
    assert features.prefiltered_features(st, stored_only=True) is not None
    b = scenes.render_uniform("checker_wall", width=N, height=N, spp=1, seed=9, features=True)
    st.add(b.positions, b.values, features=b.features)
    assert features.prefiltered_features(st, stored_only=True) is None

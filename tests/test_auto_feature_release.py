"""What auto with features lets go of during a frame: each feature candidate stored as it is built, no
unfiltered feature planes where the prefiltered ones are stored, and a dispatcher's halves' feature
statistics dropped past their last reader, with the same image."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from mcrecon.core.samples import SampleSet
from mcrecon.methods import get_method
from mcrecon.methods.auto import features
from mcrecon.methods.auto.passes import _stored
from mcrecon.offline.inputs import gather_inputs

from helpers import checker_wall_halves

N = 24


def test_each_feature_candidate_is_stored_as_it_is_built_with_the_stored_values_of_the_unstored_run():
    hv = checker_wall_halves(N, 7)
    names = ("nfor", "nfor_own", "dnlm", "mix")
    plain = features.feature_candidates(names, hv.a, hv.b)
    built = []

    def store(c):
        # the candidates built before this one are stored already when it arrives
        assert all(b.image.dtype == np.float32 for b in built)
        c.image, c.mse = _stored(c.image), _stored(c.mse)
        built.append(c)
        return c

    got = features.feature_candidates(names, hv.a, hv.b, store=store)
    assert [c.name for c in got] == [c.name for c in plain] and len(built) == len(plain)
    for g, p in zip(got, plain):
        assert g.image.dtype == np.float32
        assert np.array_equal(g.image, _stored(p.image)) and np.array_equal(g.mse, _stored(p.mse), equal_nan=True)


def test_the_regressions_build_no_unfiltered_feature_planes_where_the_prefiltered_ones_are_stored(monkeypatch):
    hv = checker_wall_halves(N, 8)
    want = {c.name: c for c in features.feature_candidates(("nfor", "nfor_own"), hv.a, hv.b)}
    features.release_prefiltered(hv.a, hv.b)
    features.prefiltered_features(hv.a)
    features.prefiltered_features(hv.b)
    calls = []
    real = features._feature_planes
    monkeypatch.setattr(features, "_feature_planes", lambda st: calls.append(st) or real(st))
    got = {c.name: c for c in features.feature_candidates(("nfor", "nfor_own"), hv.a, hv.b)}
    assert calls == []
    for name, c in want.items():
        assert np.array_equal(got[name].image, c.image) and np.array_equal(got[name].mse, c.mse, equal_nan=True)


def _sample_set(seed=4):
    from mcrecon.renderers import scenes

    b = scenes.render_uniform("checker_wall", width=N, height=N, spp=8, seed=seed, features=True)
    return SampleSet(b.positions, b.values, width=N, height=N, features=b.features)


def test_the_dispatchers_halves_keep_only_the_albedo_from_oidn_on_with_the_same_image(monkeypatch):
    pytest.importorskip("pyoidn", reason="needs pyoidn (Intel OIDN), a dependency of mcrecon: pip install -e .")
    from mcrecon.methods.auto import method as auto_method

    seen = []
    real = auto_method.oidn_candidate
    monkeypatch.setattr(auto_method, "oidn_candidate",
                        lambda name, stats, v, halves, **kw: seen.append(halves.a.feature_names) or
                        real(name, stats, v, halves, **kw))
    m = get_method("auto")
    inputs = gather_inputs(_sample_set(), m)
    hv, stats = inputs.halves, inputs.stats
    assert hv.transient and set(hv.a.feature_names) == {"albedo", "normal", "depth"}
    # the same split held on by its caller (not transient): it keeps every feature
    kept = gather_inputs(_sample_set(), m)
    kept.halves.transient = False
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        img = np.asarray(m.reconstruct(inputs))
        ref = np.asarray(m.reconstruct(kept))
    # the normal and depth went once their last reader was done, the albedo after dnlm (the selection
    # reads its merge); the image is the same bits, so nothing read them after (their reads would find
    # them missing)
    assert hv.a.feature_names == hv.b.feature_names == ()
    # OIDN (its albedo and normal from the stored prefiltered planes) already met the halves without them
    assert seen[:2] == [("albedo",)] * 2 and seen[2:] == [("albedo", "normal", "depth")] * 2
    assert tuple(stats.features) == ("albedo",)
    assert set(kept.halves.a.feature_names) == {"albedo", "normal", "depth"}
    assert np.array_equal(img, ref)


def test_the_release_is_refused_for_halves_that_live_on():
    hv = checker_wall_halves(N, 9)
    assert not hv.transient
    assert hv.release_features(keep=("albedo",)) is False
    assert set(hv.a.feature_names) == {"albedo", "normal", "depth"}
    hv.transient = True
    merged = hv.a.merged(hv.b, features_on_read=True)
    assert hv.release_features(keep=("albedo",), merged=merged) is True
    assert hv.a.feature_names == hv.b.feature_names == tuple(merged.features) == ("albedo",)
    assert np.array_equal(merged.features["albedo"].mean, hv.a.merged(hv.b).features["albedo"].mean)


def test_the_regression_of_colours_given_apart_is_that_of_their_concatenation():
    from mcrecon.filters.regression import collaborative_regression

    rng = np.random.default_rng(3)
    a, b = rng.gamma(2.0, 1.0, (12, 14, 3)), rng.gamma(2.0, 1.0, (12, 14, 3))
    v, f = rng.uniform(0.1, 0.2, (12, 14, 3)), rng.uniform(0, 1, (12, 14, 4))
    kw = dict(radius=3, patch=1, k=1.0, variance_scale=1.0, return_centre_weight=True)
    want = collaborative_regression(np.concatenate([a, b], axis=2), a, v, f, **kw)
    got = collaborative_regression([a, b], a, v, f, **kw)
    assert all(np.array_equal(x, y) for x, y in zip(got, want))
    with pytest.raises(ValueError, match="shapes differ"):
        collaborative_regression([a, b[:-1]], a, v, f, **kw)

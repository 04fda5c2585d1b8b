"""How many times auto runs the denoiser: OIDN with the albedo and normal replaces the colour-only OIDN."""

from __future__ import annotations

import warnings

import numpy as np

import pytest

import mcrecon
from mcrecon.renderers import scenes

pytest.importorskip("pyoidn", reason="needs pyoidn (Intel OIDN), a dependency of mcrecon: pip install -e .")

from mcrecon.methods.auto import blackbox, features  # noqa: E402

N = 24


def _samples(features: bool):
    b = scenes.render_uniform("checker_wall", width=N, height=N, spp=8, seed=4, features=features)
    return mcrecon.SampleSet(b.positions, b.values, width=N, height=N, features=b.features if features else None)


def _run(ss, monkeypatch, **options):
    """auto's reconstruction of ``ss``: (its candidate names, the denoiser calls as (with aux, clean_aux))."""
    calls = []
    real = blackbox.oidn_denoise

    def counting(colour, aux=(), **kw):
        calls.append(len(aux))
        return real(colour, aux, **kw)

    monkeypatch.setattr(blackbox, "oidn_denoise", counting)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec = mcrecon.reconstruct(ss, method="auto", full=True, **options)
    return rec.run.candidate_names, calls


def test_with_an_albedo_colour_only_oidn_runs_on_the_halves_alone(monkeypatch):
    names, calls = _run(_samples(True), monkeypatch)
    assert {"oidn_halves", "oidn_aux", "oidn_aux_halves"} <= set(names)
    assert "oidn" not in names
    assert calls == [0, 0, 2, 2, 2]     # colour on each half; with albedo and normal on all the samples and each half


def test_without_features_the_colour_only_oidn_stays(monkeypatch):
    names, calls = _run(_samples(False), monkeypatch)
    assert {"oidn", "oidn_halves"} <= set(names)
    assert calls == [0, 0, 0]


def test_without_oidn_aux_the_colour_only_oidn_stays_beside_the_features(monkeypatch):
    names, calls = _run(_samples(True), monkeypatch, feature_candidates="dnlm")
    assert {"oidn", "oidn_halves", "dnlm"} <= set(names)
    assert calls == [0, 0, 0]



def test_all_the_samples_aux_is_the_halves_prefiltered_planes_merged_not_a_third_prefilter(monkeypatch):
    from mcrecon.core.fill import mean_variance_policy
    from mcrecon.core.halves import split_halves
    from mcrecon.filters import nlmeans as nlm

    ss = _samples(True)
    hv = split_halves(ss, features=tuple(ss.features))
    st = hv.merged()
    features.prefiltered_features(hv.a), features.prefiltered_features(hv.b)   # the feature candidates' prefilters
    a, b = blackbox.oidn_aux(hv.a), blackbox.oidn_aux(hv.b)
    calls, seen = [], []
    real_nlm, real_oidn = nlm.nlmeans_filter, blackbox.oidn_denoise
    monkeypatch.setattr(nlm, "nlmeans_filter", lambda *a_, **k: calls.append(1) or real_nlm(*a_, **k))
    monkeypatch.setattr(blackbox, "oidn_denoise", lambda c, aux=(), **k: seen.append(aux) or real_oidn(c, aux, **k))
    blackbox.oidn_candidate("oidn_aux", st, mean_variance_policy(st), hv, aux=True)
    assert calls == []                                       # no prefilter of all the samples' features
    n = hv.a.count + hv.b.count
    wa = np.where(n > 0, hv.a.count / np.maximum(n, 1), 0.5)[..., None]
    for got, pa, pb in zip(seen[0], a, b):                   # the first run: OIDN on all the samples
        np.testing.assert_allclose(got, wa * pa + (1 - wa) * pb, rtol=1e-15, atol=0)
    assert [len(s) for s in seen] == [2, 2, 2]


def test_the_halves_average_alone_is_the_same_candidate_as_beside_oidn_on_all_the_samples():
    from mcrecon.core.fill import mean_variance_policy
    from mcrecon.core.halves import split_halves

    ss = _samples(False)
    hv = split_halves(ss)
    st = hv.merged()
    v = mean_variance_policy(st)
    both = blackbox.oidn_candidate("oidn", st, v, hv)
    (alone,) = blackbox.oidn_candidate("oidn", st, v, hv, halves_only=True)
    assert [c.name for c in both] == ["oidn", "oidn_halves"] and alone.name == "oidn_halves"
    np.testing.assert_array_equal(alone.image, both[1].image)
    np.testing.assert_array_equal(alone.mse, both[1].mse)

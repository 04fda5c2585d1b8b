"""auto runs OIDN before the feature regressions, so its scratch memory meets only the statistics, and the
choice sees the same candidates in the same order, with the same images and estimates."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from mcrecon.filters import regression
from mcrecon.methods import get_method
from mcrecon.methods.auto import blackbox, features

from helpers import checker_wall_halves

pytest.importorskip("pyoidn", reason="needs pyoidn (Intel OIDN), a dependency of mcrecon: pip install -e .")

N = 24


def _halves(seed=7):
    return checker_wall_halves(N, seed)


def _candidates(hv):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cands, *_ = get_method("auto")._candidates(hv.merged(), hv, "drop")
    return cands


def test_every_oidn_run_comes_before_the_first_regression(monkeypatch):
    calls = []
    real_oidn, real_reg = blackbox.oidn_denoise, regression.collaborative_regression

    def oidn(*a, **k):
        calls.append("oidn")
        return real_oidn(*a, **k)

    def reg(*a, **k):
        calls.append("regression")
        return real_reg(*a, **k)

    monkeypatch.setattr(blackbox, "oidn_denoise", oidn)
    monkeypatch.setattr(regression, "collaborative_regression", reg)
    names = [c.name for c in _candidates(_halves())]
    assert calls.count("oidn") == 5 and "regression" in calls
    assert calls.index("regression") > max(i for i, c in enumerate(calls) if c == "oidn")
    # listed in choice order all the same: colour candidates, then the feature-guided ones, OIDN's aux last
    assert names[0] == "box" and names.index("oidn_halves") < names.index("nfor") < names.index("oidn_aux")
    assert names[-2:] == ["oidn_aux", "oidn_aux_halves"]


def test_oidn_aux_reads_the_same_planes_whether_or_not_the_regressions_prefiltered_them_first():
    hv = _halves(seed=8)
    st = hv.merged()
    v = features.mean_variance_policy(st)
    features.release_prefiltered(hv.a, hv.b)
    alone = blackbox.oidn_candidate("oidn_aux", st, v, hv, aux=True)
    features.prefiltered_features(hv.a)
    features.prefiltered_features(hv.b)
    shared = blackbox.oidn_candidate("oidn_aux", st, v, hv, aux=True)
    features.release_prefiltered(hv.a, hv.b)
    for x, y in zip(alone, shared):
        assert x.name == y.name
        assert np.array_equal(x.image, y.image) and np.array_equal(x.mse, y.mse, equal_nan=True)

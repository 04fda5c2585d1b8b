"""What auto with features lets go of once used: the same candidates, fewer arrays held through the selection."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from mcrecon.methods import get_method
from mcrecon.methods.auto import features
from mcrecon.methods.auto.estimates import cross_validation_mse

from helpers import checker_wall_halves

N = 24


def _halves(seed=5):
    return checker_wall_halves(N, seed)


def test_the_halves_prefiltered_planes_are_not_held_after_the_candidates():
    pytest.importorskip("pyoidn", reason="needs pyoidn (Intel OIDN), a dependency of mcrecon: pip install -e .")
    hv = _halves()
    m = get_method("auto")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cands, *_ = m._candidates(hv.merged(), hv, "drop")
    assert {"nfor", "mix50", "oidn_aux"} <= {c.name for c in cands}
    assert features.prefiltered_features(hv.a, stored_only=True) is None
    assert features.prefiltered_features(hv.b, stored_only=True) is None


def test_the_mixes_built_one_at_a_time_are_the_weighted_halves_scored_by_cross_validation():
    hv = _halves(seed=6)
    cands = {c.name: c for c in features.feature_candidates(("nfor_own", "dnlm", "mix"), hv.a, hv.b)}
    assert list(cands) == ["nfor_own", "dnlm", "mix33", "mix50", "mix67"]
    pa, pb = features._HalfPlanes(hv.a), features._HalfPlanes(hv.b)
    ra, rb = features.feature_guided_half("nfor_own", pa), features.feature_guided_half("nfor_own", pb)
    da, db = features.feature_guided_half("dnlm", pa), features.feature_guided_half("dnlm", pb)
    for w in features.MIX_WEIGHTS:
        a, b = w * ra + (1.0 - w) * da, w * rb + (1.0 - w) * db
        want = features.dual_candidate("mix", a, b, cross_validation_mse(a, hv.b.mean, pb.variance),
                                       cross_validation_mse(b, hv.a.mean, pa.variance), hv.a.count, hv.b.count)
        got = cands[f"mix{round(100 * w)}"]
        assert np.array_equal(got.image, want.image) and np.array_equal(got.mse, want.mse, equal_nan=True)

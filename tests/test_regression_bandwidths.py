"""Several bandwidths of one collaborative regression in one pass equal one regression per bandwidth, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from mcrecon.filters.regression import collaborative_regression, collaborative_regressions
from mcrecon.methods.nfor.pipeline import cross_regression

from nfor_reference import collaborative_regression_reference


def _inputs(seed=0, h=21, w=18, nf=3):
    rng = np.random.default_rng(seed)
    y = rng.gamma(2.0, 1.0, size=(h, w, 3))
    guide = y + rng.normal(0, 0.4, size=(h, w, 3))
    var = rng.uniform(0.05, 0.3, size=(h, w, 3))
    feats = rng.uniform(0, 1, size=(h, w, nf))
    return y, guide, var, feats


@pytest.mark.parametrize("extras", [(False, False), (True, True)])
def test_bandwidths_in_one_pass_equal_one_call_each(extras):
    y, guide, var, feats = _inputs()
    rw, rc = extras
    ks = (0.5, 1.0, 0.7)
    got = collaborative_regressions(y, guide, var, feats, ks=ks, radius=3, patch=1, return_weights=rw,
                                    return_centre_weight=rc)
    assert len(got) == len(ks)
    for k, g in zip(ks, got):
        alone = collaborative_regression(y, guide, var, feats, radius=3, patch=1, k=k, return_weights=rw,
                                         return_centre_weight=rc)
        for a, b in zip(g if rw else (g,), alone if rw else (alone,)):
            assert np.array_equal(a, b)


def test_bandwidths_in_one_pass_match_the_reference_kernels_and_do_not_depend_on_threads():
    y, guide, var, feats = _inputs(1, h=40, w=23)
    one = collaborative_regressions(y, guide, var, feats, ks=(0.5, 1.0), radius=4, patch=2, threads=1)
    two = collaborative_regressions(y, guide, var, feats, ks=(0.5, 1.0), radius=4, patch=2, threads=2)
    for k, a, b in zip((0.5, 1.0), one, two):
        assert np.array_equal(a, b)
        ref = collaborative_regression_reference(y, guide, var, feats, radius=4, patch=2, k=k)
        np.testing.assert_allclose(a, ref, rtol=1e-9, atol=1e-12)


def test_nfor_cross_regression_of_several_bandwidths_equals_one_per_bandwidth():
    y_a, guide, var, feats = _inputs(2)
    y_b = guide
    pf_a, pf_b = feats, feats[::-1].copy()
    many_a, many_b = cross_regression(y_a, y_b, var, pf_a, pf_b, radius=3, k=(0.5, 1.0))
    for k, ca, cb in zip((0.5, 1.0), many_a, many_b):
        one_a, one_b = cross_regression(y_a, y_b, var, pf_a, pf_b, radius=3, k=k)
        assert np.array_equal(ca, one_a) and np.array_equal(cb, one_b)


def test_no_bandwidth_is_refused():
    y, guide, var, feats = _inputs()
    with pytest.raises(ValueError):
        collaborative_regressions(y, guide, var, feats, ks=(), radius=2)

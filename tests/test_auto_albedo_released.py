"""Past auto's last half-buffer reader of the albedo (dnlm) only its merge is read (the selection's albedo
divisor): the halves' albedo statistics go and the merge keeps its own, the same bits as a merge on read."""

import weakref

import numpy as np

from helpers import checker_wall_halves


def test_the_halves_albedo_goes_and_the_merge_keeps_the_same_bits():
    hv = checker_wall_halves(16, 5)
    hv.transient = True
    want = hv.a.merged(hv.b).features["albedo"]
    merged = hv.a.merged(hv.b, features_on_read=True)
    refs = [weakref.ref(getattr(h.features["albedo"], k)) for h in hv for k in ("mean", "m2", "count")]
    assert hv.release_features(merged=merged, merged_keep=("albedo",)) is True
    assert hv.a.feature_names == hv.b.feature_names == () and tuple(merged.features) == ("albedo",)
    assert all(r() is None for r in refs)  # no half's albedo array is held any longer
    got = merged.features["albedo"]
    assert got is merged.features["albedo"]  # stored, not merged anew from the (gone) halves on each read
    for k in ("count", "mean", "m2"):
        assert np.array_equal(getattr(got, k), getattr(want, k))


def test_an_eager_merge_keeps_its_albedo_and_halves_that_live_on_keep_theirs():
    hv = checker_wall_halves(12, 6)
    merged = hv.a.merged(hv.b)
    assert hv.release_features(merged=merged, merged_keep=("albedo",)) is False
    assert set(hv.a.feature_names) == {"albedo", "normal", "depth"}
    hv.transient = True
    alb = merged.features["albedo"]
    assert hv.release_features(merged=merged, merged_keep=("albedo",)) is True
    assert hv.a.feature_names == () and tuple(merged.features) == ("albedo",) and merged.features["albedo"] is alb

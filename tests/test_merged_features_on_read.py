"""The dispatcher's merge of the halves it splits merges each feature when read: the same bits as the
eager merge, no feature held until read, and a merge into such statistics keeps every feature."""

import numpy as np

from mcrecon.core.features import layout_of
from mcrecon.core.halves import split_halves
from mcrecon.core.merge import MergedOnRead
from mcrecon.core.samples import SampleSet
from mcrecon.core.stats import PixelStats
from mcrecon.methods import get_method
from mcrecon.offline.inputs import gather_inputs

from helpers import feature_samples

W, H = 9, 6


def _set(n=1500, seed=5):
    pos, val, feats = feature_samples(n, seed, width=W, height=H)
    return SampleSet(pos, val, width=W, height=H, features=feats)


def _same(x: PixelStats, y: PixelStats):
    for k in ("count", "mean", "m2", "min", "max"):
        u, v = getattr(x, k), getattr(y, k)
        assert (u is None and v is None) or np.array_equal(u, v, equal_nan=True), k
    assert x.feature_names == y.feature_names and x.n_feature_zeroed == y.n_feature_zeroed
    for name in x.feature_names:
        _same(x.features[name], y.features[name])


def test_features_merged_on_read_equal_the_eager_merge_bit_for_bit():
    h = split_halves(_set(), features="all")
    lazy = h.a.merged(h.b, features_on_read=True)
    assert isinstance(lazy.features, MergedOnRead)
    assert layout_of(lazy.features) == {"albedo": 3, "normal": 3, "depth": 1}
    _same(lazy, h.merged())
    assert lazy.dtype == h.merged().dtype


def test_nfor_inputs_hold_no_merged_feature_until_one_is_read():
    inputs = gather_inputs(_set(), get_method("nfor"))
    feats = inputs.stats.features
    assert isinstance(feats, MergedOnRead) and not feats._set
    a = feats["albedo"]
    assert a is not feats["albedo"]  # merged anew at each read, never kept
    np.testing.assert_array_equal(a.mean, inputs.halves.merged().features["albedo"].mean)


def test_a_merge_into_statistics_with_features_merged_on_read_keeps_every_feature():
    s = _set()
    h = split_halves(s, features="all")
    lazy = h.a.merged(h.b, features_on_read=True)
    extra = PixelStats.from_samples(s.positions[:200], s.values[:200], width=W, height=H,
                                    features={k: v[:200] for k, v in s.features.items()})
    lazy.merge(extra)
    assert isinstance(lazy.features, dict)
    _same(lazy, h.merged().merge(extra))
    _same(lazy.copy(), lazy)

"""nfor's pipeline lets each input plane go once its stage is done: the unfiltered features before the
regression (a caller that hands its planes over in a list keeps none of them), with the same image."""

import weakref

import numpy as np

from mcrecon.methods.nfor import pipeline
from mcrecon.methods.nfor.pipeline import PAPER, denoise_planes, nfor_denoise
from mcrecon.filters.regression import MIN_COVER_WEIGHT, RIDGE


def _planes(seed=2, h=12, w=11):
    rng = np.random.default_rng(seed)
    y_a, y_b = rng.gamma(2.0, 0.5, size=(2, h, w, 3))
    var = rng.uniform(0.01, 0.05, size=(h, w, 3))
    f_a, f_b = rng.uniform(0, 1, size=(2, h, w, 2))
    f_v = rng.uniform(0.001, 0.01, size=(h, w, 2))
    return [y_a, y_b, var, f_a, f_b, f_v]


def test_the_unfiltered_features_are_gone_before_the_regression_and_the_image_is_unchanged(monkeypatch):
    expected = nfor_denoise(*[x.copy() for x in _planes()])
    planes = _planes()
    refs = [weakref.ref(x) for x in planes[3:]]
    seen = []
    regression = pipeline.cross_regression

    def spy(*args, **kw):
        seen.append([r() is None for r in refs])
        return regression(*args, **kw)

    monkeypatch.setattr(pipeline, "cross_regression", spy)
    kw = {k: v for k, v in PAPER.items()}
    img = denoise_planes(planes, ridge=RIDGE, threads=1, stride=1, min_weight=MIN_COVER_WEIGHT, diagnostics=None,
                         **kw)
    assert planes == [] and seen == [[True, True, True]]
    np.testing.assert_array_equal(img, expected)

"""Several images filtered with one guide's NL-means weights equal each image filtered alone, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from mcrecon.filters.nlmeans import nlmeans_filter, nlmeans_filter_shared
from mcrecon.methods.nfor.pipeline import estimate_mse, nfor_denoise

from nfor_reference import nlmeans_filter_reference


def _images(seed=0, h=23, w=19, c=3, m=3):
    rng = np.random.default_rng(seed)
    guide = rng.gamma(2.0, 1.0, size=(h, w, c))
    var = rng.uniform(0.01, 0.3, size=(h, w, c))
    imgs = [rng.normal(size=(h, w, c)) for _ in range(m)]
    return imgs, guide, var


@pytest.mark.parametrize("radius,patch", [(9, 1), (2, 3), (0, 0)])
def test_shared_weights_equal_one_filter_per_image_bit_for_bit(radius, patch):
    imgs, guide, var = _images()
    got = nlmeans_filter_shared(imgs, guide, var, radius=radius, patch=patch, k=0.8, variance_scale=2.0)
    for img, g in zip(imgs, got):
        alone = nlmeans_filter(img, guide, var, radius=radius, patch=patch, k=0.8, variance_scale=2.0)
        assert np.array_equal(g, alone)
        ref = nlmeans_filter_reference(img, guide, var, radius=radius, patch=patch, k=0.8, variance_scale=2.0)
        np.testing.assert_allclose(g, ref, rtol=1e-12, atol=1e-14)


def test_shared_weights_keep_each_image_shape_and_do_not_depend_on_threads():
    imgs, guide, var = _images(1, h=40, w=37, c=1, m=2)
    imgs = [i[..., 0] for i in imgs]
    one = nlmeans_filter_shared(imgs, guide[..., 0], var[..., 0], radius=3, patch=1, k=1.0, threads=1)
    two = nlmeans_filter_shared(imgs, guide[..., 0], var[..., 0], radius=3, patch=1, k=1.0, threads=2)
    assert [o.shape for o in one] == [(40, 37), (40, 37)]
    for a, b in zip(one, two):
        assert np.array_equal(a, b)


def test_shared_weights_refuse_an_image_of_another_shape():
    imgs, guide, var = _images(m=1)
    with pytest.raises(ValueError):
        nlmeans_filter_shared([imgs[0][:-1]], guide, var, radius=2, patch=1, k=1.0)


def test_nfor_mse_estimates_filtered_together_equal_them_filtered_one_by_one():
    """The pipeline's two bandwidths' MSE filters (same guide, same parameters) share their weights."""
    rng = np.random.default_rng(2)
    h, w = 20, 22
    y_a, y_b = rng.gamma(2.0, 1.0, size=(2, h, w, 3))
    var = rng.uniform(0.01, 0.1, size=(h, w, 3))
    fa, fb = rng.uniform(size=(2, h, w, 4))
    fv = rng.uniform(0.0, 0.01, size=(h, w, 4))
    diag = {}
    nfor_denoise(y_a, y_b, var, fa, fb, fv, radius=3, feature_radius=2, mse_radius=3, second_pass=False,
                 diagnostics=diag)
    # the selection map, rebuilt from the candidates with one filter per MSE estimate
    from mcrecon.methods.nfor.pipeline import cross_regression, prefilter_features
    pf_a, pf_b = prefilter_features(fa, fb, fv, radius=2)
    y = 0.5 * (y_a + y_b)
    m = [nlmeans_filter(estimate_mse(y_a, y_b, *cross_regression(y_a, y_b, var, pf_a, pf_b, radius=3, k=k), var),
                        y, var, radius=3, patch=1, k=1.0) for k in (0.5, 1.0)]
    sel = nlmeans_filter((m[0] >= m[1]).astype(np.float64), y, var, radius=3, patch=1, k=1.0)
    assert np.array_equal(diag["selection"], sel.mean(axis=2))
    assert np.array_equal(diag["estimated_mse"], np.minimum(m[0], m[1]).mean(axis=2))

"""The RDFC-style cross-bilateral filter: brute-force weights, invariants, and what the features buy."""

import numpy as np
import pytest

from mcrecon.filters.cross_bilateral import cross_bilateral, feature_gradient2


def _brute(img, var, feat, fvar, r, kc, kf, tau):
    h, w, c = img.shape
    g2 = feature_gradient2(feat)
    out = np.zeros_like(img)
    for i in range(h):
        for j in range(w):
            num, den = np.zeros(c), 0.0
            for qi in range(max(0, i - r), min(h, i + r + 1)):
                for qj in range(max(0, j - r), min(w, j + r + 1)):
                    vp, vq = var[i, j], var[qi, qj]
                    dc = np.mean(((img[i, j] - img[qi, qj]) ** 2 - (vp + np.minimum(vp, vq)))
                                 / (1e-10 + kc * kc * (vp + vq)))
                    sp, sq = fvar[i, j], fvar[qi, qj]
                    df = ((feat[i, j] - feat[qi, qj]) ** 2 - (sp + np.minimum(sp, sq))) \
                        / (kf * kf * np.maximum(np.maximum(tau, sp), g2[i, j]))
                    wt = np.exp(-max(0.0, dc, df.max()))
                    num += wt * img[qi, qj]
                    den += wt
            out[i, j] = num / den
    return out


def test_matches_brute_force_weights():
    rng = np.random.default_rng(4)
    h, w = 9, 11
    img = rng.gamma(2.0, 1.0, size=(h, w, 3))
    var = rng.uniform(0.05, 0.5, size=(h, w, 3))
    feat = np.concatenate([rng.uniform(size=(h, w, 2)), np.linspace(0, 2, w)[None, :, None].repeat(h, 0)], axis=2)
    fvar = rng.uniform(1e-4, 1e-2, size=(h, w, 3))
    got = cross_bilateral(img, var, feat, fvar, radius=2, k_colour=0.6, k_feature=0.8, tau=1e-3)
    # the weights use exp_neg (within 6e-10 relative of exp): the output within 2e-9 relative
    np.testing.assert_allclose(got, _brute(img, var, feat, fvar, 2, 0.6, 0.8, 1e-3), rtol=2e-9)


def test_constant_image_is_kept_and_hdr_scale_commutes():
    rng = np.random.default_rng(1)
    h, w = 12, 10
    feat = rng.uniform(size=(h, w, 4))
    fvar = np.full((h, w, 4), 1e-3)
    flat = np.full((h, w, 3), 7.5)
    np.testing.assert_allclose(cross_bilateral(flat, np.full((h, w, 3), 0.1), feat, fvar), flat, rtol=1e-14)
    img = rng.gamma(2.0, 1.0, size=(h, w, 3))
    var = np.full((h, w, 3), 0.2)
    s = 1e5  # the colour distance is invariant to u -> s u, V -> s^2 V: HDR values neither clipped nor rescaled
    np.testing.assert_allclose(cross_bilateral(s * img, s * s * var, feat, fvar), s * cross_bilateral(img, var, feat, fvar),
                               rtol=1e-9)


def test_a_noise_free_feature_edge_keeps_the_colour_edge():
    """Two flat regions split by a noise-free albedo edge: the features alone (k_colour None) keep the
    regions apart (no mixing across the edge), while the noise of each region is averaged away."""
    rng = np.random.default_rng(7)
    h, w = 16, 20
    albedo = np.where(np.arange(w)[None, :, None] < w // 2, 0.1, 0.9) * np.ones((h, w, 3))
    truth = 2.0 * albedo
    noisy = truth + rng.normal(0, 0.3, size=truth.shape)
    out = cross_bilateral(noisy, np.full(truth.shape, 0.09), albedo, np.zeros_like(albedo), radius=4,
                          k_colour=None)
    assert np.abs(out - truth).max() < 0.25  # no pixel pulled across the 1.6 step
    assert np.mean((out - truth) ** 2) < 0.030 * np.mean((noisy - truth) ** 2)  # measured 0.0258; 15 % margin


def test_bad_parameters_are_refused():
    z = np.zeros((4, 4, 3))
    with pytest.raises(ValueError, match="k_feature"):
        cross_bilateral(z, z, z, z, k_feature=0)
    with pytest.raises(ValueError, match="differ"):
        cross_bilateral(z, z[:2], z, z)

"""An albedo is read as a reflectance in [0, 1]: Cycles' "Denoising Albedo" carries an emitter's radiance
(up to 318) where a mirror or glass path ends on a light; the colour is never clamped."""

from __future__ import annotations

import warnings

import numpy as np

import mcrecon
from mcrecon.core.features import as_guide, check_features
from mcrecon.core.halves import split_halves


def _samples(albedo_of_light: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    w = h = 16
    spp = 8
    pos = np.repeat(np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 2), spp, axis=0) \
        + rng.random((w * h * spp, 2))
    n = pos.shape[0]
    val = 0.3 * rng.exponential(1.0, (n, 1)) * np.array([1.0, 0.9, 0.8])
    alb = np.full((n, 3), 0.6)
    light = (pos[:, 0] >= 6) & (pos[:, 0] < 9) & (pos[:, 1] >= 6) & (pos[:, 1] < 9) & (rng.random(n) < 0.5)
    val[light] = 300.0  # a mirror path ending on a light: HDR colour, kept as it is
    alb[light] = albedo_of_light
    feats = {"albedo": alb, "normal": np.tile([0.0, 0.0, -1.0], (n, 1)), "depth": np.ones((n, 1))}
    return mcrecon.SampleSet(pos, val, width=w, height=h, features=feats), val


def test_check_features_clamps_an_albedo_into_0_1_and_nothing_else():
    feats = {"albedo": np.array([[318.0, 0.5, -0.2], [0.1, 0.2, 0.3]]), "normal": np.array([[0, 0, -3.0]] * 2)}
    out, n_zeroed = check_features(feats, 2)
    np.testing.assert_array_equal(out["albedo"], [[1.0, 0.5, 0.0], [0.1, 0.2, 0.3]])
    np.testing.assert_array_equal(out["normal"], feats["normal"])  # not a reflectance: as given
    assert n_zeroed == 0
    inside = np.array([[0.2, 0.4, 1.0]], np.float32)
    assert as_guide("albedo", inside) is inside and as_guide("albedo", inside).dtype == np.float32


def test_the_pixel_albedo_a_method_reads_is_a_reflectance_and_the_colour_is_kept():
    ss, val = _samples(318.0)
    st = split_halves(ss, features="all").merged()
    assert st.features["albedo"].mean.max() <= 1.0
    np.testing.assert_array_equal(ss.values, val)  # the radiance is not clipped
    assert st.mean.max() > 100.0


def test_nfor_reads_an_emitters_albedo_as_an_albedo_of_one():
    ss, _ = _samples(318.0)
    ref, _ = _samples(1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        np.testing.assert_array_equal(mcrecon.reconstruct(ss, method="nfor"), mcrecon.reconstruct(ref, method="nfor"))

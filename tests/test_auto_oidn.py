"""auto's OIDN candidates: OIDN on all the samples by default, scored by an estimate of that filter's error."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import mcrecon
from mcrecon import get_method
from mcrecon.core.fill import mean_variance_policy
from mcrecon.core.halves import split_halves
from mcrecon.core.metrics import relative_mse
from mcrecon.errors import InputError
from mcrecon.renderers import scenes

pyoidn = pytest.importorskip("pyoidn", reason="needs pyoidn (Intel OIDN), a dependency of mcrecon: pip install -e .")

from mcrecon.methods.auto import blackbox  # noqa: E402

N = 64


def _scene(name, features=False, seed=0):
    ref = scenes.reference_image(name, N, N)
    b = scenes.render_uniform(name, width=N, height=N, spp=32, seed=seed, features=features)
    fe = b.features if features else None
    ss = mcrecon.SampleSet(b.positions, b.values, width=N, height=N, features=fe)
    return ss, split_halves(ss, features=tuple(fe) if fe else ()), ref


def _quiet(f):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return f()


def _oidn(colour, *aux):
    f32 = [np.ascontiguousarray(a, dtype=np.float32) for a in (colour,) + aux]
    return np.asarray(pyoidn.denoise(*f32, hdr=True, quality="high"), np.float64)


def test_oidn_candidates_are_in_the_default():
    m = get_method("auto")
    assert "oidn" in m.params["candidates"].split(",")
    assert "oidn_aux" in m.params["feature_candidates"].split(",")
    with pytest.raises(InputError, match="feature_candidates"):
        get_method("auto", feature_candidates="oidn_aux,bogus")


def test_the_oidn_candidate_is_oidn_on_all_the_samples_and_its_halves_average_comes_too():
    ss, hv, ref = _scene("soft_shadow")
    st = hv.merged()
    full, halves = blackbox.oidn_candidate("oidn", st, mean_variance_policy(st), hv)
    assert (full.name, halves.name) == ("oidn", "oidn_halves")
    np.testing.assert_array_equal(full.image, _oidn(st.mean))
    np.testing.assert_array_equal(halves.image, 0.5 * (_oidn(hv.a.mean) + _oidn(hv.b.mean)))
    # without halves: OIDN on all the samples alone
    assert [c.name for c in blackbox.oidn_candidate("oidn", st, mean_variance_policy(st), None)] == ["oidn"]


def test_the_halves_estimate_predicts_the_full_sample_error():
    """The halves' cross-validation scaled by HALF_TO_FULL sums to the full-sample OIDN's true squared error:
    soft_shadow 64^2, 32 spp, seed 0, measured 0.99; unscaled (the error of OIDN on a half) 1.65."""
    ss, hv, ref = _scene("soft_shadow")
    st = hv.merged()
    c = blackbox.oidn_candidate("oidn", st, mean_variance_policy(st), hv)[0]
    ratio = float(np.nansum(c.mse) / np.sum((c.image - ref) ** 2))
    assert 0.8 <= ratio <= 1.2, ratio


def test_oidn_aux_feeds_prefiltered_features_with_clean_aux():
    """OIDN on all the samples takes the halves' prefiltered albedo and normal merged by sample counts."""
    ss, hv, ref = _scene("soft_shadow", features=True)
    st = hv.merged()
    c, h = blackbox.oidn_candidate("oidn_aux", st, mean_variance_policy(st), hv, aux=True)
    assert h.name == "oidn_aux_halves" and h.feature
    assert c.feature
    (aa, na), (ab, nb) = blackbox.oidn_aux(hv.a), blackbox.oidn_aux(hv.b)
    wa = (hv.a.count / (hv.a.count + hv.b.count))[..., None]
    alb, nrm = wa * aa + (1 - wa) * ab, wa * na + (1 - wa) * nb
    f32 = lambda a: np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
    want = np.asarray(pyoidn.denoise(f32(st.mean), f32(alb), f32(nrm), hdr=True, quality="high", clean_aux=True))
    np.testing.assert_array_equal(c.image, want.astype(np.float64))


def test_without_halves_the_estimate_is_monte_carlo_sure():
    ss, hv, ref = _scene("soft_shadow")
    st = hv.merged()
    (c,) = blackbox.oidn_candidate("oidn", st, mean_variance_policy(st), None)
    assert np.isfinite(c.mse).all()
    ratio = float(np.sum(c.mse) / np.sum((c.image - ref) ** 2))
    assert 0.7 <= ratio <= 1.1, ratio   # Stein's lemma holds for near-Gaussian noise: measured 0.91


@pytest.mark.parametrize("name,features,measured", [
    ("soft_shadow", True, 0.567), ("caustic", False, 0.421), ("depth_of_field", False, 0.734)])
def test_auto_quality_with_oidn(name, features, measured):
    """auto's relative MSE over the pixel mean's (64^2, 32 spp, seed 0), within 15 % of the measured value;
    with features at least as good as OIDN given the pixel means of the albedo and normal (0.670 there), and
    on depth of field at least as good as colour-only OIDN (0.828)."""
    ss, hv, ref = _scene(name, features)
    st = hv.merged()
    e = relative_mse(_quiet(lambda: mcrecon.reconstruct(ss, method="auto")), ref) / relative_mse(st.mean, ref)
    assert e <= 1.15 * measured, e
    if features:
        an = _oidn(st.mean, st.features["albedo"].mean, st.features["normal"].mean)
        assert e <= relative_mse(an, ref) / relative_mse(st.mean, ref), e
    if name == "depth_of_field":
        assert e <= relative_mse(_oidn(st.mean), ref) / relative_mse(st.mean, ref), e

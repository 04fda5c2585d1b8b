"""Tests of ``awr`` (Overbeck, Donner, Ramamoorthi 2009, "Adaptive Wavelet Rendering").

Every formula has a test that fails if it is wrong: Appendix A taps,
Eq. 5/6 (variance image), Eq. 9/10 (propagated variance against Monte
Carlo), the renormalisation, Eq. 11 (soft threshold), Eq. 8 (priority,
against brute-force inner products), Fig. 5 (importance sampling, chi^2),
plus GEM's 1-D two-box experiment and the scene comparisons.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from scipy import stats as sstats

import mcrecon
from mcrecon.errors import InputError, McreconWarning
from mcrecon.methods import AdaptiveState, get_method
from mcrecon.methods.base import MethodInputs
from mcrecon.methods.awr import (
    RECONSTRUCTION_RENORM, SAMPLING_RENORM, WAVELETS, AWRMethod, analysis_matrices, analyze,
    awr_reconstruct, coefficient_variances, default_levels, equivalent_filter_norms, functional_variance,
    get_wavelet, pixel_variance, plan_awr_positions, renormalisation_factor, sample_scale_functions,
    scale_priorities, soft_threshold, synthesize)
from mcrecon.core.stats import PixelStats

BASES = list(WAVELETS)
MODES = ["symmetric", "periodization"]


# --------------------------------------------------------------------------- bases

def _half(taps):
    """Nonzero taps of a symmetric filter from its centre outwards."""
    t = np.trim_zeros(np.asarray(taps, dtype=np.float64))
    return t[len(t) // 2:]


def test_cdf97_taps_match_appendix_a():
    """bior4.4 is the paper's CDF 9/7 with the same sqrt 2 scaling (Appendix A).

    Appendix A lists 6 significant digits, so agreement to 2e-6 (rounding
    of the 6th digit times sqrt 2) is the strongest claim possible.
    """
    w = get_wavelet("cdf97")
    s2 = math.sqrt(2.0)
    a_lo = s2 * np.array([0.602949, 0.266864, -0.078223, -0.016864, 0.026749])
    a_hi = np.array([1.115087, -0.591272, -0.057544, 0.091272]) / s2
    s_lo = np.array([1.115087, 0.591272, -0.057544, -0.091272]) / s2
    s_hi = s2 * np.array([0.602949, -0.266864, -0.078223, 0.016864, 0.026749])
    np.testing.assert_allclose(_half(w.dec_lo), a_lo, atol=2e-6)
    np.testing.assert_allclose(_half(w.rec_lo), s_lo, atol=2e-6)
    # PyWavelets' high-pass filters carry the opposite sign convention:
    # the basis functions differ by a global sign, which Eq. 10 (squares)
    # and Eq. 11 (sign-symmetric) cannot see.
    np.testing.assert_allclose(-_half(w.dec_hi), a_hi, atol=2e-6)
    np.testing.assert_allclose(-_half(w.rec_hi), s_hi, atol=2e-6)
    assert abs(np.sum(w.dec_lo) - s2) < 1e-12


def test_legall53_taps_match_appendix_a():
    w = get_wavelet("legall53")
    s2 = math.sqrt(2.0)
    np.testing.assert_allclose(_half(w.dec_lo), s2 / 8 * np.array([6, 2, -1]), atol=1e-12)
    np.testing.assert_allclose(-_half(w.dec_hi), 1 / s2 / 2 * np.array([2, -1]), atol=1e-12)
    np.testing.assert_allclose(_half(w.rec_lo), 1 / s2 / 2 * np.array([2, 1]), atol=1e-12)
    # The paper lists this one with the opposite global sign from its 9/7
    # listing (centre -6); PyWavelets agrees with the paper's value here.  A
    # global sign of one high-pass filter is a convention of the shift used
    # in the alternating-flip relation, invisible to Eq. 10 (squares).
    np.testing.assert_allclose(_half(w.rec_hi), s2 / 8 * np.array([-6, 2, 1]), atol=1e-12)


def test_wavelet_registry_rejects_unknown_names():
    with pytest.raises(InputError) as e:
        get_wavelet("db4")
    assert e.value.field == "wavelet" and "cdf97" in e.value.problem and "legall53" in e.value.problem
    with pytest.raises(InputError) as e:
        AWRMethod(wavelet="bior4.4")
    assert e.value.field == "wavelet" and "haar" in e.value.problem
    with pytest.raises(InputError) as e:
        awr_reconstruct(np.zeros((9, 9)), np.zeros((9, 9)), wavelet="sym8")
    assert "cdf97" in e.value.problem


@pytest.mark.parametrize("opts, field", [
    (dict(cs=-1.0), "cs"), (dict(cs=float("nan")), "cs"), (dict(levels=-1), "levels"), (dict(levels=2.5), "levels"),
    (dict(renorm=0.0), "renorm"), (dict(round_spp=0), "round_spp"), (dict(initial_spp=0), "initial_spp"),
    (dict(per_coefficient=-1), "per_coefficient"), (dict(priority_threshold=float("inf")), "priority_threshold"),
    (dict(variance="mad"), "variance"), (dict(boundary="zero"), "boundary"), (dict(reconstruction="gem"), "reconstruction"),
    (dict(colour=1), "colour"),
])
def test_options_validated_with_stable_errors(opts, field):
    with pytest.raises(InputError) as e:
        AWRMethod(**opts)
    assert e.value.field == field and e.value.where == "method awr"


# ------------------------------------------------------------ transform + matrices

@pytest.mark.parametrize("wavelet", BASES)
@pytest.mark.parametrize("mode", MODES)
def test_perfect_reconstruction_cs0_odd_size(wavelet, mode, rng):
    """c_s = 0 and the bare analysis/synthesis pair reproduce a 333x517 HDR image."""
    mean = np.exp(rng.normal(0, 3, (333, 517, 3)))            # 1e-4 .. 1e4
    var = rng.random((333, 517, 3)) * mean
    a, det, shp, _ = analyze(mean, wavelet, 6, mode=mode)
    back = synthesize(a, det, shp, wavelet, mode=mode)
    assert back.shape == mean.shape
    np.testing.assert_allclose(back, mean, rtol=1e-9, atol=1e-9 * mean.max())
    out = awr_reconstruct(mean, var, wavelet=wavelet, cs=0.0, levels=6, mode=mode)
    np.testing.assert_array_equal(out, mean)
    # ... and thresholding with a vanishing c_s converges to it (the transform
    # path, not the c_s = 0 short cut).
    tiny = awr_reconstruct(mean, var, wavelet=wavelet, cs=1e-12, levels=6, mode=mode)
    np.testing.assert_allclose(tiny, mean, rtol=1e-6, atol=1e-9 * mean.max())


@pytest.mark.parametrize("wavelet", BASES)
@pytest.mark.parametrize("mode", MODES)
def test_analysis_matrices_are_the_transform(wavelet, mode, rng):
    """Kronecker products of the 1-D matrices give PyWavelets' 2-D coefficients
    (so Var = (A o A) sigma^2 is Eq. 13-15 for the transform we threshold)."""
    h, w, L = 23, 37, 3
    x = rng.standard_normal((h, w))
    _, det, _, scales = analyze(x, wavelet, L, mode=mode)
    loy, hiy = analysis_matrices(h, wavelet, mode, L)
    lox, hix = analysis_matrices(w, wavelet, mode, L)
    for k in range(L):
        m = {"a": (loy[k].toarray(), lox[k].toarray()), "d": (hiy[k].toarray(), hix[k].toarray())}
        np.testing.assert_allclose(m["a"][0] @ x @ m["a"][1].T, scales[k], atol=1e-12)
        for key, c in det[k].items():
            np.testing.assert_allclose(m[key[0]][0] @ x @ m[key[1]][1].T, c, atol=1e-12)


# --------------------------------------------------------------- variance image

def _stats_from(values_per_pixel, h=1, w=None):
    """PixelStats of one channel from a list of sample lists (one per pixel)."""
    w = w or len(values_per_pixel)
    pos, val = [], []
    for i, vals in enumerate(values_per_pixel):
        for v in vals:
            pos.append((i % w + 0.5, i // w + 0.5))
            val.append(v)
    return PixelStats.from_samples(np.array(pos).reshape(-1, 2), np.array(val, float).reshape(-1, 1),
                                   width=w, height=h, channels=("Y",))


def test_variance_estimators_eq5_eq6():
    st = _stats_from([[1.0, 3.0, 2.0], [0.0, 0.0], [5.0, 5.0, 5.0, 5.0], [2.0, -1.0]])
    rng_ = functional_variance(st, "range")[0, :, 0]
    np.testing.assert_allclose(rng_, [4.0, 0.0, 0.0, 9.0])
    con = functional_variance(st, "contrast")[0, :, 0]
    # Eq. 5: (Imax-Imin)^2/(Imax+Imin)^2; all-black pixel 0; signed values use |Imax|+|Imin|.
    np.testing.assert_allclose(con, [4.0 / 16.0, 0.0, 0.0, 9.0 / 9.0])
    smp = functional_variance(st, "sample")[0, :, 0]
    np.testing.assert_allclose(smp, [1.0, 0.0, 0.0, 4.5])
    # Eq. 6: divided by N.
    np.testing.assert_allclose(pixel_variance(st, "range")[0, :, 0], [4.0 / 3, 0.0, 0.0, 9.0 / 2])


def test_variance_policy_for_pixels_with_one_or_no_sample():
    # Pixel 1 has one sample, pixel 3 none: they take the 3x3 neighbourhood
    # average over pixels with n >= 2 (here pixels 0 and 2, resp. 2 and 4).
    st = _stats_from([[0.0, 2.0], [7.0], [1.0, 3.0, 5.0], [], [0.0, 1.0]])
    f = functional_variance(st, "sample")[0, :, 0]
    np.testing.assert_allclose(f, [2.0, (2.0 + 4.0) / 2, 4.0, (4.0 + 0.5) / 2, 0.5])
    v = pixel_variance(st, "sample")[0, :, 0]
    np.testing.assert_allclose(v, [1.0, 3.0, 4.0 / 3, 2.25, 0.25])
    # No pixel with two samples: nothing to borrow, variance 0 (no smoothing).
    st1 = _stats_from([[1.0], [4.0]])
    assert np.all(functional_variance(st1, "range") == 0)


# ------------------------------------------------------ Eq. 9/10 against Monte Carlo

@pytest.mark.slow
@pytest.mark.parametrize("wavelet", BASES)
@pytest.mark.parametrize("mode", MODES)
def test_propagated_variance_matches_monte_carlo(wavelet, mode, full_run):
    """Eq. 9/10 (exact propagation) vs the empirical variance of the
    coefficients of R independent Gaussian noise images with a spatially
    varying pixel variance, on an odd-sized image.

    Tolerance: for Gaussian coefficients with known mean 0 the empirical
    variance ``mean(c^2)`` has relative sd ``sqrt(2/R)`` per coefficient.
    The region-mean ratio is compared within 5 % (the issue's bound); that
    is >= 3 sd even if all coefficients of a region were fully correlated
    at R = 2000 (sd 3.2 %) and ~1 % sd for near-independent ones.  Single
    coefficients must lie within 6 sd (1e-9 false-alarm rate each).
    """
    R = 8000 if full_run else 2000
    h, w, L = (61, 83, 4) if full_run else (37, 45, 3)
    rng = np.random.default_rng(20240)
    sd = np.exp(rng.uniform(-1.0, 1.0, (h, w)))
    x = rng.standard_normal((h, w, R)) * sd[..., None]
    _, det, _, _ = analyze(x, wavelet, L, mode=mode)
    prop = coefficient_variances(sd ** 2, wavelet, L, mode=mode, propagation="exact")
    tol1 = 6 * math.sqrt(2.0 / R)
    for k in range(L):
        for key, c in det[k].items():
            emp = np.mean(c * c, axis=2)
            p = prop[k][key]
            zero = p < 1e-12 * sd.max() ** 2      # e.g. Haar details of a mirrored pair: exactly 0
            assert np.all(emp[zero] < 1e-20)
            r = p[~zero] / emp[~zero]
            assert np.all(np.abs(r - 1) < tol1), (k + 1, key, np.abs(r - 1).max())
            b = 2 * (get_wavelet(wavelet).dec_len // 2)   # coefficients touching a border
            inner = np.zeros(p.shape, bool)
            inner[b:-b, b:-b] = True
            if inner.any():
                ri = p[inner] / emp[inner]
                assert abs(ri.mean() - 1) < 0.05, (k + 1, key, ri.mean())
            border = ~inner & ~zero
            rb = p[border] / emp[border]
            assert abs(rb.mean() - 1) < 0.05, (k + 1, key, "border", rb.mean())


def test_cascade_shortcut_is_biased_where_the_exact_propagation_is_not():
    """The paper's squared-tap DWT ignores the covariance of overlapping scale
    coefficients (it says so) and of mirrored border samples: on a constant
    variance image it is off by > 10 % at level 2 (9/7, HH, interior) and
    by > 2x at the border, which the exact propagation gets right
    analytically (constant variance: ||Psi_k||^2 in the interior)."""
    n, L = 128, 3
    ones = np.ones((n, n))
    ex = coefficient_variances(ones, "cdf97", L, propagation="exact")
    ca = coefficient_variances(ones, "cdf97", L, propagation="cascade")
    n_lo, n_hi = equivalent_filter_norms("cdf97", 2)
    mid = ex[1]["dd"].shape[0] // 2
    assert ex[1]["dd"][mid, mid] == pytest.approx(n_hi * n_hi, rel=1e-12)
    assert ca[1]["dd"][mid, mid] / ex[1]["dd"][mid, mid] < 0.9
    assert np.max(ca[0]["dd"] / ex[0]["dd"]) > 2.0


@pytest.mark.parametrize("wavelet", BASES)
def test_renormalisation_reproduces_the_papers_constant_variance_values(wavelet):
    """Squared filters renormalised to sum r give a unit variance image the
    variance r^(2k) at level k (2-D); our renormalised basis functions must
    give exactly that in the interior, for both renormalisations."""
    n, L = 160, 4
    for r in (SAMPLING_RENORM, RECONSTRUCTION_RENORM):
        sv = coefficient_variances(np.ones((n, n)), wavelet, L, renorm=r, which="scales")
        dv = coefficient_variances(np.ones((n, n)), wavelet, L, renorm=r, which="details")
        for k in range(1, L + 1):
            c = sv[k - 1].shape[0] // 2
            assert sv[k - 1][c, c] == pytest.approx(r ** (2 * k), rel=1e-10)
            for key in ("ad", "da", "dd"):
                assert dv[k - 1][key][c, c] == pytest.approx(r ** (2 * k), rel=1e-10)
    # and the factor is the one documented
    n_lo, n_hi = equivalent_filter_norms(wavelet, 3)
    assert renormalisation_factor(wavelet, 3, "ad", 0.5) == pytest.approx(0.5 ** 6 / (n_lo * n_hi))
    assert renormalisation_factor(wavelet, 3, "ad", None) == 1.0


# ------------------------------------------------------------------ Eq. 11

def test_soft_threshold_eq11():
    w = np.array([3.0, -3.0, 0.5, -0.5, 2.0, -7.0, 0.0])
    d = np.array([1.0, 1.0, 1.0, 1.0, 0.0, 2.0, 1.0])
    np.testing.assert_array_equal(soft_threshold(w, d, 1.0), [2.0, -2.0, 0.0, 0.0, 2.0, -5.0, 0.0])
    np.testing.assert_array_equal(soft_threshold(w, d, 2.0), [1.0, -1.0, 0.0, 0.0, 2.0, -3.0, 0.0])
    np.testing.assert_array_equal(soft_threshold(w, np.zeros(7), 1.0), w)


def test_reconstruction_thresholds_with_eq10_deltas(rng):
    """awr_reconstruct = synthesis of the coefficients shrunk by c_s * sqrt(Eq. 10)."""
    h, w, L = 29, 34, 3
    mean = rng.random((h, w, 2))
    var = rng.random((h, w, 2)) * 0.05
    out = awr_reconstruct(mean, var, cs=1.3, levels=L)
    for c in range(2):
        a, det, shp, _ = analyze(mean[..., c], "cdf97", L)
        dv = coefficient_variances(var[..., c], "cdf97", L, renorm=RECONSTRUCTION_RENORM)
        loy, hiy = analysis_matrices(h, "cdf97", "symmetric", L)
        lox, hix = analysis_matrices(w, "cdf97", "symmetric", L)
        new = []
        for k in range(L):
            m = {"a": (loy[k].toarray(), lox[k].toarray()), "d": (hiy[k].toarray(), hix[k].toarray())}
            nd = {}
            for key, coef in det[k].items():
                # Eq. 10 by brute force: sum over pixels of Psi^2 sigma^2, renormalised.
                my, mx = m[key[0]][0], m[key[1]][1]
                delta2 = (my ** 2) @ var[..., c] @ (mx ** 2).T
                delta2 *= renormalisation_factor("cdf97", k + 1, key, RECONSTRUCTION_RENORM)
                np.testing.assert_allclose(dv[k][key], delta2, rtol=1e-10, atol=1e-15)
                t = 1.3 * np.sqrt(delta2)
                nd[key] = np.sign(coef) * np.maximum(0, np.abs(coef) - t)
            new.append(nd)
        np.testing.assert_allclose(out[..., c], synthesize(a, new, shp, "cdf97"), atol=1e-12)


def test_zero_variance_passes_through_and_skips_work(monkeypatch, rng):
    mean = rng.random((40, 50, 3))
    var = np.zeros_like(mean)
    var[..., 1] = 0.01
    import mcrecon.methods.awr.reconstruction as awr
    calls = []
    orig = awr._awr_core
    monkeypatch.setattr(awr, "_awr_core", lambda m, v, **kw: calls.append(m.shape) or orig(m, v, **kw))
    out = awr_reconstruct(mean, var, levels=3)
    assert calls == [(1, 40, 50)]                  # only the channel with variance was transformed
    np.testing.assert_array_equal(out[..., [0, 2]], mean[..., [0, 2]])
    assert np.abs(out[..., 1] - mean[..., 1]).max() > 1e-3
    calls.clear()
    np.testing.assert_array_equal(awr_reconstruct(mean, np.zeros_like(mean), levels=3), mean)
    assert calls == []


def test_reconstruct_refuses_nonfinite_and_negative_inputs_naming_them(rng):
    """One NaN pixel would spread over the support of every basis function that
    covers it (at the default depth the whole image: 4096 of 4096 pixels at 64^2,
    still 2704 at 2 levels); awr_reconstruct refuses
    such inputs up front, naming the argument and the number of bad pixels
    (a pixel is bad when any of its channels is)."""
    mean = rng.random((40, 50, 3))
    var = rng.random((40, 50, 3)) * 0.01
    bad_mean = mean.copy()
    bad_mean[3, 4, 1] = np.nan
    bad_mean[7, 8, :] = np.inf
    bad_var = var.copy()
    bad_var[0, 0, 2] = np.inf
    neg_var = var.copy()
    neg_var[1:4, 2, 0] = -1e-3
    neg_var[1, 2, 1] = -2.0
    for m, v, field, what in ((bad_mean, var, "mean", "2 of 2000 pixel(s) hold NaN or Inf"),
                              (mean, bad_var, "var", "1 of 2000 pixel(s) hold NaN or Inf"),
                              (mean, neg_var, "var", "3 of 2000 pixel(s) hold a negative variance")):
        for kw in ({}, {"cs": 0.0}, {"levels": 0}, {"propagation": "cascade"}):   # before any short cut
            with pytest.raises(InputError) as e:
                awr_reconstruct(m, v, **kw)
            assert (e.value.where, e.value.field) == ("awr_reconstruct", field)
            assert what in e.value.problem, e.value.problem
    assert "-2" in str(e.value)                                       # the smallest variance is shown
    # A 1-D signal: its pixels lie along the transformed axis.
    sig = np.zeros(250)
    sig[[3, 9]] = np.nan
    with pytest.raises(InputError, match="mean: 2 of 250 pixel"):
        awr_reconstruct(sig, np.zeros(250), axes=(0,))
    with pytest.raises(InputError) as e:
        awr_reconstruct(mean, var[..., :2])
    assert e.value.field == "var" and "(40, 50, 2)" in e.value.problem
    # Valid inputs with zero variances (and -0.0) pass.
    np.testing.assert_array_equal(awr_reconstruct(mean, -np.zeros_like(var)), mean)


# ------------------------------------------------------------ GEM Fig. 6 (1-D)

def _two_box_signal():
    f = np.zeros(250)
    f[50:100] = 1.0
    f[150:200] = 0.5
    return f


@pytest.mark.slow
def test_gem_two_box_experiment(full_run):
    """GEM Fig. 6: two boxes with uniform noise, 250 pixels, 32 samples each,
    through AWR's thresholding (CDF 9/7, c_s = 1, 5 levels, renorm 2^-1/2).

    Amplitudes (GEM does not list them): boxes of height 1 and 0.5 on 0,
    sample noise U(-1, 1) (per-sample variance 1/3), so the box filter's
    MSE is exactly 1/(3*32) = 1.04e-2.  GEM reports 7.6e-3 for AWR.
    Full run (200 runs, like GEM): range variance 5.7e-3, sample variance
    4.4e-3; squared bias of the mean reconstruction 4.4e-3 / 5.3e-4.

    Asserted: thresholding beats the pixel means by the measured margin
    (MSE / box: range 0.542, sample 0.426 at 50 runs; bounds + 15 %, wider
    than the run-to-run sd of the mean MSE, < 2 % at 50 runs: each run's MSE
    averages 250 pixels of variance ~1e-2); and with the range estimator
    most of the error is bias (GEM's point: (Imax-Imin)^2 over-smooths and
    rings), i.e. squared bias of the average reconstruction > 1/2 MSE.
    """
    runs = 200 if full_run else 50
    f = _two_box_signal()
    rng = np.random.default_rng(6)
    out = {}
    for est in ("range", "sample"):
        mses, avg = [], np.zeros(250)
        for _ in range(runs):
            s = f[:, None] + rng.uniform(-1.0, 1.0, (250, 32))
            m = s.mean(axis=1)
            v = ((s.max(1) - s.min(1)) ** 2 if est == "range" else s.var(1, ddof=1)) / 32
            rec = awr_reconstruct(m, v, cs=1.0, levels=5, axes=(0,))
            mses.append(np.mean((rec - f) ** 2))
            avg += rec / runs
        out[est] = (float(np.mean(mses)), float(np.mean((avg - f) ** 2)))
    box = 1.0 / (3 * 32)
    print(f"\nGEM Fig. 6 two boxes ({runs} runs): box {box:.3g}, AWR range {out['range'][0]:.3g} "
          f"(bias^2 {out['range'][1]:.3g}), AWR sample {out['sample'][0]:.3g} (bias^2 {out['sample'][1]:.3g}); "
          "GEM paper: AWR 7.6e-3")
    assert out["range"][0] < 0.63 * box    # measured 0.542 (50 runs), 0.547 (200); 15 % margin
    assert out["sample"][0] < 0.49 * box   # measured 0.426 (50 runs), 0.42 (200)
    assert out["range"][1] > 0.5 * out["range"][0]


# ---------------------------------------------------------------- sampler (§4.1)

def _brute_scale_function(h, w, wavelet, level, iy, ix):
    """Phi_{k,iy,ix} over the pixels by analysing every delta image (no matrices)."""
    deltas = np.zeros((h, w, h * w))
    deltas[np.unravel_index(np.arange(h * w), (h, w)) + (np.arange(h * w),)] = 1.0
    _, _, _, scales = analyze(deltas, wavelet, level)
    return scales[level - 1][iy, ix].reshape(h, w)


def _brute_basis(h, w, wavelet, level, key, iy, ix):
    """Psi^key_{k,iy,ix} over the pixels by analysing every delta image."""
    deltas = np.zeros((h, w, h * w))
    deltas[np.unravel_index(np.arange(h * w), (h, w)) + (np.arange(h * w),)] = 1.0
    _, det, _, _ = analyze(deltas, wavelet, level)
    return det[level - 1][key][iy, ix].reshape(h, w)


def test_priority_eq8_against_brute_force(rng):
    h, w, L = 21, 26, 3
    mean = rng.random((h, w, 3))
    var = rng.random((h, w)) * 0.1
    pri = scale_priorities(mean, var, levels=L)
    np.testing.assert_array_equal(pri[0], var)          # level 0: the pixels, no wavelets
    # Wavelets of the intensity (channel-mean) image, by brute force too.
    inten = mean.mean(axis=2)
    for k, (iy, ix) in ((1, (4, 7)), (2, (3, 5)), (3, (2, 2))):
        phi = _brute_scale_function(h, w, "cdf97", k, iy, ix)
        s_var = np.sum(phi ** 2 * var) * renormalisation_factor("cdf97", k, "aa", SAMPLING_RENORM)
        w2 = 0.0
        for key in ("ad", "da", "dd"):
            psi = _brute_basis(h, w, "cdf97", k, key, iy, ix)
            w2 += np.sum(psi * inten) ** 2 / 3
        # The sampler analyses the means in float32 (ranking only): 1e-6 relative.
        assert pri[k][iy, ix] == pytest.approx(s_var - w2, abs=1e-6 * (s_var + w2))


@pytest.mark.parametrize("wavelet", ["cdf97", "legall53"])
def test_importance_sampling_follows_abs_scale_function(wavelet):
    """Fig. 5: positions of one coefficient are distributed as |Phi| (chi^2 test
    on pixel counts, 40 000 samples, p > 1e-4 for a fixed seed)."""
    h, w, k, iy, ix = 40, 44, 2, 5, 6
    rng = np.random.default_rng(55)
    n = 40_000
    pos = sample_scale_functions(k, [iy], [ix], [n], width=w, height=h, rng=rng, wavelet=wavelet, levels=3)
    assert pos.shape == (n, 2)
    assert pos[:, 0].min() >= 0 and pos[:, 0].max() < w and pos[:, 1].min() >= 0 and pos[:, 1].max() < h
    phi = np.abs(_brute_scale_function(h, w, wavelet, k, iy, ix))
    p = phi / phi.sum()
    cnt = np.zeros((h, w))
    np.add.at(cnt, (pos[:, 1].astype(int), pos[:, 0].astype(int)), 1)
    assert cnt[p == 0].sum() == 0
    keep = p * n >= 5
    exp = p[keep] * n
    obs = cnt[keep]
    chi2 = np.sum((obs - exp) ** 2 / exp) + (cnt[~keep].sum() - n * p[~keep].sum()) ** 2 / max(n * p[~keep].sum(), 1e-9)
    dof = keep.sum()
    assert sstats.chi2.sf(chi2, dof) > 1e-4
    # Level 0 is the pixel itself.
    p0 = sample_scale_functions(0, [3], [9], [100], width=w, height=h, rng=rng, wavelet=wavelet)
    assert np.all(np.floor(p0) == [9, 3])


def _noisy_stats(h, w, spp, seed, scale=1.0):
    from mcrecon.core.requests import jittered_positions
    rng = np.random.default_rng(seed)
    pos = jittered_positions(np.full((h, w), spp), rng)
    n = len(pos)
    xx = pos[:, 0]
    base = np.where(xx > w / 2, 1.0, 0.2)[:, None] * scale
    val = base * (0.5 + rng.random((n, 3)))
    return PixelStats.from_samples(pos, val, width=w, height=h)


def test_plan_positions_budget_threshold_and_determinism():
    st = _noisy_stats(48, 40, 4, 1)
    pos, info = plan_awr_positions(st, 5000, np.random.default_rng(3))
    assert pos.shape == (5000, 2)
    assert pos[:, 0].max() < 40 and pos[:, 1].max() < 48 and pos.min() >= 0
    assert sum(info["levels_used"].values()) == 5000
    pos2, _ = plan_awr_positions(st, 5000, np.random.default_rng(3))
    np.testing.assert_array_equal(pos, pos2)                   # resume contract: same state + rng
    none, info = plan_awr_positions(st, 5000, np.random.default_rng(3), priority_threshold=1e9)
    assert none is None and info["max_priority"] < 1e9
    # Only coefficients above the threshold get samples.
    thr = np.quantile(st.count * 0 + pixel_variance(st, "contrast").mean(2), 0.9)
    p3, info3 = plan_awr_positions(st, 10 ** 7, np.random.default_rng(3), priority_threshold=thr)
    assert 0 < len(p3) < 10 ** 7


def test_pending_samples_count_as_taken():
    """A pipelined plan discounts the round in flight: sigma^2(B) = sigma^2(F) / (N + pending)."""
    st = _noisy_stats(48, 40, 4, 1)
    base, _ = plan_awr_positions(st, 5000, np.random.default_rng(3))
    # no pending sample (or none given): the sequential plan, bit for bit
    same, _ = plan_awr_positions(st, 5000, np.random.default_rng(3), pending=np.zeros((48, 40), np.int64))
    np.testing.assert_array_equal(base, same)
    # many samples in flight in the left half: the batch goes mostly to the right half
    pending = np.zeros((48, 40), np.int64)
    pending[:, :20] = 64
    pos, _ = plan_awr_positions(st, 5000, np.random.default_rng(3), pending=pending)
    assert pos.shape == (5000, 2)
    left_before = np.mean(base[:, 0] < 20)
    left_after = np.mean(pos[:, 0] < 20)
    assert left_after < 0.5 * left_before
    # the pending samples discount exactly as committed ones would in Eq. 6
    from mcrecon.methods.awr import sampling

    seen = {}
    orig = sampling.scale_priorities

    def spy(mean, var, **kw):
        seen["var"] = var
        return orig(mean, var, **kw)

    sampling.scale_priorities = spy
    try:
        plan_awr_positions(st, 5000, np.random.default_rng(3), pending=pending)
    finally:
        sampling.scale_priorities = orig
    f = functional_variance(st, "contrast")
    np.testing.assert_allclose(seen["var"], f / np.maximum(st.count + pending, 1)[..., None], rtol=1e-15)


def test_method_plan_respects_remaining_and_returns_none():
    m = AWRMethod(variant="paper", round_spp=1.0)
    st = PixelStats(30, 20)
    state = AdaptiveState(st, 0, budget=30 * 20 * 6 + 17, n_samples=0, rng=np.random.default_rng(0))
    run = m.start(30, 20)
    from mcrecon.adaptive.schedule import _initial_request
    req = _initial_request(m, state, 1)  # the driver takes the initial pass the method declares
    assert req.counts is not None and req.total == 4 * 600            # initial 4 spp (paper)
    st2 = _noisy_stats(20, 30, 4, 2)
    state = AdaptiveState(st2, 1, budget=st2.n_samples + 17, n_samples=st2.n_samples, rng=np.random.default_rng(1))
    req = m.plan(run, state)
    assert req.counts is not None and req.positions is None and req.total == 17  # never more than remaining
    state = AdaptiveState(st2, 2, budget=st2.n_samples, n_samples=st2.n_samples, rng=np.random.default_rng(1))
    assert m.plan(run, state) is None
    m2 = AWRMethod(variant="paper", priority_threshold=1e6)
    state = AdaptiveState(st2, 1, budget=10 ** 6, n_samples=st2.n_samples, rng=np.random.default_rng(1))
    assert m2.plan(m2.start(30, 20), state) is None


def test_sampler_prefers_coarse_levels_in_smooth_noise_and_fine_levels_at_edges():
    """Eq. 8's intent (Fig. 3): smooth high-variance regions go to coarse scale
    coefficients, a strong edge raises the coarse wavelets and lowers them."""
    h = w = 160                       # level-4 9/7 support is 145 pixels: fits
    mean = np.full((h, w, 1), 0.5)
    var = np.full((h, w), 0.01)
    pri = scale_priorities(mean, var, levels=4)
    # Constant variance, no wavelets: P_k = 0.01 * 1.05^(2k) in the interior.
    for k in (1, 2, 4):
        c = pri[k].shape[0] // 2
        assert pri[k][c, c] == pytest.approx(0.01 * SAMPLING_RENORM ** (2 * k), rel=1e-9)
    edge = mean.copy()
    edge[:, 81:] = 5.0
    pe = scale_priorities(edge, var, levels=4)
    # The edge's wavelets make the coarse coefficients on it the least wanted,
    # while the pixels beside it keep their variance as priority.
    for k in (1, 2, 3, 4):
        row = pe[k][pe[k].shape[0] // 2]
        assert row.min() < -1.0 < 0 < pe[0][80, 20]
        far = row[:2].mean()
        assert far > 0


# ---------------------------------------------------------------- robustness

@pytest.mark.parametrize("variant", ["paper", "robust"])
@pytest.mark.parametrize("h, w", [(1, 1), (1, 9), (7, 1), (13, 17), (8, 8)])
def test_tiny_and_prime_sizes(h, w, variant):
    st = _noisy_stats(h, w, 3, 4)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        img = mcrecon.reconstruct(st, method=AWRMethod(variant=variant))
        img2 = mcrecon.reconstruct(st, method=AWRMethod(variant=variant, levels=2)) if min(h, w) >= 2 else img
    assert img.shape == (h, w, 3) and np.isfinite(img).all() and np.isfinite(img2).all()


def test_extreme_inputs_stay_finite():
    rng = np.random.default_rng(8)
    h, w = 33, 40
    n = h * w * 8
    pos = rng.random((n, 2)) * [w, h]
    val = np.zeros((n, 3))
    hit = rng.random(n) < 0.03                                      # 97 % zeros, rare huge ones
    val[hit] = 1e4
    val[pos[:, 0] < 5] = 1e-3
    val[(pos[:, 0] > 30) & (pos[:, 1] < 5)] = 500.0                 # 1e-3 beside 500
    st = PixelStats.from_samples(pos, val, width=w, height=h)
    for est in ("range", "contrast", "sample"):
        for wv in BASES:
            for variant in ("paper", "robust"):
                img = mcrecon.reconstruct(st, method=AWRMethod(variant=variant, variance=est, wavelet=wv))
                assert np.isfinite(img).all()
    one = PixelStats.from_samples(rng.random((h * w, 2)) * [w, h], rng.random((h * w, 3)), width=w, height=h)
    with pytest.warns(McreconWarning, match="without samples filled"):     # ~1 spp, many empty pixels
        img = mcrecon.reconstruct(one, method=AWRMethod(variant="paper", variance="sample"))
    assert np.isfinite(img).all()
    with pytest.warns(McreconWarning, match="without samples filled"):
        img = mcrecon.reconstruct(one, method=AWRMethod())
    assert np.isfinite(img).all()
    pri = scale_priorities(st.mean, pixel_variance(st, "contrast"), levels=3)
    assert all(np.isfinite(p).all() for p in pri)


def test_default_levels_rule():
    assert default_levels((1024, 1024)) == 6 and default_levels((128, 128)) == 5
    assert default_levels((64, 333)) == 4 and default_levels((7, 500)) == 0


# ---------------------------------------------------------------- scenes

def _scene_stats(scene, size, spp, seed):
    from mcrecon.renderers.scenes import render_uniform
    b = render_uniform(scene, width=size, height=size, spp=spp, seed=seed)
    return PixelStats.from_samples(b.positions, b.values, width=size, height=size)


# Where the paper's AWR beats the box filter at 128x128, 32 spp (measured,
# seeds 0-3 all alike).  The cases where it loses (an HDR edge or rare huge
# samples make the variance image huge and the shrinkage leaks into 1e-3
# pixels: soft_shadow/range, caustic, hdr) are measured limits, not tests:
# ``python benchmarks/bench_awr.py --limits`` prints them against box, and
# docs/methods/awr.md ("Measured limits") quotes the numbers.
# The third field is the measured relative MSE ratio AWR / box of the test's seed.
_AWR_WINS = [("soft_shadow", "sample", 0.709), ("depth_of_field", "range", 0.943),
             ("depth_of_field", "sample", 0.580), ("motion_blur", "range", 0.824), ("motion_blur", "sample", 0.559),
             ("flat", "range", 0.0234), ("flat", "sample", 0.336)]


@pytest.mark.parametrize("scene, variance, measured", _AWR_WINS)
def test_awr_vs_box_on_scenes(scene, variance, measured):
    """Offline AWR beats box at 32 spp, 128x128 (relative MSE, eps 0.01) where measured to.

    Bound: the measured ratio to box + 15 % (the seed is fixed), and never above box (the
    smallest win, depth_of_field with the range estimator, is 5.7 %).
    """
    from mcrecon.core.metrics import relative_mse
    from mcrecon.renderers.scenes import reference_image
    size = 128
    ref = reference_image(scene, size, size)
    st = _scene_stats(scene, size, 32, seed=1)
    box = relative_mse(mcrecon.reconstruct(st, method="box"), ref)
    awr = relative_mse(mcrecon.reconstruct(st, method="awr", variant="paper", variance=variance), ref)
    assert awr < min(1.0, 1.15 * measured) * box, (awr / box, measured)


@pytest.mark.parametrize("scene, measured", [("motion_blur", 0.550), ("caustic", 0.848), ("flat", 0.223)])
def test_adaptive_awr_vs_box_on_scenes(scene, measured):
    """The full method (AWR sampling + AWR reconstruction, paper defaults) beats
    uniform box at 32 spp, 128x128 where measured to: ``measured`` is the ratio
    of relative MSEs to box of the test's seed; bound it + 15 %, below box.  On
    soft_shadow it ties (0.90-1.00x over 4 seeds, docs/methods/awr.md): a
    benchmark row, not an assertion.  It loses on depth_of_field and hdr: measured
    limits (``python benchmarks/bench_awr.py --limits``, docs/methods/awr.md)."""
    from mcrecon.adaptive.run import adapt
    from mcrecon.core.metrics import relative_mse
    from mcrecon.renderers.scenes import SceneRenderer, reference_image
    size = 128
    ref = reference_image(scene, size, size)
    box = relative_mse(mcrecon.reconstruct(_scene_stats(scene, size, 32, seed=1), method="box"), ref)
    res = adapt(SceneRenderer(scene, width=size, height=size, seed=1), get_method("awr", variant="paper"), spp=32, seed=1,
                progress=False, track_error=False)
    adaptive = relative_mse(res.image, ref)
    assert adaptive < min(1.0, 1.15 * measured) * box, (adaptive / box, measured)


@pytest.mark.parametrize("scene", ["soft_shadow", "depth_of_field"])
def test_adaptive_awr_vs_offline_awr(scene):
    """Adaptive AWR (paper defaults) vs offline AWR on uniform samples, equal
    spp (32, 128x128): the adaptive run spends exactly its budget, and beats
    offline AWR on soft_shadow (2.8e-3 vs 4.1e-3).  On depth_of_field the
    paper's sampler loses (4.1e-3 vs 2.6e-3, 2 seeds: it allocates worse
    than uniform, test_depth_of_field_loss_is_the_sample_allocation): a
    measured limit (``python benchmarks/bench_awr.py --limits``), not asserted."""
    from mcrecon.adaptive.run import adapt
    from mcrecon.core.metrics import relative_mse
    from mcrecon.renderers.scenes import SceneRenderer, reference_image
    size = 128
    res = adapt(SceneRenderer(scene, width=size, height=size, seed=1), get_method("awr", variant="paper"), spp=32, seed=1,
                progress=False, track_error=False)
    assert int(res.counts.sum()) == 32 * size * size
    assert np.isfinite(res.image).all()
    if scene == "soft_shadow":
        ref = reference_image(scene, size, size)
        off = relative_mse(mcrecon.reconstruct(_scene_stats(scene, size, 32, seed=1), method="awr", variant="paper"), ref)
        adaptive = relative_mse(res.image, ref)
        assert adaptive < off, (adaptive, off)


def test_awr_sampling_with_box_reconstruction():
    """Paper Fig. 10: the sampler alone, another reconstruction (option
    ``reconstruction='box'``) returns the pixel means of the adaptive samples."""
    from mcrecon.adaptive.run import adapt
    from mcrecon.renderers.scenes import SceneRenderer
    res = adapt(SceneRenderer("soft_shadow", width=48, height=40, seed=2), get_method("awr", variant="paper", reconstruction="box"),
                spp=12, seed=2, progress=False, track_error=False)
    np.testing.assert_array_equal(res.image, res.stats.mean)
    assert res.counts.max() > 4 * res.counts.min()                    # really adaptive


def test_adaptive_run_reports_the_sample_density_map():
    """``finish`` publishes the per-pixel sample counts as diagnostic ``samples``."""
    from mcrecon.adaptive.run import adapt
    from mcrecon.renderers.scenes import SceneRenderer
    for recon in ("awr", "box"):
        m = get_method("awr", variant="paper", reconstruction=recon)
        res = adapt(SceneRenderer("soft_shadow", width=40, height=36, seed=3), m, spp=10, seed=3, progress=False,
                    track_error=False)
        d = res.diagnostics()
        np.testing.assert_array_equal(d["samples"], res.counts)
        assert d["samples"].shape == (36, 40) and d["samples"].sum() == 10 * 36 * 40


def test_depth_of_field_loss_is_the_sample_allocation():
    """Why adaptive AWR loses to offline AWR on depth_of_field (128^2, 32 spp,
    seed 1; a measured limit, ``benchmarks/bench_awr.py --limits``).  Measured, and asserted so that a change
    of mechanism is noticed:

    * the sample allocation is bimodal, 4 or >= 64 spp: level-0 pops (64
      samples into one pixel, decided from a 4-sample contrast) take >= 90 %
      of the samples after round 1 (47 % of pixels stay at 4 spp, 40 % get
      >= 64; 51 % have <= 5);
    * that allocation is worse than uniform for *any* reconstruction: box
      of the adaptive samples 7.8e-3 vs uniform box 2.75e-3;
    * the reconstruction's variance estimate is not the cause: AWR of the
      adaptive samples with the exact variance sigma^2(F) / N (sigma^2(F)
      from an independent 256 spp render) gives 4.0e-3, still above offline
      AWR's 2.6e-3 (range estimator, uniform samples).

    Margins: 2.8x (box), 1.53x (oracle AWR, asserted 1.3x); the oracle variance from 256
    samples has relative sd sqrt(2/255) = 9 % per pixel, which moves the
    AWR error by ~1 % (measured 4.0e-3 at 256 and 512 spp).
    """
    from mcrecon.adaptive.run import adapt
    from mcrecon.core.metrics import relative_mse
    from mcrecon.renderers.scenes import SceneRenderer, reference_image
    size, scene = 128, "depth_of_field"
    ref = reference_image(scene, size, size)
    uni = _scene_stats(scene, size, 32, seed=1)
    res = adapt(SceneRenderer(scene, width=size, height=size, seed=1), get_method("awr", variant="paper"), spp=32, seed=1,
                progress=False, track_error=False)
    c = res.counts
    assert np.mean(c <= 5) > 0.35 and np.mean(c >= 64) > 0.3
    assert relative_mse(res.stats.mean, ref) > 1.5 * relative_mse(uni.mean, ref)
    big = _scene_stats(scene, size, 256, seed=99)
    sig2 = big.m2 / (big.count[..., None] - 1)
    oracle = awr_reconstruct(res.stats.mean, sig2 / res.stats.count[..., None])
    offline = relative_mse(mcrecon.reconstruct(uni, method="awr", variant="paper"), ref)
    assert relative_mse(oracle, ref) > 1.3 * offline


def test_diagnostics_maps():
    st = _noisy_stats(20, 30, 4, 5)
    m = AWRMethod(variant="paper")
    run = m.start(30, 20)
    img = m.reconstruct(MethodInputs(st), run=run)
    d = m.diagnostics(run)
    assert set(d) == {"pixel_std", "smoothing"}
    assert d["pixel_std"].shape == (20, 30) and d["smoothing"].shape == (20, 30)
    np.testing.assert_allclose(d["smoothing"], np.abs(img - st.mean).mean(axis=2))
    np.testing.assert_allclose(d["pixel_std"], np.sqrt(pixel_variance(st, "range")).mean(axis=2))

"""nfor (Bitterli et al. 2016): the regression's exactness, brute-force weights and averaging,
the cross-buffer construction, the paper's qualitative result, the method end to end."""

import warnings

import numpy as np
import pytest

import mcrecon
from mcrecon.core.fill import mean_variance_policy
from mcrecon.core.halves import split_halves
from mcrecon.core.metrics import relative_mse
from mcrecon.core.requests import SampleBatch
from mcrecon.core.samples import SampleSet
from mcrecon.errors import InputError
from mcrecon.filters.cross_bilateral import cross_bilateral
from mcrecon.methods.auto.nlmeans import nlmeans_cross
from mcrecon.methods.nfor.method import feature_planes
from mcrecon.filters.nlmeans import DISTANCE_CLAMP, MIN_CENTER_WEIGHT, NLM_EPS, nlmeans_filter
from mcrecon.methods.nfor.pipeline import cross_regression, estimate_mse, nfor_denoise, prefilter_features
from mcrecon.filters.nlmeans import exp_neg
from mcrecon.filters.regression import RIDGE, collaborative_regression, standardise

from helpers import jittered_renderer
from nfor_reference import collaborative_regression_reference, nlmeans_filter_reference
from nfor_scene import scene_reference, scene_samples, scene_values


# ------------------------------------------------------------------ brute force
def _weights_brute(guide, var, r, f, k, per_channel):
    """w[p, q] of every pair of a (2r+1)^2 window by explicit loops: the patch mean (over pairs s, s + o
    inside the image) of the clamped variance-cancelled distance, exp(-max(0, .)), centre >= 1e-4."""
    h, w, c = guide.shape
    out = {}
    for i in range(h):
        for j in range(w):
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    qi, qj = i + dy, j + dx
                    if not (0 <= qi < h and 0 <= qj < w):
                        continue
                    ds = []
                    for si in range(i - f, i + f + 1):
                        for sj in range(j - f, j + f + 1):
                            if 0 <= si < h and 0 <= sj < w and 0 <= si + dy < h and 0 <= sj + dx < w:
                                vp, vq = var[si, sj], var[si + dy, sj + dx]
                                d = ((guide[si, sj] - guide[si + dy, sj + dx]) ** 2 - (vp + np.minimum(vp, vq))) \
                                    / (NLM_EPS + k * k * (vp + vq))
                                ds.append(np.minimum(d, DISTANCE_CLAMP))
                    dist = np.mean(ds, axis=0)  # per channel
                    wt = np.exp(-np.maximum(dist, 0.0))
                    wt = wt if per_channel else wt.min()
                    if dy == 0 and dx == 0:
                        wt = np.maximum(wt, MIN_CENTER_WEIGHT)
                    out[(i, j, qi, qj)] = wt
    return out


def _tiny(seed=0, h=9, w=10):
    rng = np.random.default_rng(seed)
    y = rng.gamma(2.0, 1.0, size=(h, w, 3))
    guide = y + rng.normal(0, 0.5, size=(h, w, 3))
    var = rng.uniform(0.05, 0.3, size=(h, w, 3))
    feats = np.concatenate([rng.uniform(0, 1, size=(h, w, 2)), np.linspace(0, 1, w)[None, :, None].repeat(h, 0)],
                           axis=2)
    return y, guide.astype(np.float32).astype(np.float64), var.astype(np.float32).astype(np.float64), feats


def test_nlmeans_filter_matches_brute_force_weights():
    y, guide, var, _ = _tiny()
    r, f, k = 2, 1, 0.7
    wts = _weights_brute(guide, 2.0 * var, r, f, k, per_channel=True)
    want_num = np.zeros_like(y)
    want_den = np.zeros_like(y)
    for (i, j, qi, qj), wt in wts.items():
        want_num[i, j] += wt * y[qi, qj]
        want_den[i, j] += wt
    got = nlmeans_filter(y, guide, var, radius=r, patch=f, k=k, variance_scale=2.0)
    np.testing.assert_allclose(got, want_num / want_den, rtol=2e-5)


def _brute_weights_and_features(y, guide, var, feats, r, f, k):
    """The regression's NL-means weights by brute force and its standardised features."""
    wts = _weights_brute(guide, 2.0 * var, r, f, k, per_channel=False)
    return wts, np.moveaxis(standardise(np.moveaxis(feats, 2, 0)), 0, 2)


def _fit_window(y, fs, wts, r, i, j):
    """The weighted ridge fit of the window centred on (i, j): its pixels, their weights, its predictions."""
    win = [(qi, qj) for (pi, pj, qi, qj) in wts if (pi, pj) == (i, j)]
    wv = np.array([wts[(i, j, qi, qj)] for qi, qj in win])
    x = np.array([[1.0, (qj - j) / r, (qi - i) / r, *(fs[qi, qj] - fs[i, j])] for qi, qj in win])
    a = x.T @ (wv[:, None] * x) + RIDGE * wv.sum() * np.diag([0.0] + [1.0] * (x.shape[1] - 1))
    beta = np.linalg.solve(a, x.T @ (wv[:, None] * np.array([y[q] for q in win])))
    return win, wv, x @ beta


def test_collaborative_regression_matches_brute_force_fits_and_averaging():
    y, guide, var, feats = _tiny(1)
    r, f, k = 2, 1, 0.8
    h, w, _ = y.shape
    wts, fs = _brute_weights_and_features(y, guide, var, feats, r, f, k)
    num, den = np.zeros_like(y), np.zeros((h, w))
    for i in range(h):
        for j in range(w):
            win, wv, preds = _fit_window(y, fs, wts, r, i, j)
            for (qi, qj), wt, pred in zip(win, wv, preds):  # each fit predicts its whole window
                num[qi, qj] += wt * pred
                den[qi, qj] += wt
    got, got_den = collaborative_regression(y, guide, var, feats, radius=r, patch=f, k=k, return_weights=True)
    np.testing.assert_allclose(got_den, den, rtol=2e-5)
    np.testing.assert_allclose(got, num / den[..., None], rtol=1e-4, atol=1e-6)
    # row bands accumulate privately and are summed in a fixed order: any thread count, the same bits
    np.testing.assert_array_equal(collaborative_regression(y, guide, var, feats, radius=r, patch=f, k=k, threads=1),
                                  collaborative_regression(y, guide, var, feats, radius=r, patch=f, k=k, threads=2))


def test_centre_weight_is_the_derivative_of_each_output_by_its_own_input():
    """With the guide and the features fixed the regression is linear in the image: a unit impulse at
    pixel i moves output i by exactly the centre weight (for every channel), and asking for it changes
    neither the image nor the weights."""
    y, guide, var, feats = _tiny(2, h=8, w=11)
    r, f, k = 3, 1, 0.8
    plain, den = collaborative_regression(y, guide, var, feats, radius=r, patch=f, k=k, return_weights=True)
    out, den2, cw = collaborative_regression(y, guide, var, feats, radius=r, patch=f, k=k, return_weights=True,
                                             return_centre_weight=True)
    np.testing.assert_array_equal(out, plain)
    np.testing.assert_array_equal(den2, den)
    h, w, c = y.shape
    for i in range(h):
        for j in range(w):
            for ch in range(c):
                e = np.zeros_like(y)
                e[i, j, ch] = 1.0
                moved = collaborative_regression(y + e, guide, var, feats, radius=r, patch=f, k=k) - plain
                assert moved[i, j, ch] == pytest.approx(cw[i, j], rel=1e-9, abs=1e-12)
    assert 0.0 < cw.min() and cw.max() <= 1.0 + 1e-12


# ------------------------------------------------------------------ fast kernels = the reference kernels
def test_exp_neg_is_exp_to_1e_9_and_zero_beyond_80():
    t = np.concatenate([np.linspace(0.0, 80.0, 4001), [1e-12, 79.999, 80.0]])
    got = np.array([exp_neg(x) for x in t])
    np.testing.assert_allclose(got, np.exp(-t), rtol=1e-9, atol=0)
    assert exp_neg(0.0) == 1.0 and exp_neg(80.0 + 1e-9) == 0.0 and exp_neg(1e4) == 0.0


@pytest.mark.parametrize("r, f", [(4, 3), (9, 1), (2, 0)])
def test_fast_kernels_equal_the_reference_kernels_to_1e_6(r, f):
    """The vectorised kernels (direct patch sums, offset-major normal equations, polynomial exp) against
    the first implementation (summed-area tables, per-window dot products, math.exp), kept in
    tests/nfor_reference.py: they differ by rounding only (a float32 patch distance one ulp apart: measured 1.3e-7
    at most at 128^2); weights with bimodal
    distances, features with a gradient and noise, and a border wider than the window on a 37 x 41 image."""
    rng = np.random.default_rng(7)
    h, w = 37, 41
    y = rng.gamma(2.0, 1.0, size=(h, w, 3)) * np.where(rng.uniform(size=(h, w, 1)) < 0.5, 1.0, 8.0)
    guide = y * rng.exponential(1.0, size=y.shape)
    var = rng.uniform(0.05, 3.0, size=y.shape)
    feats = rng.uniform(size=(h, w, 5)) + np.linspace(0, 4, w)[None, :, None]
    np.testing.assert_allclose(nlmeans_filter(y, guide, var, radius=r, patch=f, k=0.6, variance_scale=2.0),
                               nlmeans_filter_reference(y, guide, var, radius=r, patch=f, k=0.6, variance_scale=2.0),
                               rtol=1e-6)
    got, got_w = collaborative_regression(y, guide, var, feats, radius=r, patch=f, k=0.8, return_weights=True)
    want, want_w = collaborative_regression_reference(y, guide, var, feats, radius=r, patch=f, k=0.8,
                                                      return_weights=True)
    np.testing.assert_allclose(got_w, want_w, rtol=1e-6)
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-9 * np.abs(want).max())
    # row bands in parallel, each pixel's sums in a fixed order: the same bits on any thread count
    np.testing.assert_array_equal(nlmeans_filter(y, guide, var, radius=r, patch=f, k=0.6, threads=1),
                                  nlmeans_filter(y, guide, var, radius=r, patch=f, k=0.6, threads=2))


# ------------------------------------------------------------------ exactness
def test_regression_reproduces_an_image_linear_in_the_features_exactly():
    """colour = a . albedo + b depth + c from noise-free features is in the span of every window's
    design: whatever the weights (here from a very noisy guide) each fit is exact, and so their average;
    a flat normal and collinear albedo channels (R = 2 G) only need the ridge."""
    rng = np.random.default_rng(5)
    h, w = 24, 26
    yy, xx = np.mgrid[0:h, 0:w]
    chk = np.where((yy // 4 + xx // 4) % 2 == 0, 0.9, 0.1)
    albedo = np.stack([chk, 0.5 * chk, 0.3 + 0.2 * np.sin(xx / 3.0)], axis=2)
    depth = 1.0 + 0.05 * xx + 0.02 * yy ** 1.5
    normal = np.zeros((h, w, 3)) + [0.0, 0.0, 1.0]
    feats = np.concatenate([albedo, depth[..., None], normal], axis=2)
    a = np.array([[2.0, 0.5, 0.1], [1.0, 3.0, 0.0], [0.2, 0.0, 4.0]])
    colour = albedo @ a.T + np.array([0.7, -0.2, 1.5]) * depth[..., None] + np.array([0.5, 1.0, 2.0])
    guide = colour * rng.exponential(1.0, size=colour.shape)  # strong noise: weights far from uniform
    var = np.full(colour.shape, 0.5)
    out = collaborative_regression(colour, guide, var, feats, radius=4, patch=1, k=0.5)
    np.testing.assert_allclose(out, colour, rtol=0, atol=1e-6 * np.abs(colour).max())
    # HDR: a huge scale is neither clipped nor rescaled (the fit is linear in the colour)
    big = collaborative_regression(1e6 * colour, guide, var, feats, radius=4, patch=1, k=0.5)
    np.testing.assert_allclose(big, 1e6 * colour, rtol=1e-6)


# ------------------------------------------------------------------ cross-buffer
def test_cross_buffer_weights_and_features_come_from_the_other_half():
    """F_A = regression of y_A with B's colour as the weights' guide and B's features: F_A is linear in
    y_A (weights independent of it), does not change with A's features, and does change with y_B."""
    rng = np.random.default_rng(2)
    h, w = 16, 18
    y_a, y_b, y_c = (rng.gamma(2.0, 1.0, size=(h, w, 3)) for _ in range(3))
    var = np.full((h, w, 3), 0.2)
    pf_a, pf_b, pf_c = (rng.uniform(size=(h, w, 4)) for _ in range(3))
    kw = dict(radius=3, patch=1, k=0.7)
    fa, fb = cross_regression(y_a, y_b, var, pf_a, pf_b, **kw)
    # superposition in y_A with y_B fixed: the weights and design do not see y_A
    f1, _ = cross_regression(y_c, y_b, var, pf_a, pf_b, **kw)
    f12, _ = cross_regression(y_a + 2.0 * y_c, y_b, var, pf_a, pf_b, **kw)
    np.testing.assert_allclose(f12, fa + 2.0 * f1, rtol=1e-9, atol=1e-9)
    # A's own features play no part in F_A (nor B's in F_B)
    fa2, fb2 = cross_regression(y_a, y_b, var, pf_c, pf_b, **kw)
    np.testing.assert_array_equal(fa2, fa)
    fa3, fb3 = cross_regression(y_a, y_b, var, pf_a, pf_c, **kw)
    np.testing.assert_array_equal(fb3, fb)
    assert np.abs(fb2 - fb).max() > 1e-3 and np.abs(fa3 - fa).max() > 1e-3
    # the guide is B: changing y_B changes F_A, and F_A is not F_A's own NL-means-of-A
    fa4, _ = cross_regression(y_a, y_c, var, pf_a, pf_b, **kw)
    assert np.abs(fa4 - fa).max() > 1e-3
    # the feature prefilter: A's features are a linear filter of A with weights from B
    g_a, g_b = prefilter_features(pf_a, pf_b, var[..., :1].repeat(4, 2), radius=2, patch=1, k=0.5)
    g_a2, _ = prefilter_features(pf_a + pf_c, pf_b, var[..., :1].repeat(4, 2), radius=2, patch=1, k=0.5)
    g_c, _ = prefilter_features(pf_c, pf_b, var[..., :1].repeat(4, 2), radius=2, patch=1, k=0.5)
    np.testing.assert_allclose(g_a2, g_a + g_c, rtol=1e-9, atol=1e-12)


def test_dual_buffer_mse_estimate_is_unbiased_for_a_fixed_linear_filter():
    """E[estimate_mse] = MSE of (F_A + F_B) / 2 when F_A is a filter of y_A alone (brute-force Monte Carlo)."""
    rng = np.random.default_rng(11)
    truth = np.array([1.0, 2.0, 3.0, 4.0])
    sig2 = 0.5  # variance of a half's mean: the full buffer's mean has sig2 / 2
    n = 200_000
    y_a = truth + rng.normal(0, np.sqrt(sig2), size=(n, 4))
    y_b = truth + rng.normal(0, np.sqrt(sig2), size=(n, 4))
    filt = lambda y: 0.6 * y + 0.4 * y.mean(axis=1, keepdims=True)  # biased, variance-reducing
    f_a, f_b = filt(y_a), filt(y_b)
    est = estimate_mse(y_a, y_b, f_a, f_b, np.full((n, 4), sig2 / 2)).mean(axis=0)
    true = ((0.5 * (f_a + f_b) - truth) ** 2).mean(axis=0)
    se = estimate_mse(y_a, y_b, f_a, f_b, np.full((n, 4), sig2 / 2)).std(axis=0) / np.sqrt(n)
    assert np.all(np.abs(est - true) < 5 * se + 1e-12)


# ------------------------------------------------------------------ the paper's result
@pytest.fixture(scope="module")
def textured():
    ref = scene_reference(64, 64)
    return ref, scene_samples(64, 64, 16, seed=0)


def test_nfor_beats_cross_bilateral_colour_nlmeans_and_the_pixel_mean_on_a_textured_scene(textured):
    """Checkerboard albedo x smooth shading, a defocused band with noisy features, 16 spp: measured
    relative MSE ratios nfor / cross-bilateral 0.211, nfor / colour NL-means 0.256, nfor / box 0.137,
    cross-bilateral / box 0.647, NL-means / box 0.534.  Bounds: each measured ratio + 15 % (fixed seeds:
    deterministic), so a 20 % regression of nfor or of a baseline fails."""
    ref, ss = textured
    img = mcrecon.reconstruct(ss, method="nfor", variant="paper")
    h = split_halves(ss, features="all")
    st = h.a.copy().merge(h.b)
    var = mean_variance_policy(st)
    fa, fb, fv = feature_planes(h.a, h.b, st)
    cb = cross_bilateral(st.mean, var, 0.5 * (fa + fb), fv)
    na, _, nb, _ = nlmeans_cross(h.a.mean, mean_variance_policy(h.a), h.a.count, h.b.mean,
                                 mean_variance_policy(h.b), h.b.count, radius=7, patch=3)
    e = {name: relative_mse(im, ref) for name, im in
         (("nfor", img), ("cb", cb), ("nlm", 0.5 * (na + nb)), ("box", st.mean))}
    assert e["nfor"] < 0.25 * e["cb"], e   # measured 0.211; 15 % margin
    assert e["nfor"] < 0.30 * e["nlm"], e  # measured 0.256
    assert e["nfor"] < 0.16 * e["box"], e  # measured 0.137
    assert e["cb"] < 0.75 * e["box"] and e["nlm"] < 0.62 * e["box"], e  # measured 0.647, 0.534


# ------------------------------------------------------------------ end to end
def test_reconstruct_from_samples_equals_the_half_buffer_pair_and_refuses_without_features():
    ss = scene_samples(24, 20, 8, seed=3)
    rec = mcrecon.reconstruct(ss, method="nfor", full=True)
    img = rec.image
    diag = rec.diagnostics()
    assert set(diag) >= {"selection", "estimated_mse"} and 0 <= diag["selection"].min() <= diag["selection"].max() <= 1
    # the array-level pipeline: without the second pass, the image is the mean of the halves' results
    st = split_halves(ss, features="all")
    whole = st.a.copy().merge(st.b)
    fa, fb, fv = feature_planes(st.a, st.b, whole)
    d = {}
    one = nfor_denoise(st.a.mean, st.b.mean, mean_variance_policy(whole), fa, fb, fv, second_pass=False,
                       diagnostics=d)
    np.testing.assert_allclose(one, 0.5 * (d["half_results"][0] + d["half_results"][1]), rtol=1e-15)
    h = split_halves(ss, features="all")
    pair = mcrecon.reconstruct((h.a, h.b), method="nfor", radius=9)
    np.testing.assert_array_equal(img, pair)
    assert img.shape == (20, 24, 3) and np.isfinite(img).all()
    plain = SampleSet(ss.positions, ss.values, width=24, height=20)
    with pytest.raises(InputError, match="features"):
        mcrecon.reconstruct(plain, method="nfor")
    with pytest.raises(InputError, match="features"):
        mcrecon.reconstruct((h.a.without_features(), h.b.without_features()), method="nfor")
    with pytest.raises(InputError, match="bandwidths"):
        mcrecon.get_method("nfor", bandwidths="0.5,1,2")
    # the default departs from the paper's algorithm in the safeguard alone (docs/methods/nfor.md)
    paper, default = mcrecon.get_method("nfor", variant="paper").params, mcrecon.get_method("nfor").params
    differ = {k for k in paper if paper[k] != default[k]}
    assert differ == {"variant", "safeguard"} and paper["safeguard"] is None and default["safeguard"] == 4.0


def test_restoration_nfor_is_the_method_on_samples_and_on_a_half_buffer_pair():
    ss = scene_samples(20, 18, 8, seed=4)
    img = mcrecon.restoration.nfor(ss, radius=4)
    np.testing.assert_array_equal(img, mcrecon.reconstruct(ss, method="nfor", radius=4))
    h = split_halves(ss, features="all")
    np.testing.assert_array_equal(mcrecon.restoration.nfor((h.a, h.b), radius=4), img)
    with pytest.raises(InputError, match="features"):
        mcrecon.restoration.nfor(SampleSet(ss.positions, ss.values, width=20, height=18))
    with pytest.raises(InputError, match="valid: bandwidths"):
        mcrecon.restoration.nfor(ss, window=4)


def test_demo_runs_nfor_by_default_on_the_textured_scenes_only(tmp_path, monkeypatch, capsys):
    """The demo's default method list (here cut to box and nfor) keeps nfor on a scene that renders
    features (checker_wall) and leaves it out, saying why, on one that does not (soft_shadow)."""
    import re

    import mcrecon.methods
    from mcrecon.cli import main

    monkeypatch.setattr(mcrecon.methods, "available_methods", lambda: ["box", "nfor"])
    assert main(["demo", "--scene", "checker_wall", "--size", "16x16", "--spp", "4", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    errors = dict(re.findall(r"^(\w+)\s+relative MSE ([0-9.eE+-]+)", out, re.M))
    assert set(errors) == {"box", "nfor"} and "not run" not in out, out
    assert (tmp_path / "checker_wall_nfor.exr").exists()
    assert main(["demo", "--scene", "soft_shadow", "--size", "16x16", "--spp", "4", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert re.search(r"^box\s+relative MSE", out, re.M) and not re.search(r"^nfor\s", out, re.M)
    assert "not run: nfor" in out


def _renderer(features=True, w=20, h=16):
    def shade(pos, rng, request):
        val, feats = scene_values(pos, rng, w, h)
        return SampleBatch(pos, val, feats if features else {})
    return jittered_renderer(shade, width=w, height=h, name="textured")


def test_adaptive_runs_observe_the_halves_reuse_the_object_and_match_their_log(tmp_path):
    """An adaptive run's halves (built round by round by observe) are the log's split: the run's image is
    the offline image of its log; one method object serves runs as fresh ones do; no features: refused."""
    m = mcrecon.get_method("nfor", radius=4)
    res = mcrecon.adapt(_renderer(), m, spp=8, seed=1, log=str(tmp_path / "a.h5"), progress=False)
    # to rounding: the run accumulates the halves round by round, the reader in chunks of the log
    np.testing.assert_allclose(res.image, mcrecon.reconstruct(str(tmp_path / "a.h5"), method=m), rtol=1e-9)
    other = mcrecon.adapt(_renderer(w=13, h=9), m, spp=6, seed=2, progress=False)
    again = mcrecon.adapt(_renderer(), m, spp=8, seed=1, progress=False)
    np.testing.assert_array_equal(again.image, res.image)
    assert other.image.shape == (9, 13, 3) and np.isfinite(other.image).all()
    with pytest.raises(InputError, match="features"):
        mcrecon.adapt(_renderer(features=False), m, spp=4, seed=1, progress=False)


def test_sparse_pixels_and_a_firefly_stay_finite_and_unclipped():
    """Pixels with no sample in a half (or none at all) are filled, n < 2 follows the fill-in policy;
    a 1e6 firefly is not clipped (the image keeps energy of that order near it)."""
    rng = np.random.default_rng(8)
    w, h = 20, 16
    n = w * h * 3
    pos = rng.uniform(0, [w, h], size=(n, 2))
    pos = pos[~((pos[:, 0] < 3) & (pos[:, 1] < 3))]  # a 3 x 3 corner without samples
    val, feats = scene_values(pos, rng, w, h)
    val[0] = 1e6
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        img = mcrecon.reconstruct(SampleSet(pos, val, width=w, height=h, features=feats), method="nfor", radius=4)
    assert np.isfinite(img).all()
    px = np.floor(pos[0]).astype(int)
    assert img[max(px[1] - 4, 0):px[1] + 5, max(px[0] - 4, 0):px[0] + 5].max() > 1e3


def test_robust_is_the_paper_image_clamped_into_each_pixels_interval_bit_for_bit():
    """variant='robust' = confidence_clamp(paper image, mean, safeguard_variance(channel_floor(v, albedo), n, albedo),
    4, 3x3 sample range), then leave_out_isolated(., stats, 4)."""
    from mcrecon.core.safeguard import albedo_divisor, confidence_clamp, safeguard_variance, sample_range_bounds
    from mcrecon.methods.nfor.firefly import leave_out_isolated
    from mcrecon.methods.nfor.method import channel_floor

    ss = scene_samples(24, 20, 8, seed=5)
    paper = mcrecon.reconstruct(ss, method="nfor", variant="paper")
    robust = mcrecon.reconstruct(ss, method="nfor")
    h = split_halves(ss, features="all")
    st = h.a.copy().merge(h.b)
    lo, hi = sample_range_bounds(st)
    d = albedo_divisor(st)
    v = safeguard_variance(channel_floor(mean_variance_policy(st), d), st.count, d)
    np.testing.assert_array_equal(robust, leave_out_isolated(confidence_clamp(paper, st.mean, v, 4.0, lo, hi), st,
                                                             4.0))
    assert not np.array_equal(robust, paper)  # the clamp acts on this scene
    np.testing.assert_array_equal(mcrecon.reconstruct(ss, method="nfor", safeguard=None), paper)


def test_robust_default_stays_below_the_pixel_mean_under_a_caustic_where_the_paper_does_not():
    """The built-in caustic (rare huge samples), 32^2, 16 spp, seed 0. Measured over seeds 0-2: the paper's
    algorithm 2.4-3.2x the pixel mean's relMSE (its colour weights spread one pixel's caustic sample over exact
    dim neighbours), the robust default 0.12-0.41x.  Seed 0: paper 2.42x, robust 0.298x; asserted > 1.5
    (the paper's failure) and < 0.34 (the robust default's measured ratio + 15 %)."""
    from mcrecon.renderers import scenes

    ref = scenes.reference_image("caustic", 32, 32)
    b = scenes.render_uniform("caustic", width=32, height=32, spp=16, seed=0, features=True)
    ss = SampleSet(b.positions, b.values, width=32, height=32, features=b.features)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        e = {v: relative_mse(mcrecon.reconstruct(ss, method="nfor", variant=v), ref) for v in ("paper", "robust")}
    e_box = relative_mse(mcrecon.reconstruct(ss, method="box"), ref)
    assert e["paper"] > 1.5 * e_box, (e, e_box)
    assert e["robust"] < 0.34 * e_box, (e, e_box)  # measured 0.298; 15 % margin


def test_a_pixel_without_samples_keeps_its_filled_value_under_the_safeguard():
    """The clamp has no interval at an empty pixel (mean 0, variance 0): the default keeps the value the
    paper's algorithm filled in from the neighbours there (it was set to 0)."""
    from mcrecon.renderers import scenes

    b = scenes.render_uniform("checker_spot", width=24, height=20, spp=8, seed=3, features=True)
    keep = ~((np.floor(b.positions[:, 0]) == 15) & (np.floor(b.positions[:, 1]) == 10))
    ss = SampleSet(b.positions[keep], b.values[keep], width=24, height=20,
                   features={k: v[keep] for k, v in b.features.items()})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        paper = mcrecon.reconstruct(ss, method="nfor", variant="paper")
        robust = mcrecon.reconstruct(ss, method="nfor")
    assert (paper[10, 15] > 0.05).all()
    np.testing.assert_array_equal(robust[10, 15], paper[10, 15])


# ------------------------------------------------------------------ the safeguard keeps colours
def _caustic_shadow(seed=3, w=24, h=24, spp=32):
    """A sparse caustic's shadow (grey truth 0.18: 1 % of samples worth 18), one pixel holding a single red
    path (6, 0, 0) and nothing else, one a firefly (125) alone; constant features."""
    rng = np.random.default_rng(seed)
    pos = np.repeat(np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 2), spp, axis=0) \
        + rng.random((w * h * spp, 2))
    n = pos.shape[0]
    val = np.zeros((n, 3))
    val[rng.random(n) < 0.01] = 18.0 * np.array([1.0, 0.9, 0.8])
    pix = np.floor(pos[:, 1]).astype(int) * w + np.floor(pos[:, 0]).astype(int)
    red = np.flatnonzero(pix == 12 * w + 13)
    val[red] = 0.0
    val[red[0]] = (6.0, 0.0, 0.0)
    fly = np.flatnonzero(pix == 12 * w + 12)
    val[fly] = 0.0
    val[fly[0]] = 125.0
    feats = {"albedo": np.full((n, 3), 0.7), "normal": np.tile([0.0, 0.0, -1.0], (n, 1)), "depth": np.ones((n, 1))}
    return SampleSet(pos, val, width=w, height=h, features=feats)


def test_a_channel_whose_samples_are_all_zero_is_not_pinned_to_zero_beside_a_varying_one():
    # the per-channel clamp on the pixel's own variance gave (0.19, 0, 0): green and blue zeroed, a red dot
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        img = mcrecon.reconstruct(_caustic_shadow(), method="nfor")
        paper = mcrecon.reconstruct(_caustic_shadow(), method=mcrecon.get_method("nfor", variant="paper"))
    r, g, b = img[12, 13]
    assert g > 0.5 * r and b > 0.5 * r
    np.testing.assert_allclose(img[12, 13], paper[12, 13], rtol=1e-9)  # the clamp leaves it as the filter made it
    assert img[12, 12].max() < 0.5  # the lone firefly (3.9 in the pixel mean) does not stay

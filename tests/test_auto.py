"""The ``auto`` method: per-pixel selection among reconstructions by their estimated error."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import mcrecon
from mcrecon import PixelStats, SampleSet
from mcrecon.adaptive.run import adapt
from mcrecon.errors import InputError, McreconWarning
from mcrecon.core.halves import split_halves
from mcrecon.methods.auto.estimates import sure
from mcrecon.methods import get_method
from mcrecon.methods.auto import nlmeans_cross
from mcrecon.core.fill import mean_variance_policy
from mcrecon.core.metrics import relative_mse
from mcrecon.renderers.scenes import SceneRenderer


def _quiet(fn):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", McreconWarning)
        return fn()


def _samples(ref, sigma, spp, seed, *, heavy=False):
    rng = np.random.default_rng(seed)
    h, w, c = ref.shape
    pix = np.repeat(np.arange(h * w), spp)
    pos = np.stack([pix % w + rng.random(pix.size), pix // w + rng.random(pix.size)], axis=1)
    noise = rng.standard_normal((pix.size, c))
    if heavy:  # rare strong outliers (a firefly-like tail), mean-preserving
        hit = rng.random(pix.size) < 0.01
        noise = noise + hit[:, None] * 20.0 - 0.2
    val = ref.reshape(-1, c)[pix] + sigma.reshape(-1, c)[pix] * noise
    return SampleSet(pos, val, width=w, height=h)


def _scene_blobs(w=48, h=40):
    """Smooth blobs on a dark background, homoscedastic noise."""
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    ref = 0.05 + np.exp(-((xx - 15) ** 2 + (yy - 20) ** 2) / 60.0) + 0.5 * np.exp(-((xx - 35) ** 2 + (yy - 12) ** 2) / 20)
    ref = np.repeat(ref[..., None], 3, axis=2) * np.array([1.0, 0.7, 0.4])
    return ref, np.full(ref.shape, 0.4)


def _scene_edges(w=44, h=37):
    """Hard edges, a checkerboard corner and a thin bright line; noise grows with brightness."""
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    ref = np.where(xx > 20, 0.8, 0.1) + np.where((yy < 12) & ((xx // 4 + yy // 4) % 2 == 0), 0.5, 0.0)
    ref = ref + np.where(np.abs(yy - 28) < 0.6, 3.0, 0.0)
    ref = np.repeat(ref[..., None], 3, axis=2)
    return ref, 0.3 * np.sqrt(ref) + 0.05


@pytest.mark.parametrize("scene, measured", [(_scene_blobs, 0.0272), (_scene_edges, 0.322)])
def test_auto_is_not_worse_than_the_pixel_mean_on_procedural_scenes(scene, measured):
    """Mean over 4 seeds of relMSE(auto) / relMSE(box), 8 spp: measured blobs 0.0272 (seeds 0.024-0.029),
    edges 0.322 (0.30-0.33).  Bound: the measured mean + 15 % (the seeds are fixed, so the mean is
    deterministic; 15 % lets rounding-level changes pass and fails a 20 % regression)."""
    ref, sigma = scene()
    m = get_method("auto")
    ratios = []
    for seed in range(4):
        ss = _samples(ref, sigma, 8, seed)
        img = _quiet(lambda: mcrecon.reconstruct(ss, method=m))
        ratios.append(relative_mse(img, ref) / relative_mse(PixelStats.from_source(ss).mean, ref))
    assert np.mean(ratios) <= 1.15 * measured, ratios


def _caustic_ring_samples(seed, w=40, h=36, spp=16):
    """A ring of rare huge samples (p = 0.05, value 200) on exact zeros elsewhere: a caustic of
    our own.  Returns the samples and the exact expectation."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    ring = np.abs(np.hypot(xx - 20, yy - 18) - 10) < 1.5
    pix = np.repeat(np.arange(h * w), spp)
    hit = ring.ravel()[pix] & (rng.random(pix.size) < 0.05)
    val = np.repeat((200.0 * hit)[:, None], 3, axis=1)
    pos = np.stack([pix % w + rng.random(pix.size), pix // w + rng.random(pix.size)], axis=1)
    ref = np.repeat((ring * 10.0)[..., None], 3, axis=2)
    return SampleSet(pos, val, width=w, height=h), ref, ring


def test_safeguard_keeps_light_out_of_exact_dark_pixels_and_auto_below_the_pixel_mean():
    """Rare huge samples beside exact zeros (the caustic row of issue 12, where auto without the
    clamp measured 1.6x the pixel mean): with the default safeguard, pixels whose 3x3 neighbourhood
    holds only zero samples stay exactly 0, and the mean ratio to the pixel mean over 4 seeds is
    at most 0.40: measured 0.348 (per seed 0.28-0.39) with the clamp, 15 % margin; 147-223 per seed
    with safeguard=None (the noisy error estimates beside the ring vote wide filters that carry its
    light into the dark)."""
    m = get_method("auto")
    ratios = []
    for seed in range(4):
        ss, ref, ring = _caustic_ring_samples(seed)
        img = _quiet(lambda: mcrecon.reconstruct(ss, method=m))
        st = PixelStats.from_source(ss)
        from scipy import ndimage
        dark = ndimage.maximum_filter(st.max.max(axis=2), size=3, mode="nearest") == 0
        assert dark.any() and np.all(img[dark] == 0.0)
        ratios.append(relative_mse(img, ref) / relative_mse(st.mean, ref))
    assert np.mean(ratios) <= 0.40, ratios  # measured 0.348; 15 % margin
    assert get_method("auto", safeguard=None).params["safeguard"] is None


def test_default_safeguard_costs_nothing_on_a_flat_field():
    """The clamp at k standard errors moves a pixel *away* from the truth wherever its mean is
    more than k standard errors off: on a flat field (0.5 +- 0.5, 8 spp, 4 seeds) k = 2 costs
    1.15-1.21x the error of the same reconstruction without that part of the clamp
    (``safeguard=1e6`` keeps the sample-range bound and the zero-variance pins; 1.45-1.50x before
    the interval used the neighbourhood's pooled variance), the default k = 4 1.00x (measured;
    docs/methods/auto.md, "Safeguard width").  Bounds: 1.02, a few seed spreads above the default,
    and 1.1, below k = 2's lowest seed (the test tells them apart)."""
    h, w = 40, 48
    ref = np.full((h, w, 3), 0.5)
    sigma = np.full((h, w, 3), 0.5)
    err = {"default": [], 2.0: [], 1e6: []}
    for seed in range(4):
        ss = _samples(ref, sigma, 8, seed)
        for k in err:
            # the plain per-pixel choice (global_prior=None): what the clamp costs it.  With the global
            # prior's near-exact wide Gaussian on this field the same clamp is 1.17x of a far smaller error
            m = get_method("auto", global_prior=None) if k == "default" else \
                get_method("auto", safeguard=k, global_prior=None)
            err[k].append(relative_mse(_quiet(lambda: mcrecon.reconstruct(ss, method=m)), ref))
    assert get_method("auto").params["safeguard"] == 4.0
    assert np.mean(err["default"]) / np.mean(err[1e6]) <= 1.02, err
    assert np.mean(err[2.0]) / np.mean(err[1e6]) >= 1.1, err


def test_default_safeguard_still_protects_the_built_in_caustic():
    """The other side of the width: a clamp so wide that only the zero-variance pins and the sample
    range are left (``safeguard=1e6``) lets the caustic's light into its dark pixels.  Built-in
    caustic, 48x48, 32 spp, seeds 0-2: the default's mean relative MSE is 0.736x the unclamped one's
    (measured).  Bound: 0.85x, the measured ratio + 15 %."""
    from mcrecon.renderers import scenes

    sc = scenes.get_scene("caustic")
    ref = scenes.reference_image(sc, 48, 48)
    err = {"default": [], 1e6: []}
    for seed in range(3):
        b = scenes.render_uniform(sc, width=48, height=48, spp=32, seed=seed)
        ss = mcrecon.SampleSet(b.positions, b.values, width=48, height=48)
        for k in err:
            # the candidates without OIDN: what the clamp does to mcrecon's own filters (with OIDN the
            # unclamped run picks it more and the ratio is 0.91)
            m = get_method("auto", candidates="box,gauss,nlm") if k == "default" else \
                get_method("auto", candidates="box,gauss,nlm", safeguard=k)
            err[k].append(relative_mse(_quiet(lambda: mcrecon.reconstruct(ss, method=m)), ref))
    assert np.mean(err["default"]) <= 0.85 * np.mean(err[1e6]), err  # measured 0.736; 15 % margin


def test_diagnostics_are_present_finite_and_name_the_choice():
    ref, sigma = _scene_edges()
    ss = _samples(ref, sigma, 8, 0)
    rec = _quiet(lambda: mcrecon.reconstruct(ss, method="auto", full=True))
    d = rec.diagnostics()
    assert {"choice", "estimated_mse", "estimated_rel_mse"} <= set(d)
    for k, a in d.items():
        assert a.shape == ref.shape[:2] and np.isfinite(a).all(), k
    m = get_method("auto")
    names = m.candidate_names()
    assert names[0] == "box" and names[-3:] == ["nlm", "oidn", "oidn_halves"] and len(names) == 12
    assert d["choice"].min() >= 0 and d["choice"].max() < len(names)
    assert np.array_equal(d["choice"], np.round(d["choice"]))
    # (the default's global prior gives NL-means nearly every pixel of this scene: 1627 of 1628 before
    # the border's smaller effective count, all of them after; the plain per-pixel choice tells edges
    # from flat regions)
    plain = _quiet(lambda: mcrecon.reconstruct(ss, method=get_method("auto", global_prior=None), full=True))
    assert len(np.unique(plain.diagnostics()["choice"])) > 1


def test_candidates_option_is_validated_and_normalised():
    assert get_method("auto", candidates=" gauss, box ").params["candidates"] == "box,gauss"
    for bad, match in (("box,median", "'median' is not valid; valid: box, gauss"), ("", "no candidate"),
                       ("box,box", "twice")):
        with pytest.raises(InputError, match=match):
            get_method("auto", candidates=bad)
    assert get_method("auto").requires.samples
    assert not get_method("auto", candidates="box,gauss").requires.samples


def test_statistics_only_falls_back_to_sure_candidates():
    """SURE-only candidates work on pixel statistics (EXR inputs); the dual-buffer candidates
    without samples fall back to them with a warning."""
    ref, sigma = _scene_blobs()
    ss = _samples(ref, sigma, 8, 1)
    st = PixelStats.from_source(ss)
    img = mcrecon.restoration.auto(st, candidates="box,gauss")
    assert np.isfinite(img).all()
    assert relative_mse(img, ref) < 0.032 * relative_mse(st.mean, ref)  # measured 0.0278; 15 % margin
    m = get_method("auto")
    with pytest.raises(InputError, match="individual samples"):  # the reader refuses statistics up front
        mcrecon.reconstruct(st, method=m)
    from mcrecon.methods import MethodInputs
    with pytest.warns(McreconWarning, match="falls back to the SURE candidates"):
        img2 = m.reconstruct_run(m.start(st.width, st.height), MethodInputs(st))
    # OIDN needs no halves: without them it is scored by Monte-Carlo SURE and stays
    np.testing.assert_array_equal(img2, mcrecon.restoration.auto(st, candidates="box,gauss,oidn"))


def test_nlmeans_cross_sure_uses_the_exact_centre_weight():
    """F_B y_A is linear in y_A: perturbing y_A at a pixel changes the output there by w_ii."""
    rng = np.random.default_rng(0)
    ya, yb = rng.random((10, 12, 3)), rng.random((10, 12, 3))
    va = vb = np.full((10, 12, 3), 0.05)
    c = np.ones((10, 12), np.int64)
    fa, wa, fb, wb = nlmeans_cross(ya, va, c, yb, vb, c, radius=2, patch=1)
    y2 = ya.copy()
    y2[4, 5, 1] += 1e-3
    fa2, wa2, _, _ = nlmeans_cross(y2, va, c, yb, vb, c, radius=2, patch=1)
    np.testing.assert_allclose(wa2, wa)  # A's weights come from B only
    assert (fa2 - fa)[4, 5, 1] == pytest.approx(1e-3 * wa[4, 5], rel=1e-9)
    assert np.all((wa > 0) & (wa <= 1))


def test_nlm_error_estimate_is_unbiased_reduced():
    """The dual-buffer estimate of the NL-means output, summed over the image, against the true
    error: mean over 6 seeds within 10 % (measured spread of the ratio: std ~0.05, so 10 % is
    about 5 standard errors of the 6-seed mean)."""
    ref, sigma = _scene_edges()
    from mcrecon.methods.auto.estimates import dual_buffer_mse
    r = []
    for seed in range(6):
        hv = split_halves(_samples(ref, sigma, 8, seed))
        va, vb = mean_variance_policy(hv.a), mean_variance_policy(hv.b)
        fa, wa, fb, wb = nlmeans_cross(hv.a.mean, va, hv.a.count, hv.b.mean, vb, hv.b.count)
        est = dual_buffer_mse(fa, fb, sure(hv.a.mean, va, fa, wa), sure(hv.b.mean, vb, fb, wb))
        r.append(est.sum() / (((fa + fb) / 2 - ref) ** 2).sum())
    assert abs(np.mean(r) - 1) < 0.10, r


@pytest.mark.parametrize("case", ["1spp", "emitter", "zeros", "1x1", "prime"])
def test_extreme_inputs_give_finite_images(case):
    rng = np.random.default_rng(5)
    if case == "1x1":
        ss = SampleSet(rng.random((3, 2)) * 0.99, rng.random((3, 3)), width=1, height=1)
    elif case == "prime":
        w, h = 13, 7
        ref = np.full((h, w, 3), 0.5)
        ss = _samples(ref, np.full(ref.shape, 0.2), 5, 1)
    else:
        w, h = 17, 11
        spp = 1 if case == "1spp" else 8
        n = w * h * spp
        pix = np.repeat(np.arange(w * h), spp)
        pos = np.stack([pix % w + rng.random(n), pix // w + rng.random(n)], axis=1)
        val = rng.random((n, 3)) * 1e-3
        if case == "emitter":
            val[(pix == 5 * w + 8)] = 1e4  # an emitter beside 1e-3 values
        if case == "zeros":
            val[rng.random(n) < 0.97] = 0.0
        ss = SampleSet(pos, val, width=w, height=h)
    rec = _quiet(lambda: mcrecon.reconstruct(ss, method="auto", full=True))
    assert np.isfinite(rec.image).all()
    assert all(np.isfinite(a).all() for a in rec.diagnostics().values())
    if case == "emitter":
        # the emitter's energy is not smeared across the dark pixels beyond a few pixels
        assert rec.image[0, 0].max() < 1.0


@pytest.mark.parametrize("sampling", ["gem", "uniform", "greedy"])
def test_adaptive_run_is_resume_safe_and_adaptive(tmp_path, sampling):
    r = SceneRenderer("soft_shadow", width=20, height=16, seed=0)
    log = tmp_path / "run.h5"
    m = get_method("auto", sampling=sampling)
    res = _quiet(lambda: adapt(r, m, spp=12, seed=2, log=log, max_rounds=3, progress=False))
    if sampling == "greedy":
        assert res.counts.std() > 0  # not uniform after the initial pass
    elif sampling == "gem":
        # initial 4 spp, then half of each round uniform: every pixel keeps at least its initial
        # samples plus about half a uniform share of the rest, and the other half is placed
        n_uniform_part = (res.counts.sum() - 4 * res.counts.size) * 0.5 / res.counts.size
        assert res.counts.min() >= 4 + np.floor(n_uniform_part) - 2
        assert res.counts.std() > 1
    else:  # uniform doubling rounds: every pixel within one sample of the others
        assert res.counts.max() - res.counts.min() <= 1
    from mcrecon.adaptive.run import resume
    full = _quiet(lambda: adapt(r, m, spp=12, seed=2, progress=False))
    cont = _quiet(lambda: resume(log, r, progress=False))
    np.testing.assert_array_equal(cont.counts, full.counts)
    np.testing.assert_array_equal(cont.image, full.image)
    assert {"choice", "estimated_mse"} <= set(full.diagnostics())


def _nlmeans_brute(ya, va, ma, yb, vb, mb, r, f, k, alpha=1.0, eps=1e-10):
    """Cross-filtered NL-means straight from the formula (float64, loops): the reference."""
    h, w, c = ya.shape
    both = ma & mb
    out = []
    for y_own, m_own, y_w, v_w in ((ya, ma, yb, vb), (yb, mb, ya, va)):
        num = np.zeros((h, w, c))
        den = np.zeros((h, w))
        for i in range(h):
            for j in range(w):
                for dy in range(-r, r + 1):
                    for dx in range(-r, r + 1):
                        qi, qj = i + dy, j + dx
                        if not (0 <= qi < h and 0 <= qj < w and both[i, j] and both[qi, qj] and m_own[qi, qj]):
                            continue
                        s, nv = 0.0, 0
                        for si in range(max(i - f, 0), min(i + f + 1, h)):
                            for sj in range(max(j - f, 0), min(j + f + 1, w)):
                                pi, pj = si + dy, sj + dx
                                if 0 <= pi < h and 0 <= pj < w and both[si, sj] and both[pi, pj]:
                                    a, b = v_w[si, sj], v_w[pi, pj]
                                    d2 = (y_w[si, sj] - y_w[pi, pj]) ** 2 - alpha * (a + np.minimum(a, b))
                                    s += float(np.mean(d2 / (eps + k * k * (a + b))))
                                    nv += 1
                        wt = np.exp(-max(0.0, s / nv))
                        num[i, j] += wt * y_own[qi, qj]
                        den[i, j] += wt
        lone = m_own & (den <= 0)
        num[lone] = y_own[lone]
        den[lone] = 1.0
        with np.errstate(invalid="ignore", divide="ignore"):
            out += [num / den[..., None], np.where(den > 0, 1.0 / den, 0.0)]
    return out


def test_nlmeans_kernel_matches_the_formula_and_not_the_thread_count():
    """The banded, threaded kernel against loops straight from the formula: relative difference
    below 1e-5 (its distances, patch sums and exp are float32 -- the weights of cross-filtered
    NL-means may be any numbers computed from the other half, so their precision does not touch the
    exactness of its SURE, which uses the weights actually applied); bit-identical for 1 and 2 threads."""
    rng = np.random.default_rng(3)
    h, w = 13, 11
    ya, yb = rng.random((h, w, 3)), rng.random((h, w, 3))
    va, vb = rng.random((h, w, 3)) * 0.05, rng.random((h, w, 3)) * 0.05
    ca = (rng.random((h, w)) > 0.1).astype(int)
    cb = (rng.random((h, w)) > 0.1).astype(int)
    ref = _nlmeans_brute(ya, va, ca > 0, yb, vb, cb > 0, 2, 1, 0.45)
    got1 = nlmeans_cross(ya, va, ca, yb, vb, cb, radius=2, patch=1, threads=1)
    got2 = nlmeans_cross(ya, va, ca, yb, vb, cb, radius=2, patch=1, threads=2)
    for r, a, b in zip(ref, got1, got2):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(np.isfinite(r), np.isfinite(a))
        fin = np.isfinite(r)
        np.testing.assert_allclose(a[fin], r[fin], rtol=1e-5, atol=1e-12)


def test_fast_exp_of_the_nlmeans_weights_against_numpy():
    """exp(-x) of the NL-means weights: within 3e-6 relative of float64 exp where weights matter
    (x <= 30: weights >= 1e-13 next to a centre weight of 1), and 0 <= w < 2e-38 beyond x = 88."""
    import numba

    from mcrecon.methods.auto.nlmeans import _POW2_NEG, _exp_neg

    @numba.njit
    def many(xs, table):
        out = np.empty_like(xs)
        for i in range(xs.size):
            out[i] = _exp_neg(xs[i], table)
        return out

    xs = np.concatenate([np.linspace(0, 30, 300_001), np.float32([1e-8, 0.6931472, 29.999])]).astype(np.float32)
    got = many(xs, _POW2_NEG).astype(np.float64)
    want = np.exp(-xs.astype(np.float64))
    assert np.max(np.abs(got - want) / want) < 3e-6
    assert got[0] == 1.0
    assert np.isnan(many(np.float32([np.nan]), _POW2_NEG)[0])
    far = many(np.float32([88.0, 100.0, 1e6, np.finfo(np.float32).max]), _POW2_NEG)
    assert np.all((far >= 0) & (far < 2e-38))


def test_compiled_selection_helpers_are_bit_identical_to_their_numpy_definitions():
    from scipy.ndimage import maximum_filter, minimum_filter, uniform_filter

    from mcrecon.methods.auto.method import Candidate
    from mcrecon.methods.auto.passes import _FirstLeast, _arrays, _floor_and_choose, _mean_c, _means, _picked
    from mcrecon.methods.auto.selection import (_biased, _compress, _difference_rows, _guard_rows,
                                                _neighbourhood_mean, _passed_rows)
    from mcrecon.filters.masked import MaskedSmoothing, smooth_masked
    from mcrecon.core.safeguard import sample_range_bounds
    rng = np.random.default_rng(2)
    a = rng.random((37, 44)) ** 3
    b = a.copy()
    b[3, 4] = np.nan
    b[5, 5] = np.inf
    for sigma in (0.7, 2.0, 4.0):
        for x, y in zip((a, b, a * 2 + 1), MaskedSmoothing(sigma)([a, b, a * 2 + 1])):
            np.testing.assert_array_equal(smooth_masked(x, sigma), y)
    # one MaskedSmoothing for several calls (the weight sum of full maps filtered once) is smooth_masked
    sm = MaskedSmoothing(2.0)
    for x in (a, b, a * 2 + 1, a):
        np.testing.assert_array_equal(sm([x])[0], smooth_masked(x, 2.0))
    # channel means of every candidate's estimate at once: numpy's (pairwise from 8 channels)
    for c in (1, 3, 9):
        ms = [rng.random((70, 8, c)) - 0.1 for _ in range(3)]
        for mk in ms:
            mk[rng.random(mk.shape) < 0.05] = np.nan
            mk[rng.random(mk.shape) < 0.05] = np.inf
        d = rng.random((70, 8, c)) + 0.01
        v = rng.random(d.shape) * 0.1
        v[rng.random(d.shape) < 0.05] = np.nan
        for got, mk in zip(_means(ms, d), ms):
            np.testing.assert_array_equal(got, np.mean(mk / d, axis=2))
        for got, mk in zip(_means(ms, d, v, 25.0), ms):
            np.testing.assert_array_equal(got, np.mean(np.where(np.isnan(mk), np.nan, np.minimum(mk, 25.0 * v)) / d,
                                                       axis=2))
        np.testing.assert_array_equal(_mean_c(ms[0]), np.mean(ms[0], axis=2))
    m = ms[0][..., :3]
    d = np.ascontiguousarray(d[..., :3])   # contiguous, as the selection passes it (one compiled signature)
    # the floor, max(r, mean_c max(|x - y| - z sd, 0)^2 / den) (0 where the pixel is empty, NaN as
    # np.maximum), in place for every candidate, and the choice: np.argmin of the floored stack with NaN
    # as +inf (ties and all-undefined pixels to the first)
    xs = [rng.random(m.shape) for _ in range(3)]
    yy, sd = rng.random(m.shape), rng.random(m.shape) * 0.1
    yy[rng.random(m.shape) < 0.05] = np.nan
    rel = rng.integers(0, 3, (3,) + m.shape[:2]).astype(float) * 0.01
    rel[rng.random(rel.shape) < 0.05] = np.nan
    rel[:, :2] = np.nan
    has = rng.random(m.shape[:2]) < 0.9
    ref = np.stack([np.maximum(r, np.mean(lb * lb / d, axis=2)) for r, lb in
                    zip(rel, [np.where(has[..., None], np.maximum(np.abs(x - yy) - 2.0 * sd, 0.0), 0.0) for x in xs])])
    choice = _floor_and_choose(rel, xs, yy, sd, d, has, 2.0)
    np.testing.assert_array_equal(rel, ref)
    np.testing.assert_array_equal(choice, np.argmin(np.where(np.isnan(ref), np.inf, ref), axis=0))
    assert len(set(choice.ravel())) == 3
    # the picks by the choice and the region guard's difference of relative estimates
    mses = [m, m * 2, -m]
    cands = [Candidate(f"c{k}", x, mk) for k, (x, mk) in enumerate(zip(xs, mses))]
    img, raw_abs, est = _picked(cands, rel, choice)
    np.testing.assert_array_equal(img, np.take_along_axis(np.stack(xs), choice[None, ..., None], axis=0)[0])
    np.testing.assert_array_equal(raw_abs, np.take_along_axis(np.stack([np.mean(mk, axis=2) for mk in mses]),
                                                              choice[None], axis=0)[0])
    np.testing.assert_array_equal(est, np.take_along_axis(rel, choice[None], axis=0)[0])
    raw = np.stack([np.mean(mk / d, axis=2) for mk in mses])
    fin = np.where(np.isfinite(raw), raw, np.nan)
    diff = np.empty(choice.shape)
    _guard_rows(_arrays(mses), d, choice, diff, 0, diff.shape[0])
    np.testing.assert_array_equal(diff, np.take_along_axis(fin, choice[None], axis=0)[0] - fin[0])
    r = rel[0]
    # the running choice: np.argmin of the stack with NaN as +inf (ties and all-undefined pixels to the first)
    maps = [rng.integers(0, 3, r.shape).astype(float) for _ in range(4)]
    maps[1][rng.random(r.shape) < 0.2] = np.nan
    maps[2][rng.random(r.shape) < 0.2] = np.inf
    maps[0][:5] = maps[1][:5] = maps[2][:5] = maps[3][:5] = np.nan
    least = _FirstLeast(r.shape)
    for k, mk in enumerate(maps):
        least.offer(k, mk)
    np.testing.assert_array_equal(least.index, np.argmin(np.stack([np.where(np.isnan(mk), np.inf, mk)
                                                                    for mk in maps]), axis=0))
    # the global prior's sums of the voters, its difference maps and local test
    vote = rng.random(r.shape) < 0.8
    buf = np.empty(r.size)
    rr = rng.standard_normal(r.shape) * 10.0 ** rng.uniform(-5, 5, r.shape)
    assert float(np.sum(buf[:_compress(rr.ravel(), vote.ravel(), buf)])) == float(np.sum(rr[vote]))
    lk, lg = maps[1] - 1.5, maps[2] - 1.0
    lg[3, 4] = -np.inf
    d, d2, fin = np.empty(r.shape), np.empty(r.shape), np.empty(r.shape, bool)
    _difference_rows(lk, lg, d, d2, fin, 0, r.shape[0])
    dref = np.where(np.isnan(lk) | np.isnan(lg) | np.isinf(lg), np.nan, lk - lg)
    np.testing.assert_array_equal(d, dref)
    np.testing.assert_array_equal(d2, dref * dref)
    np.testing.assert_array_equal(fin, np.isfinite(dref))
    mm, qq, neff = rng.standard_normal(r.shape), rng.random(r.shape), rng.random(r.shape) * 50
    mm[rng.random(r.shape) < 0.05] = np.inf
    neff[rng.random(r.shape) < 0.05] = 0.0
    passed = np.empty(r.shape)
    _passed_rows(mm, qq, neff, 0.5, r, passed, 0, r.shape[0])
    with np.errstate(invalid="ignore", divide="ignore"):
        ok = np.isfinite(mm) & (mm < -0.5 * np.sqrt(np.maximum(qq - mm * mm, 0.0) / neff))
    np.testing.assert_array_equal(passed, np.where(ok, r, np.inf))
    assert ok.any() and not ok.all()
    # scipy's 3 x 3 uniform filter of the finite variances, term for term
    for shape in ((1, 1, 1), (1, 6, 3), (7, 1, 2), (70, 9, 3)):
        vv = rng.exponential(1.0, shape) ** 3
        vv[rng.random(shape) < 0.2] = 0.0
        vv[rng.random(shape) < 0.05] = np.nan
        got = np.empty(shape)
        _neighbourhood_mean(vv, got)
        v_nb = uniform_filter(np.where(np.isfinite(vv), vv, 0.0), size=(3, 3, 1), mode="nearest")
        np.testing.assert_array_equal(got, v_nb)
        # and the global prior's bias test on it, row by row
        xg, yg = rng.random(shape), rng.random(shape)
        has = rng.random(shape[:2]) < 0.9
        biased = np.empty(shape[:2], bool)
        _biased(xg, yg, vv, 5.0, has, biased)
        with np.errstate(invalid="ignore"):
            ref = np.any(np.abs(xg - yg) > 5.0 * np.sqrt(np.maximum(vv, v_nb)), axis=2) & has
        np.testing.assert_array_equal(biased, ref)
    ss, _, _ = _caustic_ring_samples(1)
    st = PixelStats.from_source(ss)
    st.count[3:6, 4:9] = 0
    st.min[3:6, 4:9], st.max[3:6, 4:9] = np.inf, -np.inf
    # the compiled neighbourhood range equals scipy's min/max filters on masked sources
    for radius in (1, 2):
        size = (2 * radius + 1, 2 * radius + 1, 1)
        has = (st.count > 0)[..., None]
        ref_lo = minimum_filter(np.where(has, st.min, np.inf), size=size, mode="nearest")
        ref_hi = maximum_filter(np.where(has, st.max, -np.inf), size=size, mode="nearest")
        ref = (np.where(np.isfinite(ref_lo), ref_lo, -np.inf), np.where(np.isfinite(ref_hi), ref_hi, np.inf))
        for x, y in zip(sample_range_bounds(st, radius), ref):
            np.testing.assert_array_equal(x, y)


def _best_single_candidate(ss, ref):
    """relMSE of auto's best candidate used at every pixel, through auto's safeguard (the clamp and the
    heavy-tail rule): what auto would output had it chosen that one candidate everywhere."""
    from mcrecon.core.halves import merge_halves
    from mcrecon.core.safeguard import confidence_clamp, pooled_mean_variance, sample_range_bounds
    from mcrecon.methods.auto.selection import _no_push_in_heavy_tails

    auto = get_method("auto")
    h = split_halves(ss)
    st = merge_halves(h.a, h.b)
    cands, y, v, count = auto._candidates(st, h, "drop")  # h.source is ss
    lo, hi = sample_range_bounds(st)
    vs = pooled_mean_variance(v, count)
    return min(relative_mse(_no_push_in_heavy_tails(confidence_clamp(c.image, y, vs, 4.0, lo, hi), y, hi), ref)
               for c in cands)


def test_pooled_mean_variance_is_the_pixel_variance_floored_by_the_neighbourhood_median():
    """Brute force: max(v_p, median over the 3 x 3 (5 x 5) pixels with samples, cut at the border,
    of n_q v_q, / n_p); empty pixels keep v."""
    from mcrecon.core.safeguard import pooled_mean_variance

    rng = np.random.default_rng(4)
    # exact, on sparse counts and on full 3 x 3 neighbourhoods (the median network) with ties and zeros,
    # over two row blocks
    for h, w, low in ((9, 11, 0), (70, 13, 1)):
        count = rng.integers(low, 6, size=(h, w))
        v = rng.random((h, w, 2)) ** 3 / np.maximum(count, 1)[..., None]
        v[rng.random(v.shape) < 0.2] = 0.5
        v[rng.random(v.shape) < 0.3] = 0.0
        v[count == 0] = 0.0
        for radius in (1, 2):
            ref = v.copy()
            for i in range(h):
                for j in range(w):
                    if count[i, j] == 0:
                        continue
                    for c in range(2):
                        nb = [count[a, b] * v[a, b, c] for a in range(max(i - radius, 0), min(i + radius + 1, h))
                              for b in range(max(j - radius, 0), min(j + radius + 1, w)) if count[a, b] > 0]
                        ref[i, j, c] = max(v[i, j, c], float(np.median(nb)) / count[i, j])
            np.testing.assert_array_equal(pooled_mean_variance(v, count, radius), ref)
    with pytest.raises(ValueError, match="var_mean"):
        pooled_mean_variance(v[..., 0], count)


def test_pooled_variance_keeps_the_true_value_inside_the_clamp_where_samples_missed_a_rare_component():
    """The why of the floor: samples 1 + 20 B, B ~ Bernoulli(1/20) (true mean 2), 32 per pixel.  The
    (19/20)^32 = 19 % of pixels that drew no 21 have v = 0 and mean 1: the interval mean +- 4 sd on
    their own variance misses the true 2 at all of them; with the neighbourhood's median the interval
    holds it at all but the few pixels most of whose neighbours also missed (measured 99.9 %)."""
    from mcrecon.core.safeguard import pooled_mean_variance

    rng = np.random.default_rng(0)
    h = w = 64
    n = 32
    s = 1.0 + 20.0 * (rng.random((h, w, n)) < 0.05)
    y = s.mean(axis=2)[..., None]
    v = (s.var(axis=2, ddof=1) / n)[..., None]
    count = np.full((h, w), n)
    own = np.abs(y - 2.0) <= 4.0 * np.sqrt(v)
    pooled = np.abs(y - 2.0) <= 4.0 * np.sqrt(pooled_mean_variance(v, count))
    assert own.mean() < 0.85  # the 19 % without a hit, and no more
    assert pooled.mean() > 0.99


def test_safeguard_variance_pools_in_albedo_units_where_the_texture_would_narrow_the_interval():
    """The same rare component under stripes of albedo 0.9 one row in three, 0.1 elsewhere: a light
    pixel's 3 x 3 neighbourhood is two thirds dark, so the median in colour units is a dark pixel's
    variance (81x smaller) and the light pixels' intervals miss the truth wherever their own samples
    missed (the 19 %); in units of the albedo every pixel shares one distribution (measured over seeds 0-5:
    0.80-0.83 of the light pixels' intervals hold the truth in colour units, 0.987-0.993 in albedo units)."""
    from mcrecon.core.safeguard import safeguard_variance

    rng = np.random.default_rng(1)
    h = w = 60
    n = 32
    alb = np.where((np.arange(h) % 3 == 2)[:, None], 0.9, 0.1) * np.ones((h, w))
    s = alb[..., None] * (1.0 + 20.0 * (rng.random((h, w, n)) < 0.05))
    y = s.mean(axis=2)[..., None]
    v = (s.var(axis=2, ddof=1) / n)[..., None]
    count = np.full((h, w), n)
    truth = 2.0 * alb[..., None]
    light = alb == 0.9
    colour = (np.abs(y - truth) <= 4.0 * np.sqrt(safeguard_variance(v, count)))[light]
    albedo = (np.abs(y - truth) <= 4.0 * np.sqrt(safeguard_variance(v, count, alb[..., None])))[light]
    assert colour.mean() < 0.86  # 1 - 0.19 expected, s.e. 0.011 over the 1200 light pixels
    assert albedo.mean() > 0.975  # as the dark pixels' 0.98-0.99 (seeds 0-5)


def test_albedo_divisor_fills_empty_pixels_floors_dark_albedo_and_is_none_without_one():
    from mcrecon.core.safeguard import albedo_divisor

    pos = np.array([[0.5, 0.5], [1.5, 0.5], [1.5, 0.5]])  # pixel (0, 0), twice (0, 1); (1, *) empty
    val = np.ones((3, 3))
    alb = np.array([[0.5, 0.5, 0.5], [0.01, 0.2, 0.3], [0.01, 0.4, 0.5]])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", McreconWarning)
        st = PixelStats.from_samples(pos, val, width=2, height=2, features={"albedo": alb})
        d = albedo_divisor(st)
    np.testing.assert_allclose(d[0, 0], 0.5)
    np.testing.assert_allclose(d[0, 1], [0.02, 0.3, 0.4])  # the mean 0.01 floored at 0.02
    np.testing.assert_allclose(d[1], d[0])  # the empty row takes its nearest sampled neighbour
    assert albedo_divisor(PixelStats.from_samples(pos, val, width=2, height=2)) is None


def test_effective_counts_match_the_variance_of_the_masked_smoothing_by_brute_force():
    """n_p = (sum_j w_j m_j)^2 / sum_j w_j^2 m_j is s^2 over the variance of smooth_masked's output at p
    for independent unit-variance pixels (brute force over the explicit weights), ~4 pi sigma^2 inside,
    a little over half of that on an edge and a quarter in a corner."""
    from mcrecon.filters.masked import _gauss_kernel, effective_counts

    rng = np.random.default_rng(5)
    h, w, sigma = 23, 29, 2.0
    mask = rng.random((h, w)) > 0.2
    mask[:, :3] = True
    (n_masked,), (n_full,) = effective_counts([mask], sigma), effective_counts([np.ones((h, w), bool)], sigma)
    k = _gauss_kernel(sigma)
    r = (k.size - 1) // 2
    for (i, j) in [(11, 14), (0, 14), (0, 0), (5, 1), (17, 22)]:
        wts = np.zeros((h, w))
        for di in range(-r, r + 1):
            for dj in range(-r, r + 1):
                if 0 <= i + di < h and 0 <= j + dj < w:
                    wts[i + di, j + dj] = k[di + r] * k[dj + r]
        wm = wts * mask
        var = np.sum(wm ** 2) / np.sum(wm) ** 2  # of sum w m x / sum w m, Var x = 1
        assert n_masked[i, j] == pytest.approx(1.0 / var, rel=1e-9)
    assert n_full[11, 14] == pytest.approx(4 * np.pi * sigma ** 2, rel=0.02)
    # the edge's row of pixels counts fully: a little over a half (0.56 at sigma 2), and its square
    assert 0.5 < n_full[0, 14] / n_full[11, 14] < 0.6
    assert 0.25 < n_full[0, 0] / n_full[11, 14] < 0.36
    # and the empirical variance of the smoothing of white noise agrees (400 draws: 7 % spread)
    from mcrecon.filters.masked import MaskedSmoothing

    draws = rng.standard_normal((400, h, w))
    sm = np.array(MaskedSmoothing(sigma)([np.where(mask, d, np.nan) for d in draws]))
    for (i, j) in [(11, 14), (0, 0)]:
        assert np.var(sm[:, i, j]) * n_masked[i, j] == pytest.approx(1.0, abs=0.2)


@pytest.mark.parametrize("noise,size", [("gaussian", 64), ("exponential", 128)])
def test_auto_is_within_1_2x_of_its_best_single_candidate_on_flat_fields(noise, size):
    """The plain per-pixel choice was 20-70x worse than its own widest Gaussian on flat noise (every
    pixel's SURE noise swamps the small differences between wide scales, and the bias floor at 2 sd
    hands one pure-noise pixel in 20 to a narrow filter).  The global prior (default z = 3) makes the
    best single candidate every pixel's default.  Measured (8 spp, seeds 0-3, mean default / mean best
    single): Gaussian noise on 64 x 64 1.04; exponential on 128 x 128 1.15, the plain choice ~5x the
    default.  Bounds: 1.2x (the issue's target) and a factor 3.  Exponential noise on 64 x 64 gives
    1.27 (one seed of four 2.2x: a 12-pixel region where NL-means' dual-buffer estimate, skewed with
    4 samples per half, passed the z test), 1.10 at 32 spp; at 16 spp on 40 x 48 the Gaussian case
    gave 1.0-4.6 per seed: on so few pixels the summed estimates cannot tell scale 8 from 16, whose
    errors are both < 2e-4 of the mean's (docs/methods/auto.md, Limits)."""
    assert get_method("auto").params["global_prior"] == 3.0
    h = w = size
    spp = 8
    ref = np.full((h, w, 3), 0.5)
    r_def, r_off, r_best = [], [], []
    for seed in range(4):
        if noise == "gaussian":
            ss = _samples(ref, np.full(ref.shape, 0.5), spp, seed)
        else:
            rng = np.random.default_rng(seed)
            pix = np.repeat(np.arange(h * w), spp)
            pos = np.stack([pix % w, pix // w], 1) + rng.uniform(size=(pix.size, 2))
            ss = SampleSet(pos, 0.5 * rng.exponential(size=(pix.size, 3)), width=w, height=h)
        r_def.append(relative_mse(_quiet(lambda: mcrecon.reconstruct(ss, method="auto")), ref))
        r_off.append(relative_mse(_quiet(lambda: mcrecon.reconstruct(ss, method=get_method("auto", global_prior=None))),
                                  ref))
        r_best.append(_quiet(lambda: _best_single_candidate(ss, ref)))
    assert np.mean(r_def) <= 1.2 * np.mean(r_best), (r_def, r_best)
    assert np.mean(r_def) < np.mean(r_off) / 3, (r_def, r_off)


def _prior_inputs(h=12, w=14, n_cands=3):
    from mcrecon.methods.auto.features import Candidate

    rng = np.random.default_rng(0)
    y = rng.uniform(0.4, 0.6, size=(h, w, 3))
    v = np.full((h, w, 3), 0.01)
    count = np.full((h, w), 16)
    cands = [Candidate("box", y.copy(), v.copy())]
    for k in range(1, n_cands):
        cands.append(Candidate(f"gauss{k}", np.full((h, w, 3), 0.5), np.full((h, w, 3), 0.01 / (4.0 * k))))
    raw = [c.mse.mean(axis=2) / 0.26 for c in cands]
    return cands, raw, np.stack(raw), y, v, count, (y.copy(), y.copy())


def test_global_prior_takes_the_best_single_candidate_and_leaves_heavy_tailed_or_biased_pixels_alone():
    from mcrecon.methods.auto.features import Candidate
    from mcrecon.methods.auto.selection import _global_prior

    cands, raw, relm, y, v, count, bounds = _prior_inputs()
    plain = np.zeros(y.shape[:2], np.int64)  # a per-pixel choice that kept the mean everywhere
    got, _ = _global_prior(cands, raw.__getitem__, relm, plain, y, v, count, bounds, 2.0, 3.0, 4.0)
    assert (got == 2).all()  # the candidate of least summed estimate, everywhere
    # a pixel with rare huge samples around (3x3 maximum > 30x its mean) keeps its per-pixel choice
    # where the global candidate lies farther from its 8 neighbours' median than that choice (a firefly
    # the global candidate kept), and takes the global candidate where it lies nearer
    hi = bounds[1].copy()
    hi[3, 4] = hi[8, 9] = 100.0
    img = cands[2].image.copy()
    img[3, 4] = 3.0
    kept = cands[:2] + [Candidate(cands[2].name, img, cands[2].mse)]
    got, held = _global_prior(kept, raw.__getitem__, relm, plain, y, v, count, (bounds[0], hi), 2.0, 3.0, 4.0)
    assert got[3, 4] == 0 and got[8, 9] == 2
    assert not held[3, 4] and held[8, 9] and held.sum() == got.size - 1  # the pixels holding the default
    assert (np.delete(got.ravel(), 3 * 14 + 4) == 2).all()
    # so does a pixel where the global candidate departs from the mean by more than 5 standard errors
    img = cands[2].image.copy()
    img[5, 6, 1] = y[5, 6, 1] + 6 * 0.1
    c2 = cands[:2] + [Candidate(cands[2].name, img, cands[2].mse)]
    got, _ = _global_prior(c2, raw.__getitem__, relm, plain, y, v, count, bounds, 2.0, 3.0, 4.0)
    assert got[5, 6] == 0 and got[5, 7] == 2
    # where the per-pixel choice happens to be the default's candidate but the test kept that choice,
    # the pixel does not count as holding the default (the region guard still reviews it)
    plain_g = plain.copy()
    plain_g[5, 6] = 2
    got, held = _global_prior(c2, raw.__getitem__, relm, plain_g, y, v, count, bounds, 2.0, 3.0, 4.0)
    assert got[5, 6] == 2 and not held[5, 6] and held[5, 7]


def test_nearer_the_neighbours_compares_distances_to_the_8_neighbour_median_by_brute_force():
    from mcrecon.methods.auto.features import Candidate
    from mcrecon.methods.auto.selection import _nearer_the_neighbours

    rng = np.random.default_rng(8)
    h, w, c = 7, 9, 3
    y = rng.random((h, w, c))
    cands = [Candidate(f"c{k}", rng.random((h, w, c)) * 2, np.zeros((h, w, c))) for k in range(3)]
    choice = rng.integers(0, 3, size=(h, w))
    where = rng.random((h, w)) < 0.6
    where[0, 0] = where[h - 1, 4] = True
    scale = rng.choice([0.05, 0.4, 0.9], size=(h, w, c))   # an albedo: everything divided by it
    for sc in (None, scale):
        got = _nearer_the_neighbours(cands, 1, choice, y, where, sc)
        div = np.ones_like(y) if sc is None else sc
        pad = np.pad(y / div, ((1, 1), (1, 1), (0, 0)), mode="edge")
        for i in range(h):
            for j in range(w):
                if not where[i, j]:
                    assert not got[i, j]
                    continue
                nb = [pad[i + 1 + di, j + 1 + dj] for di in (-1, 0, 1) for dj in (-1, 0, 1) if di or dj]
                med = np.median(np.stack(nb), axis=0)
                dg = np.abs(cands[1].image[i, j] / div[i, j] - med).sum()
                dc = np.abs(cands[choice[i, j]].image[i, j] / div[i, j] - med).sum()
                assert got[i, j] == (dg <= dc), (i, j)
    y[2, 3, 1] = np.nan  # a NaN among a pixel's neighbours: never nearer
    far = [cands[0], Candidate("g", cands[0].image.copy(), cands[0].mse)]  # equal values: nearer where no NaN
    got = _nearer_the_neighbours(far, 1, np.zeros((h, w), np.int64), y, np.ones((h, w), bool))
    near_nan = np.zeros((h, w), bool)
    near_nan[1:4, 2:5] = True
    near_nan[2, 3] = False  # the NaN pixel's own neighbours are finite
    assert not got[near_nan].any() and got[~near_nan].all()


def test_global_prior_changes_nothing_when_the_pixel_mean_is_the_best_single_candidate():
    from mcrecon.methods.auto.selection import _global_prior

    cands, raw, relm, y, v, count, bounds = _prior_inputs()
    for c in cands[1:]:
        c.mse[...] = 1.0  # every filter far worse than the mean's v = 0.01
    raw = [c.mse.mean(axis=2) / 0.26 for c in cands]
    plain = np.random.default_rng(1).integers(0, 3, size=y.shape[:2])
    got, _ = _global_prior(cands, raw.__getitem__, np.stack(raw), plain, y, v, count, bounds, 2.0, 3.0, 4.0)
    np.testing.assert_array_equal(got, plain)


def test_gem_sampling_places_the_non_uniform_share_where_gem_does():
    """uniform_share=0 is GEM's own placement: the same counts as GEM's plan on the same statistics, with GEM's
    rare-light gate at auto's (:data:`~mcrecon.core.safeguard.RARE_THRESHOLD`; GEM's own default gate for
    independent samples is lower)."""
    from mcrecon.core.safeguard import RARE_THRESHOLD
    from mcrecon.methods.base import AdaptiveState
    from mcrecon.renderers import scenes
    from mcrecon.core.stats import PixelStats

    w, h = 24, 20
    b = scenes.render_uniform(scenes.get_scene("soft_shadow"), width=w, height=h, spp=4, seed=3)
    stats = PixelStats.from_samples(b.positions, b.values, width=w, height=h)

    def plan(method):
        state = AdaptiveState(stats=stats, round_index=1, budget=w * h * 16, n_samples=int(stats.count.sum()),
                              rng=np.random.default_rng(7))
        return method.plan(method.start(w, h), state)

    req_auto = plan(get_method("auto", uniform_share=0.0, iterations=8))
    req_gem = plan(get_method("gem", uniform_share=0.0, rare_threshold=RARE_THRESHOLD))
    assert req_auto.positions is None and req_gem.positions is None
    np.testing.assert_array_equal(req_auto.counts, req_gem.counts)
    # with a uniform share, that share is spread evenly over the pixels on top of GEM's counts
    req = plan(get_method("auto", uniform_share=0.5, iterations=8))
    n_round = int(req_gem.counts.sum())
    assert req.positions is None and req.counts.sum() == n_round
    assert (req.counts > 0).mean() > (req_gem.counts > 0).mean()


def test_gem_sampling_pipelined_is_reproducible_and_spends_the_budget():
    r = SceneRenderer("soft_shadow", width=20, height=16, seed=0)
    runs = [_quiet(lambda: adapt(r, get_method("auto"), spp=12, seed=4, progress=False, pipeline=True))
            for _ in range(2)]
    np.testing.assert_array_equal(runs[0].image, runs[1].image)
    np.testing.assert_array_equal(runs[0].counts, runs[1].counts)
    assert runs[0].counts.sum() == 12 * 20 * 16 and runs[0].counts.std() > 1


def test_heavy_tailed_pixels_are_not_pushed_away_from_their_neighbours():
    """Safeguard's last rule: where the 3x3 sample maximum exceeds 10x a pixel's mean, a candidate value
    further from the neighbours' median than the pixel's own mean is replaced by that mean."""
    from mcrecon.methods.auto.selection import HEAVY_TAIL, _no_push_in_heavy_tails

    y = np.full((5, 5, 1), 0.4)
    y[2, 2, 0] = 18.0                      # a dark pixel that caught one emitter sample
    hi = np.full((5, 5, 1), 0.5)
    hi[1:4, 1:4, 0] = 500.0                # that sample is in every 3x3 window around it
    y[1, 2, 0] = 0.5                       # a neighbour a little above its neighbours' median (0.4)
    y[3, 3, 0] = 0.3                       # and one a little below it
    y[3, 1, 0] = 0.3
    img = y.copy()
    img[2, 2, 0] = 19.0                    # a candidate pushed it further up (bright neighbours elsewhere)
    img[1, 2, 0] = 2.0                     # pushed further above its median: reverted
    img[3, 3, 0] = 0.35                    # pulled up towards its median: kept
    img[3, 1, 0] = 0.2                     # pushed further below its median: reverted
    img[0, 0, 0] = 0.9                     # not heavy-tailed (hi 0.5 < 10 x 0.4): untouched
    out = _no_push_in_heavy_tails(img, y, hi)
    assert out[2, 2, 0] == 18.0 and out[1, 2, 0] == 0.5 and out[3, 1, 0] == 0.3
    assert out[3, 3, 0] == 0.35 and out[0, 0, 0] == 0.9
    assert HEAVY_TAIL == 10.0
    # a pixel pulled down towards darker neighbours keeps the candidate's value
    img2 = y.copy()
    img2[2, 2, 0] = 5.0
    assert _no_push_in_heavy_tails(img2, y, hi)[2, 2, 0] == 5.0


def _no_push_reference(img, y, hi, scale=None):
    """The rule as numpy states it (np.median of the 8 edge-repeated neighbours of y / scale, the pixel's side
    of it in the same units): the compiled pass must equal it."""
    from mcrecon.methods.auto.selection import HEAVY_TAIL

    ref = y if scale is None else y / scale
    cand = (hi > HEAVY_TAIL * np.abs(y)) & (img != y)
    ii, jj, cc = np.nonzero(cand)
    pad = np.pad(ref, ((1, 1), (1, 1), (0, 0)), mode="edge")
    neigh = np.stack([pad[ii + 1 + di, jj + 1 + dj, cc] for di in (-1, 0, 1) for dj in (-1, 0, 1)
                      if (di, dj) != (0, 0)], axis=1)
    with np.errstate(invalid="ignore"):
        med = np.median(neigh, axis=1)
    yc, oc, rc = y[ii, jj, cc], img[ii, jj, cc], ref[ii, jj, cc]
    away = ((rc > med) & (oc > yc)) | ((rc < med) & (oc < yc))
    out = img.copy()
    out[ii[away], jj[away], cc[away]] = yc[away]
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_heavy_tail_rule_compiled_equals_its_numpy_statement(seed):
    """Bit for bit on heavy-tailed random films (ties, zeros, NaN means, 1-pixel-wide films included)."""
    from mcrecon.methods.auto.selection import _no_push_in_heavy_tails

    rng = np.random.default_rng(seed)
    for h, w in ((1, 1), (1, 7), (6, 1), (23, 31)):
        y = rng.exponential(1.0, (h, w, 3)) ** 3
        y[rng.random((h, w, 3)) < 0.1] = 0.0
        y[rng.random((h, w, 3)) < 0.05] = 1.0           # ties among the neighbours
        if seed == 2:
            y[rng.random((h, w, 3)) < 0.05] = np.nan    # an empty pixel's undefined mean
        hi = y * rng.choice([1.0, 20.0, 400.0], (h, w, 3))
        img = y * rng.uniform(0.5, 1.5, (h, w, 3))
        same = rng.random((h, w, 3)) < 0.2
        img[same] = y[same]                              # candidates that kept the mean
        got = _no_push_in_heavy_tails(img, y, hi)
        ref = _no_push_reference(img, y, hi)
        np.testing.assert_array_equal(got, ref)
        inplace = img.copy()
        _no_push_in_heavy_tails(inplace, y, hi, out=inplace)
        np.testing.assert_array_equal(inplace, ref)
        assert (got != img).sum() > 0 or h * w < 8   # the rule fired: the comparison is not vacuous
        scale = rng.choice([0.02, 0.3, 0.9], (h, w, 3))   # an albedo
        np.testing.assert_array_equal(_no_push_in_heavy_tails(img, y, hi, scale=scale),
                                      _no_push_reference(img, y, hi, scale))


def test_heavy_tail_rule_takes_the_texture_out_of_its_reference():
    """A dark square (albedo 0.1) among light ones (0.8) under the same light: its rare-sample neighbourhood
    makes it heavy-tailed, and the colour's median is a light square's colour, so the rule reverted a
    candidate that moved it down to its truth; divided by the albedo the neighbours say the light is the
    same, and the move stands.  A move away from the light the neighbours agree on is still reverted."""
    from mcrecon.methods.auto.selection import _no_push_in_heavy_tails

    alb = np.full((3, 3, 1), 0.8)
    alb[1, 1] = 0.1
    y = alb * 1.0
    y[1, 1] = 0.14                      # the dark square's mean, noisy above its truth 0.1
    hi = np.full_like(y, 5.0)           # a rare bright sample nearby
    img = y.copy()
    img[1, 1] = 0.1
    assert _no_push_in_heavy_tails(img, y, hi)[1, 1, 0] == 0.14
    assert _no_push_in_heavy_tails(img, y, hi, scale=alb)[1, 1, 0] == 0.1
    img[1, 1] = 0.2
    assert _no_push_in_heavy_tails(img, y, hi, scale=alb)[1, 1, 0] == 0.14


def test_gem_sampling_pipelined_never_places_samples_from_empty_statistics():
    """Under lag, round 1 is planned while round 0 renders: it must be uniform (the driver's initial pass
    in two rounds), not GEM's placement on empty statistics (ties broken towards the top rows)."""
    from mcrecon.adaptive.schedule import Schedule, _initial_rounds
    from mcrecon.core.stats import PixelStats

    w = h = 32
    m = get_method("auto")
    run = m.start(w, h)
    empty = PixelStats(w, h)
    k = _initial_rounds(m, True, 32 * w * h, w * h)
    schedule = Schedule(budget=32 * w * h, seed=1, initial_rounds=k)
    r0, _ = schedule.plan(m, run, empty, 0, 0)
    assert r0.positions is None and r0.counts.sum() == 2 * w * h
    r1, _ = schedule.plan(m, run, empty, 1, 2 * w * h, pending=np.full((h, w), 2))
    assert r1.positions is None and r1.counts.sum() == 2 * w * h and r1.counts.max() - r1.counts.min() <= 1


def test_pixels_apart_from_the_global_prior_match_their_numpy_statement():
    """_apart computes the 3x3 median only where the heavy-tail test's first half fires: the same answer as
    the whole-image scipy median filter (edges repeated), with the brightness test and (need_v) the pixels
    without variance, on a field with rare bright pixels, NaN, zeros and ties."""
    from scipy.ndimage import median_filter
    from mcrecon.methods.auto.selection import HEAVY_PRIOR, _apart

    rng = np.random.default_rng(5)
    for h, w in ((17, 23), (70, 9), (1, 5)):
        y = rng.uniform(0.0, 1.0, size=(h, w, 3))
        y[rng.random(y.shape) < 0.05] = 0.001
        y[rng.random(y.shape) < 0.05] = 0.5
        y[rng.random(y.shape) < 0.02] = np.nan
        v = rng.uniform(0.0, 0.01, size=y.shape)
        v[rng.random(y.shape[:2]) < 0.1] = 0.0
        den = rng.uniform(0.0005, 0.01, size=y.shape)
        hi = np.where(rng.random(y.shape) < 0.1, 50.0, 1.0)
        ay = np.abs(np.where(np.isfinite(y), y, 0.0))
        heavy = hi > HEAVY_PRIOR * np.maximum(ay, median_filter(ay, size=(3, 3, 1), mode="nearest"))
        with np.errstate(invalid="ignore"):
            bright = np.maximum(y * y - v, 0.0) > HEAVY_PRIOR ** 2 * den
        ref = np.any(heavy | bright, axis=2)
        np.testing.assert_array_equal(_apart(y, v, hi, den, False), ref)
        np.testing.assert_array_equal(_apart(y, v, hi, den, True), ref | ~np.any(v > 0, axis=2))
        assert h * w < 10 or (0 < ref.sum() < ref.size and bright.any() and heavy.any())


def test_a_pixel_far_brighter_than_its_neighbours_does_not_choose_the_global_candidate():
    """Candidate 2 is better at every pixel but one, a pixel 200x brighter than its neighbours (an
    emitter's edge) where its relative estimate is huge: that pixel does not vote, so candidate 2 is the
    default everywhere else; with the pixel voting, the sum would pick candidate 1."""
    from mcrecon.methods.auto.selection import _global_prior

    cands, raw, relm, y, v, count, bounds = _prior_inputs()
    cands[2].mse[0, 0] = 1e4
    raw = [c.mse.mean(axis=2) / 0.26 for c in cands]
    assert np.sum(raw[2]) > np.sum(raw[1])
    y = y.copy()
    y[0, 0] = 100.0
    plain = np.zeros(y.shape[:2], np.int64)
    got, _ = _global_prior(cands, raw.__getitem__, np.stack(raw), plain, y, v, count, (y.copy(), y.copy()), 2.0, 3.0, None)
    assert got[0, 0] == 0 and (got.ravel()[1:] == 2).all()


# ------------------------------------------------------------------ features
def _textured(seed, size=48, spp=16, features=True, scene="checker_wall"):
    from mcrecon.renderers import scenes

    sc = scenes.get_scene(scene)
    b = scenes.render_uniform(sc, width=size, height=size, spp=spp, seed=seed, features=features)
    ss = SampleSet(b.positions, b.values, width=size, height=size, features=b.features or None)
    return ss, scenes.reference_image(sc, size, size)


def test_without_features_auto_is_the_colour_only_auto_bit_for_bit():
    """No features in the samples, or feature_candidates='none', or features auto has no use for:
    the same image as before features existed (the colour-only path)."""
    ss_f, _ = _textured(0)
    ss = SampleSet(ss_f.positions, ss_f.values, width=ss_f.width, height=ss_f.height)
    base = _quiet(lambda: mcrecon.reconstruct(ss, method=get_method("auto")))
    np.testing.assert_array_equal(_quiet(lambda: mcrecon.reconstruct(ss, method=get_method("auto", feature_candidates="none"))), base)
    np.testing.assert_array_equal(_quiet(lambda: mcrecon.reconstruct(ss_f, method=get_method("auto", feature_candidates="none"))), base)
    assert get_method("auto", feature_candidates="none").requires.features == "none"
    assert get_method("auto").requires.features == "optional"
    with pytest.raises(InputError, match="feature_candidates.*valid: none or nfor, nfor_own, dnlm, mix, xbil, fbil"):
        get_method("auto", feature_candidates="oidn")


def test_feature_guided_auto_beats_colour_only_auto_on_a_textured_scene():
    """On the built-in checker_spot (a textured wall lit by a light one sample in 20 finds; 64^2, 16 spp,
    seeds 0-2) the feature-guided candidates lower auto's error: the mean relative MSE is 0.441 of the
    colour-only auto's (measured).  Bound: 0.51, the measured ratio + 15 %."""
    r_f, r_c = [], []
    for seed in range(3):
        ss, ref = _textured(seed, scene="checker_spot", size=64)
        r_f.append(relative_mse(_quiet(lambda: mcrecon.reconstruct(ss, method="auto")), ref))
        r_c.append(relative_mse(_quiet(lambda: mcrecon.reconstruct(ss, method=get_method("auto", feature_candidates="none"))), ref))
    assert np.mean(r_f) < 0.51 * np.mean(r_c), (r_f, r_c)  # measured 0.441; 15 % margin


def test_heavy_tail_rule_leaves_feature_guided_values_where_the_light_is_rarely_found():
    """checker_spot at 128^2, 32 spp, seed 0: with the heavy-tail rule applied to every pixel auto measured
    0.072 of the pixel mean's relMSE (seeds 0-3: 0.067-0.075), restoring the dark means of pixels whose
    samples missed the light; with feature-guided pixels left to their clamped value 0.057 (0.053-0.061).
    Bound 0.064, OIDN given albedo and normal there (docs/which-method.md)."""
    ss, ref = _textured(0, scene="checker_spot", size=128, spp=32)
    e = relative_mse(_quiet(lambda: mcrecon.reconstruct(ss, method="auto")), ref)
    e_box = relative_mse(mcrecon.reconstruct(ss, method="box"), ref)
    assert e < 0.064 * e_box, e / e_box


def test_a_pixel_without_samples_keeps_a_filled_value_under_the_safeguard():
    """An empty pixel has no interval (mean 0, variance 0); with and without features auto gives it the
    value filled in from its neighbours (the clamp used to set it to 0): inside their range."""
    from mcrecon.renderers import scenes

    b = scenes.render_uniform("checker_spot", width=24, height=20, spp=8, seed=3, features=True)
    keep = ~((np.floor(b.positions[:, 0]) == 15) & (np.floor(b.positions[:, 1]) == 10))
    for feats in ({k: v[keep] for k, v in b.features.items()}, None):
        ss = SampleSet(b.positions[keep], b.values[keep], width=24, height=20, features=feats)
        img = _quiet(lambda: mcrecon.reconstruct(ss, method="auto"))
        around = np.concatenate([img[9:12, 14:17].reshape(-1, 3)[:4], img[9:12, 14:17].reshape(-1, 3)[5:]])
        assert (img[10, 15] >= around.min(axis=0)).all() and (img[10, 15] <= around.max(axis=0)).all(), img[10, 15]
        assert (img[10, 15] > 0).all()


def test_each_half_of_a_feature_candidate_depends_on_that_half_alone():
    """What makes the cross-validation unbiased, checked directly: changing every value of half B (colour
    and features) leaves each candidate's half-A image unchanged, bit for bit."""
    from mcrecon.methods.auto.features import feature_guided_half

    ss, _ = _textured(0)
    h = split_halves(ss, features="all")
    h2 = split_halves(ss, features="all")
    rng = np.random.default_rng(1)
    h2.b.mean[...] = h2.b.mean * rng.uniform(0.5, 2.0, h2.b.mean.shape)
    for f in h2.b.features.values():
        f.mean[...] = f.mean * rng.uniform(0.5, 2.0, f.mean.shape)
    for name in ("nfor_own", "xbil", "dnlm"):
        np.testing.assert_array_equal(feature_guided_half(name, h.a), feature_guided_half(name, h2.a))
        assert not np.array_equal(feature_guided_half(name, h.b), feature_guided_half(name, h2.b)), name


def test_the_crossed_regression_is_linear_in_its_half_with_everything_else_from_the_other():
    """What makes Stein's estimate of ``nfor`` exact: half A's image depends on half A only through A's
    colour, linearly (A's features changed: the same bits; A's colour doubled: the image doubled), its
    weights and design come from half B (B's features changed: the image moves), and its centre weight
    is the image's derivative at each pixel by the pixel's own value."""
    from mcrecon.methods.auto.features import _HalfPlanes, _regressions

    ss, _ = _textured(0, size=20)
    h = split_halves(ss, features="all")
    _, cross_a, cw = _regressions(_HalfPlanes(h.b), _HalfPlanes(h.a), own=False)
    h2 = split_halves(ss, features="all")
    for f in h2.a.features.values():
        f.mean[...] = f.mean * np.random.default_rng(2).uniform(0.5, 2.0, f.mean.shape)
    np.testing.assert_array_equal(_regressions(_HalfPlanes(h.b), _HalfPlanes(h2.a), own=False)[1], cross_a)
    h2.a.mean[...] = 2.0 * h.a.mean
    np.testing.assert_allclose(_regressions(_HalfPlanes(h.b), _HalfPlanes(h2.a), own=False)[1], 2.0 * cross_a,
                               rtol=1e-9, atol=1e-12)
    h3 = split_halves(ss, features="all")
    h3.b.features["albedo"].mean[...] *= 0.5
    assert not np.allclose(_regressions(_HalfPlanes(h3.b), _HalfPlanes(h.a), own=False)[1], cross_a)
    i, j = 7, 11
    h4 = split_halves(ss, features="all")
    h4.a.mean[i, j, 1] += 1.0
    moved = _regressions(_HalfPlanes(h.b), _HalfPlanes(h4.a), own=False)[1] - cross_a
    assert moved[i, j, 1] == pytest.approx(cw[i, j], rel=1e-7)
    assert moved[i, j, 0] == 0.0 and moved[i, j, 2] == 0.0


def test_the_run_names_every_candidate_of_its_choice():
    """With features the choice indices run past the colour candidates: the run lists them all (OIDN with
    the albedo and normal on all the samples replaces the colour-only one; its halves' average stays)."""
    ss, _ = _textured(0)
    rec = _quiet(lambda: mcrecon.reconstruct(ss, method="auto", full=True))
    names = rec.run.candidate_names
    assert names[:11] == [n for n in get_method("auto").candidate_names() if n != "oidn"]
    assert names[11:] == ["nfor", "nfor_own", "dnlm", "mix33", "mix50", "mix67", "oidn_aux", "oidn_aux_halves"]
    assert rec.diagnostics()["choice"].max() < len(names)
    assert "dnlm" in [names[int(k)] for k in np.unique(rec.diagnostics()["choice"])]


def test_a_pixel_sampled_in_one_half_takes_that_half_s_value():
    """_dual: where only half B has samples, B's image (the feature candidates fill A's empty pixels
    from A's neighbours, so A is finite there but knows nothing of the pixel)."""
    from mcrecon.methods.auto.method import AutoMethod

    a = np.full((2, 2, 1), 1.0)
    b = np.full((2, 2, 1), 3.0)
    ca = np.array([[1, 0], [1, 0]])
    cb = np.array([[1, 1], [0, 0]])
    c = AutoMethod._dual("x", a, b, np.zeros_like(a), np.zeros_like(b), ca, cb)
    np.testing.assert_array_equal(c.image[..., 0], [[2.0, 3.0], [1.0, 1.0]])


def test_albedo_demodulation_keeps_a_checkerboard_wall():
    """The built-in checker_wall (64^2, 16 spp, seeds 0-2): with dnlm among the feature candidates auto's
    error is 0.31-0.34 of the colour-only auto's (measured), without it 0.99-1.00: NL-means of the
    colour divided by the albedo smooths the light across the squares' edges.  Bound 0.5 per seed."""
    for seed in range(3):
        ss, ref = _textured(seed, size=64)
        e = relative_mse(_quiet(lambda: mcrecon.reconstruct(ss, method="auto")), ref)
        e_colour = relative_mse(_quiet(lambda: mcrecon.reconstruct(
            ss, method=get_method("auto", feature_candidates="none"))), ref)
        assert e < 0.5 * e_colour, (seed, e / e_colour)


def test_without_an_albedo_dnlm_is_left_out():
    """Samples with a normal and a depth but no albedo: dnlm has nothing to divide by (nor its mix); the
    run is the run without them, bit for bit."""
    ss, _ = _textured(0)
    ss = SampleSet(ss.positions, ss.values, width=ss.width, height=ss.height,
                   features={k: v for k, v in ss.features.items() if k != "albedo"})
    np.testing.assert_array_equal(_quiet(lambda: mcrecon.reconstruct(ss, method="auto")),
                                  _quiet(lambda: mcrecon.reconstruct(ss, method=get_method(
                                      "auto", feature_candidates="nfor,nfor_own,fbil"))))


def test_feature_candidates_are_estimated_without_bias():
    """Each half of nfor_own, dnlm, xbil and their mixes is filtered from that half alone
    (feature_guided_half takes one half), so their cross-validation is unbiased; nfor filters each half
    with the other's weights and features, linear in the half it filters, so Stein's estimate with its
    exact centre weight is.  Summed over pixels and seeds each estimate matches the candidate's true
    squared error (48^2, 16 spp, seeds 0-3; measured per seed 0.80-1.47, pooled nfor 1.05, nfor_own
    1.14, dnlm 1.20, xbil 1.09, mixes 1.18-1.20; over 16 seeds 0.99-1.07).  Bounds 0.7-1.3: about three
    standard errors of a 4-seed pooled ratio (per-seed spread ~0.2)."""
    from mcrecon.methods.auto.features import feature_candidates

    est, true = {}, {}
    auto = get_method("auto", feature_candidates="nfor,nfor_own,dnlm,mix,xbil")
    for seed in range(4):
        ss, ref = _textured(seed)
        h = split_halves(ss, features="all")
        for c in feature_candidates(auto._feature_names, h.a, h.b):
            ok = np.isfinite(c.mse)
            est[c.name] = est.get(c.name, 0.0) + float(np.sum(c.mse[ok]))
            true[c.name] = true.get(c.name, 0.0) + float(np.sum(((c.image - ref) ** 2)[ok]))
    assert set(est) == {"nfor", "nfor_own", "dnlm", "xbil", "mix33", "mix50", "mix67"}
    for name in est:
        assert 0.7 < est[name] / true[name] < 1.3, (name, est[name] / true[name])


def test_adaptive_auto_with_features_gives_the_image_of_its_log(tmp_path):
    """A renderer that sends features: the halves keep them round by round, and the run's image is the
    offline image of its log."""
    from mcrecon.renderers.scenes import SceneRenderer

    r = SceneRenderer("checker_wall", width=24, height=20, seed=1, features=True)
    log = tmp_path / "run.h5"
    res = _quiet(lambda: adapt(r, get_method("auto"), spp=16, seed=2, progress=False, log=log))
    offline = _quiet(lambda: mcrecon.reconstruct(mcrecon.read_log(log), method="auto"))
    np.testing.assert_allclose(res.image, offline, rtol=1e-9, atol=1e-12)
    assert mcrecon.read_log(log).feature_names == ("albedo", "depth", "normal")


def test_feature_bilateral_centre_weight_is_the_impulse_response_and_its_sure_is_unbiased():
    """fbil (features only in the weights: linear in the colour).  Its centre weight 1 / sum w is exactly
    its response at i to a unit impulse at i (brute force), and with noise-free features its SURE summed
    over an image the features do not explain alone (checkerboard albedo 0.2 / 0.8 in 4 px squares times
    a horizontal shading ramp; Gaussian noise of the mean sd 0.1; 20 seeds) matches the true squared
    error: measured pooled ratio 0.982, per seed 0.92-1.08.  Bound 0.95-1.05: four standard errors of
    the pooled ratio (a wrong centre weight moves it by 2 w_ii v per pixel, several times that)."""
    from mcrecon.filters.cross_bilateral import cross_bilateral
    from mcrecon.methods.auto.features import _feature_bilateral

    h, w = 24, 28
    yy, xx = np.mgrid[0:h, 0:w]
    alb = np.where(((yy // 4) + (xx // 4)) % 2 == 0, 0.2, 0.8)[..., None] * np.ones(3)
    mu = alb * (0.5 + xx / w)[..., None] ** 2
    v = np.full((h, w, 3), 0.01)
    _, wsum = cross_bilateral(alb, v, alb, np.zeros_like(alb), k_colour=None, return_weights=True)
    for (i, j) in ((0, 0), (5, 9), (23, 27)):
        e = np.zeros((h, w, 3))
        e[i, j] = 1.0
        resp = cross_bilateral(e, v, alb, np.zeros_like(alb), k_colour=None)
        assert resp[i, j, 0] == pytest.approx(1.0 / wsum[i, j], rel=1e-12)
    est = true = 0.0
    for seed in range(20):
        y = mu + 0.1 * np.random.default_rng(seed).standard_normal(mu.shape)
        st = PixelStats.from_moments(y, 16 * v, np.full((h, w), 16), features={"albedo": (alb, None)})
        c = _feature_bilateral(st, st.mean, v)
        est += float(np.sum(c.mse))
        true += float(np.sum((c.image - mu) ** 2))
    assert 0.95 < est / true < 1.05, est / true


def test_pixel_statistics_with_features_use_them():
    """One set of pixel statistics with feature images (an EXR's Albedo/N/P.Z) and the SURE candidates:
    fbil joins them.  checker_spot, 64^2, 16 spp, seeds 0-2: measured relMSE 0.78-0.81 of the
    colour-only run's; bound 0.9 (seed spread ~0.01)."""
    r_f, r_c = [], []
    for seed in range(3):
        ss, ref = _textured(seed, scene="checker_spot", size=64)
        st = PixelStats.from_source(ss, features="all")
        r_f.append(relative_mse(_quiet(lambda: mcrecon.reconstruct(st, method=get_method("auto", candidates="box,gauss"))), ref))
        r_c.append(relative_mse(_quiet(lambda: mcrecon.reconstruct(
            st, method=get_method("auto", candidates="box,gauss", feature_candidates="none"))), ref))
    assert np.mean(r_f) < 0.9 * np.mean(r_c), (r_f, r_c)


@pytest.mark.parametrize("size", [(8, 8), (40, 3), (2, 2)])
def test_feature_guided_auto_and_nfor_run_on_films_narrower_than_their_windows(size):
    """NFOR's regression window is 19 x 19: an offset wider than the film has no pair (a film 2-8 px
    wide crashed in its kernel)."""
    from mcrecon.renderers import scenes

    h, w = size
    b = scenes.render_uniform(scenes.get_scene("checker_wall"), width=w, height=h, spp=8, seed=0, features=True)
    ss = SampleSet(b.positions, b.values, width=w, height=h, features=b.features)
    for m in ("auto", "nfor"):
        img = _quiet(lambda: mcrecon.reconstruct(ss, method=m))
        assert img.shape == (h, w, 3) and np.isfinite(img).all()


def test_feature_candidates_none_makes_oidn_colour_only_too():
    pytest.importorskip("pyoidn", reason="needs pyoidn (Intel OIDN), a dependency of mcrecon: pip install -e . "
                        "(or pip install pyoidn)")
    ss_f, _ = _textured(0)
    ss = SampleSet(ss_f.positions, ss_f.values, width=ss_f.width, height=ss_f.height)
    opts = dict(candidates="box,gauss,nlm,oidn", feature_candidates="none")
    np.testing.assert_array_equal(_quiet(lambda: mcrecon.reconstruct(ss_f, method=get_method("auto", **opts))),
                                  _quiet(lambda: mcrecon.reconstruct(ss, method=get_method("auto", **opts))))


def test_a_feature_candidate_is_the_global_default_at_half_a_standard_error(monkeypatch):
    """_significantly_lower: the summed difference against Z_GLOBAL standard errors from the spread of
    its 8 x 8 tiles' sums.  Tile sums -2, 1, -2, 1: total -2, se = sqrt(4) * std = 2 sqrt(3) = 3.46:
    lower by 0.58 se, so it passes at the default 0.5 and not at the former 2."""
    from mcrecon.methods.auto import selection

    d = np.zeros((16, 16))
    d[0, 0], d[0, 8], d[8, 0], d[8, 8] = -2.0, 1.0, -2.0, 1.0
    assert selection.Z_GLOBAL == 0.5 and selection.BLOCK == 8
    assert selection._significantly_lower(d)
    monkeypatch.setattr(selection, "Z_GLOBAL", 2.0)
    assert not selection._significantly_lower(d)
    monkeypatch.setattr(selection, "Z_GLOBAL", 0.6)   # 0.58 se: just short of it
    assert not selection._significantly_lower(d)

"""Tests of the progressive variable-width Epanechnikov splatting (Suykens and Willems 2000).

Every formula is checked against an independent computation: Eq. 4 by
quadrature, Eq. 8 analytically, the discrete footprint by a brute-force
numpy splat, Fig. 3's progressive loop by composing the public formula
functions by hand.  Statistical tests use fixed seeds; their tolerances
are derived in comments.
"""

from __future__ import annotations

import warnings

import numpy as np

import mcrecon
import pytest

from mcrecon.adaptive.run import adapt, resume
from mcrecon.errors import InputError, McreconWarning
from mcrecon.io import read_log, write_log
from mcrecon.methods import get_method
from mcrecon.methods.base import MethodInputs
from mcrecon.methods.splat import (ProgressiveSplatter, SplatMethod, doubling_schedule, epanechnikov, kernel_width,
                                   pilot_width, sample_norm, splat)
from mcrecon.methods.splat.progressive import _radii
from mcrecon.core.metrics import mse, relative_mse
from mcrecon.renderers import scenes
from mcrecon.core.requests import SampleRequest, jittered_positions
from mcrecon.core.stats import PixelStats


# ----------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------

def brute_splat(pos, val, diam, w, h, boundary, scale=None):
    """Independent numpy splat: K of Eq. 4 at every pixel centre of a padded grid, normalised per sample."""
    scale = np.ones(len(pos)) if scale is None else scale
    out = np.zeros((h, w, val.shape[1]))
    for (x, y), v, d, s in zip(pos, val, diam, scale):
        r = d / 2
        pad = int(np.ceil(r)) + 2
        ii, jj = np.meshgrid(np.arange(-pad, w + pad), np.arange(-pad, h + pad))
        pts = np.stack([(ii + 0.5 - x) / r, (jj + 0.5 - y) / r], axis=-1)
        k = epanechnikov(pts)
        inside = (ii >= 0) & (ii < w) & (jj >= 0) & (jj < h)
        if boundary == "renormalize":
            k = np.where(inside, k, 0.0)
        tot = k.sum()
        if tot == 0:  # no centre covered: own pixel
            out[int(y), int(x)] += v * s
            continue
        k = k / tot
        for j, i, kk in zip(jj.ravel(), ii.ravel(), k.ravel()):
            if kk == 0:
                continue
            if boundary == "mirror":
                i2, j2 = i % (2 * w), j % (2 * h)
                i2 = 2 * w - 1 - i2 if i2 >= w else i2
                j2 = 2 * h - 1 - j2 if j2 >= h else j2
            else:
                i2, j2 = i, j
                if not (0 <= i < w and 0 <= j < h):
                    continue
            out[j2, i2] += v * s * kk
    return out


def rank_split(pos, val, w, schedule):
    """Split a batch sorted by pixel with equal counts into rounds by per-pixel rank."""
    pix = np.floor(pos[:, 1]).astype(int) * w + np.floor(pos[:, 0]).astype(int)
    order = np.argsort(pix, kind="stable")
    rank = np.empty(len(pix), int)
    counts = np.bincount(pix)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank[order] = np.arange(len(pix)) - np.repeat(starts, counts)
    lo = 0
    for n in schedule:
        sel = (rank >= lo) & (rank < lo + n)
        lo += n
        yield pos[sel], val[sel]


def render_rounds(scene, w, schedule, seed):
    r = scenes.SceneRenderer(scene, width=w, height=w, seed=seed)
    for j, n in enumerate(schedule):
        yield r.render(SampleRequest(w, w, counts=np.full((w, w), n), round_index=j, seed=seed))


# ----------------------------------------------------------------------------
# Eq. 4, Eq. 8, pilot width
# ----------------------------------------------------------------------------

def test_epanechnikov_eq4_value_support_and_unit_integral():
    assert epanechnikov([0.0, 0.0]) == pytest.approx(2 / np.pi, rel=1e-15)
    assert epanechnikov([0.6, 0.0]) == pytest.approx(2 / np.pi * 0.64, rel=1e-15)
    assert epanechnikov([1.0, 0.0]) == 0.0 and epanechnikov([0.8, 0.7]) == 0.0
    # Midpoint rule on a 2000^2 grid over [-1, 1]^2: K is continuous and
    # vanishes on the unit circle, so the error is O(cell^2) ~ 1e-6.
    n = 2000
    c = (np.arange(n) + 0.5) / n * 2 - 1
    xx, yy = np.meshgrid(c, c)
    integral = epanechnikov(np.stack([xx, yy], -1)).sum() * (2 / n) ** 2
    assert integral == pytest.approx(1.0, abs=2e-5)


def test_kernel_width_eq8_analytic_and_clamps():
    # C=4, N=16, alpha=1/2, G/f=4: h = 4 * 16^-1/2 * 2 = 2
    assert kernel_width(4.0, 1.0, 16, c=4, alpha=0.5) == pytest.approx(2.0, rel=1e-15)
    # paper defaults: alpha = 1.5/5 at N = 4, G = f: 4 * 4^-0.3
    assert kernel_width(0.3, 0.3, 4) == pytest.approx(4 * 4 ** -0.3, rel=1e-14)
    # negative sample: magnitude
    assert kernel_width(-4.0, 1.0, 16, c=4, alpha=0.5) == pytest.approx(2.0)
    # lower clamp (one pixel) and cap
    assert kernel_width(1e-6, 1.0, 1) == 1.0
    assert kernel_width(1e6, 1.0, 1) == 32.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        # f = 0, f tiny, G = 0, non-finite f: no warning, documented widths
        assert kernel_width(1.0, 0.0, 1) == 32.0
        assert kernel_width(1e300, 1e-300, 1, max_width=50) == 50.0
        assert kernel_width(0.0, 1.0, 1) == 1.0
        assert kernel_width(1.0, np.nan, 1) == 32.0


def test_numba_widths_agree_with_eq8(rng):
    w = h = 7
    n = 500
    pos = rng.random((n, 2)) * [w, h]
    val = rng.standard_normal((n, 3)) * 10.0 ** rng.integers(-3, 3, (n, 1))
    val[:20] = 0.0
    ref_img = np.abs(rng.standard_normal((h, w, 3)))
    ref_img[0, :] = 0.0  # f = 0 row
    counts = rng.integers(1, 40, (h, w)).astype(float)
    ref = sample_norm(ref_img)
    out = np.empty(n)
    _radii(pos, val, 0, np.array([0.2126, 0.7152, 0.0722]), ref, counts, False, 4.0, 0.3, 8.0, 1.0, 32.0, out)
    ix, iy = pos[:, 0].astype(int), pos[:, 1].astype(int)
    g = sample_norm(val)
    expect = kernel_width(g, ref[iy, ix], counts[iy, ix]) / 2
    expect[g == 0] = -1.0
    np.testing.assert_allclose(out, expect, rtol=1e-13)
    _radii(pos, val, 0, np.array([0.2126, 0.7152, 0.0722]), ref, counts, True, 4.0, 0.3, 8.0, 1.0, 32.0, out)
    np.testing.assert_allclose(out[g > 0], pilot_width(counts[iy, ix])[g > 0] / 2, rtol=1e-13)
    # C' = 8 gives an 8 pixel diameter at N0 = 1 (paper: 8-10 pixels)
    assert pilot_width(1) == 8.0 and pilot_width(4) == 4.0


def test_sample_norms():
    v = np.array([[1.0, -2.0, 3.0], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(sample_norm(v, "luminance"), [0.2126 + 2 * 0.7152 + 3 * 0.0722, 0.0])
    np.testing.assert_allclose(sample_norm(v, "mean"), [2.0, 0.0])
    np.testing.assert_allclose(sample_norm(v, "max"), [3.0, 0.0])
    with pytest.raises(InputError, match="norm"):
        sample_norm(np.ones((2, 4)), "luminance")


# ----------------------------------------------------------------------------
# The discrete footprint
# ----------------------------------------------------------------------------

@pytest.mark.parametrize("boundary", ["mirror", "renormalize", "none"])
@pytest.mark.parametrize("size", [(9, 7), (1, 1), (2, 3)])
def test_splat_matches_brute_force(boundary, size, rng):
    w, h = size
    n = 60
    pos = rng.random((n, 2)) * [w, h]
    val = rng.standard_normal((n, 2))
    diam = np.concatenate([rng.uniform(1, 3, n // 2), rng.uniform(3, 12, n - n // 2)])
    scale = rng.uniform(0.5, 2, n)
    ours = splat(pos, val, diam, width=w, height=h, boundary=boundary, scale=scale)
    np.testing.assert_allclose(ours, brute_splat(pos, val, diam, w, h, boundary, scale), rtol=1e-12, atol=1e-13)


def test_footprint_falls_back_to_own_pixel_and_skips_zero():
    # r = 0.5 (one pixel wide): a sample in a pixel corner covers no centre.
    out = splat([[3.02, 4.97]], [[2.0, 1.0, 5.0]], 1.0, width=8, height=8)
    assert out[4, 3].tolist() == [2.0, 1.0, 5.0] and out.sum() == 8.0
    # a sample at its pixel centre with r = 0.5 also stays home
    out = splat([[3.5, 4.5]], [[1.0, 1.0, 1.0]], 1.0, width=8, height=8)
    assert out[4, 3, 0] == 1.0 and out.sum() == 3.0
    # negative diameter = skipped
    assert splat([[3.5, 4.5]], [[1.0, 1.0, 1.0]], -1.0, width=8, height=8).sum() == 0.0


@pytest.mark.parametrize("boundary", ["mirror", "renormalize"])
def test_energy_exact_with_remedy_extreme_inputs(boundary, rng):
    w, h = 13, 7  # prime sizes
    n = 5000
    pos = rng.random((n, 2)) * [w, h]
    pos[:500, 0] = rng.random(500) * 0.3  # crowd the left border
    val = rng.standard_normal((n, 3)) * 10.0 ** rng.integers(-3, 4, (n, 1))
    val[1000:1500] = 0.0
    val[5] = [500.0, 500.0, 500.0]
    val[6] = [1e-3, -1e-3, 1e-3]
    diam = rng.uniform(1, 40, n)  # up to three times the film
    scale = rng.uniform(0.1, 1, n)
    out = splat(pos, val, diam, width=w, height=h, boundary=boundary, scale=scale)
    expect = (val * scale[:, None]).sum(0)
    # float64: each deposit rounds at ~1e-16 relative to |v|, so with
    # |v| <= 1e3 and 5000 * ~100 deposits the error is ~1e-11 of the largest
    # term; the totals are O(1e3), so relative 1e-9 has three orders of margin.
    np.testing.assert_allclose(out.sum((0, 1)), expect, rtol=1e-9, atol=1e-9 * np.abs(val * scale[:, None]).sum(0).max())
    lost = splat(pos, val, diam, width=w, height=h, boundary="none", scale=np.abs(scale))
    assert not np.allclose(lost.sum((0, 1)), (val * np.abs(scale)[:, None]).sum(0), rtol=1e-3)


def test_method_energy_equals_sample_energy_on_scene(tmp_path):
    """Total splatted energy = total sample energy: sum(image) = sum of pixel means (uniform spp)."""
    path = scenes.write_scene_log("caustic", tmp_path / "c.h5", width=31, height=29, spp=16, seed=2,
                                  reference=False)
    img = mcrecon.reconstruct(path, method=SplatMethod(variant="paper"))
    stats = PixelStats.from_log(read_log(path))
    np.testing.assert_allclose(img.sum((0, 1)), stats.mean.sum((0, 1)), rtol=1e-9)
    assert np.isfinite(img).all()


# ----------------------------------------------------------------------------
# Fig. 3: the progressive algorithm
# ----------------------------------------------------------------------------

def test_progressive_rounds_match_fig3_by_hand(rng):
    w, h = 11, 9
    rounds = [jittered_positions(np.full((h, w), n), rng) for n in (1, 2, 4)]
    vals = [np.abs(rng.standard_normal((len(p), 3))) ** 3 for p in rounds]
    vals[0][::7] = 0.0
    sp = ProgressiveSplatter(w, h, 3)
    for p, v in zip(rounds, vals):
        sp.add_round(p, v)

    def pix(p):
        return p[:, 1].astype(int), p[:, 0].astype(int)

    # f'_0: fixed width C' N0^-1/2 = 8 (N0 = 1), each sample carrying F / 1
    p0, v0 = rounds[0], vals[0]
    g0 = sample_norm(v0)
    d0 = np.where(g0 > 0, pilot_width(np.ones(len(p0))), -1)
    pilot = brute_splat(p0, v0, d0, w, h, "mirror")
    np.testing.assert_allclose(sp.pilot, pilot, rtol=1e-12, atol=1e-14)
    # f_0: Eq. 8 with f'_0 as reference, N = 1
    d = np.where(g0 > 0, kernel_width(g0, sample_norm(pilot)[pix(p0)], 1), -1)
    f = brute_splat(p0, v0, d, w, h, "mirror")
    total = 1
    for p, v, n in zip(rounds[1:], vals[1:], (2, 4)):
        new_total = total + n
        g = sample_norm(v)
        d = np.where(g > 0, kernel_width(g, sample_norm(f)[pix(p)], new_total), -1)
        # scale down, then splat F / N_total (each pixel has n samples this round: F/n * n/N_total)
        f = f * total / new_total + brute_splat(p, v, d, w, h, "mirror", np.full(len(p), 1 / new_total))
        total = new_total
    np.testing.assert_allclose(sp.image, f, rtol=1e-11, atol=1e-13)
    assert sp.spp_total == 7


def test_width_floor_gives_pixel_mean(rng):
    """At the one-pixel floor every sample lands in its own pixel: the estimator is the pixel mean
    (the limit the progressive widths C N^-alpha -> 0 converge to)."""
    w, h = 12, 10
    sp = ProgressiveSplatter(w, h, 3, c=1e-9, c_prime=1e-9)
    st = PixelStats(w, h)
    for n in doubling_schedule(8):
        p = jittered_positions(np.full((h, w), n), rng)
        v = rng.standard_normal((len(p), 3)) * 100
        sp.add_round(p, v)
        st.add(p, v)
    np.testing.assert_allclose(sp.image, st.mean, rtol=1e-12, atol=1e-12)


def test_doubling_schedule():
    assert doubling_schedule(4) == [1, 3]
    assert doubling_schedule(64) == [1, 2, 4, 8, 16, 33]
    assert doubling_schedule(2) == [1, 1]
    assert doubling_schedule(1) == [1]
    assert doubling_schedule(10, 2) == [2, 8]
    for s in range(1, 300):
        sch = doubling_schedule(s)
        assert sum(sch) == s and all(b >= a for a, b in zip(sch, sch[1:]))


# ----------------------------------------------------------------------------
# Boundary bias (paper Sec. 5)
# ----------------------------------------------------------------------------

@pytest.mark.parametrize("boundary", ["mirror", "none"])
def test_border_darkening_flat_scene(boundary):
    """Mean of the outermost pixel ring relative to the exact 0.5.

    Spread: the ring of a 64^2 film has 252 pixels x 3 channels; with 4 spp
    of variance 1/12 and an energy-preserving filter, the ring's mean has
    about the variance of the mean of its own samples, sqrt(1/12 / (4 * 756))
    = 0.0052, i.e. 1.05 % of 0.5 per run (measured: 0.8 %).  Over 16 seeds
    the standard error is 0.26 %, so the 1 % bound has ~4 sigma of margin
    for an unbiased remedy, and kernel truncation without a remedy (~30 %
    darker, measured) is > 100 sigma away.
    """
    w = 64
    devs = []
    for seed in range(16):
        b = scenes.render_uniform("flat", width=w, height=w, spp=4, seed=seed)
        sp = ProgressiveSplatter(w, w, 3, boundary=boundary)
        for p, v in rank_split(b.positions, b.values, w, doubling_schedule(4)):
            sp.add_round(p, v)
        ring = np.ones((w, w), bool)
        ring[1:-1, 1:-1] = False
        devs.append(sp.image[ring].mean() / 0.5 - 1)
    dev = float(np.mean(devs))
    if boundary == "mirror":
        assert abs(dev) < 0.01
    else:
        assert dev < -0.10


# ----------------------------------------------------------------------------
# Consistency and spike noise on the built-in scenes
# ----------------------------------------------------------------------------

@pytest.mark.slow
# the six scenes measured below, not the textured ones (issue 24)
@pytest.mark.parametrize("scene", [s for s in scenes.scene_names()[:6] if s != "caustic"])
def test_relative_mse_falls_with_every_doubling(scene, full_run):
    """Along one progressive run, relative MSE falls after every round (N_j = 2 N_{j-1}),
    and its ratio to the pixel-mean error of the same samples moves back towards 1.

    Margin: over 3 seeds at 64^2 every round lowered the error by >= 15 %
    while seed-to-seed spread of each error is ~5 % (measured), so a
    strict decrease is robust.  CI: 64^2, 64 spp (6 rounds); full: 128^2, 256 spp.
    Not on caustic, where the error rises again after the first rounds: a
    measured limit (``python benchmarks/bench_splat.py --limits``,
    docs/methods/splat.md "Measured limits").
    """
    w, total = (128, 256) if full_run else (64, 64)
    ref = scenes.reference_image(scene, w, w)
    sp = ProgressiveSplatter(w, w, 3)
    st = PixelStats(w, w)
    errs, ratios = [], []
    for b in render_rounds(scene, w, doubling_schedule(total), seed=5):
        sp.add_round(b.positions, b.values)
        st.add(b.positions, b.values)
        errs.append(relative_mse(sp.image, ref))
        ratios.append(errs[-1] / relative_mse(st.mean, ref))
    assert all(b < a for a, b in zip(errs, errs[1:])), errs
    logr = np.abs(np.log(ratios))
    assert logr[-1] < logr.max(), ratios


def _caustic_pair(spp, seed, w=64):
    r = scenes.SceneRenderer("caustic", width=w, height=w, seed=seed)
    s = adapt(r, SplatMethod(variant="paper"), spp=spp, seed=seed, track_error=False).image
    b = adapt(r, "box", spp=spp, seed=seed, track_error=False).image
    return s, b, scenes.reference_image("caustic", w, w)


@pytest.mark.parametrize("spp", [4, 64])
def test_caustic_spike_noise_reduced(spp):
    """Spikes are spread: the largest pixel error is far below box's at 4 and 64 spp, and at 4 spp
    the (absolute) MSE too.

    Measured over 3 seeds at 64^2: max |error| splat 3.6-4.0 vs box 31-32
    (4 spp) and 6.1-7.2 (64 spp); MSE 0.12-0.14 vs 1.0-1.6 at 4 spp.  The
    asserted factors (2 and 1.3 on the max, 3 on the MSE) keep > 30 % margin.
    """
    s, b, ref = _caustic_pair(spp, seed=7)
    assert np.abs(s - ref).max() * (2.0 if spp == 4 else 1.3) < np.abs(b - ref).max()
    if spp == 4:
        assert 3 * mse(s, ref) < mse(b, ref)


# ----------------------------------------------------------------------------
# Adaptive driver, resume, offline logs
# ----------------------------------------------------------------------------

def test_plan_schedule_every_pixel_each_round():
    r = scenes.SceneRenderer("flat", width=8, height=5, seed=0)
    res = adapt(r, SplatMethod(initial_spp=1), spp=64, seed=1, track_error=False)
    assert [x["samples"] // 40 for x in res.rounds] == [1, 2, 4, 8, 16, 33]
    # the default's N_0 = 16, split 8 + 8 when pipelined (the default): every round judged by the outlier test
    res = adapt(r, SplatMethod(), spp=64, seed=1, track_error=False)
    assert [x["samples"] // 40 for x in res.rounds] == [8, 8, 16, 32]
    res = adapt(r, SplatMethod(), spp=64, seed=1, track_error=False, pipeline=False)
    assert [x["samples"] // 40 for x in res.rounds] == [16, 48]
    assert (res.counts == 64).all()
    res = adapt(r, SplatMethod(initial_spp=2), spp=10.5, seed=1, track_error=False, pipeline=False)
    assert [x["samples"] for x in res.rounds] == [80, 320]  # 2, then 8; the 20 left over stay unspent
    # pipelined, the driver splits an initial pass of >= 2 spp in two rounds (1 + 1), then 2, then the rest
    res = adapt(r, SplatMethod(initial_spp=2), spp=10.5, seed=1, track_error=False, pipeline=True)
    assert [x["samples"] for x in res.rounds] == [40, 40, 80, 240]
    with pytest.raises(InputError, match="one sample per pixel"):
        adapt(r, SplatMethod(), spp=0.5, seed=1)


@pytest.mark.parametrize("variant", ["robust", "paper"])
def test_resume_rebuilds_progressive_state_exactly(tmp_path, variant):
    r = scenes.SceneRenderer("soft_shadow", width=16, height=12, seed=3)
    m = SplatMethod(variant=variant)
    full = adapt(r, m, spp=31, seed=4, log=tmp_path / "a.h5", track_error=False)
    adapt(r, m, spp=31, seed=4, log=tmp_path / "b.h5", max_rounds=2, track_error=False)
    resumed = resume(tmp_path / "b.h5", r, track_error=False)
    np.testing.assert_array_equal(resumed.image, full.image)
    # offline replay of the adaptive log's rounds gives the same image
    np.testing.assert_array_equal(mcrecon.reconstruct(tmp_path / "a.h5", method=m), full.image)


def test_single_round_log_split_into_pixel_rank_pseudo_rounds(tmp_path):
    w = 10
    b = scenes.render_uniform("depth_of_field", width=w, height=w, spp=7, seed=1)
    path = write_log(tmp_path / "l.h5", b.positions, b.values, width=w, height=w)
    img = mcrecon.reconstruct(path, method=SplatMethod(variant="paper"))
    pos = np.asarray(read_log(path).read_all().positions)
    sp = ProgressiveSplatter(w, w, 3)
    for p, v in rank_split(pos, b.values, w, doubling_schedule(7)):
        sp.add_round(p, v)
    np.testing.assert_array_equal(img, sp.image)


def test_single_round_log_with_unequal_counts_covers_every_pixel(tmp_path, rng):
    w, h = 9, 6
    counts = rng.integers(3, 20, (h, w))
    pos = jittered_positions(counts, rng)
    val = rng.random((len(pos), 3))
    path = write_log(tmp_path / "u.h5", pos, val, width=w, height=h)
    m = SplatMethod(variant="paper")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "pixels without samples" warning
        rec = mcrecon.reconstruct(path, method=m, full=True)
    img = rec.image
    assert np.isfinite(img).all() and len(rec.run.splatter.rounds) == len(doubling_schedule(3))
    # each pseudo-round's image is the splat of its pixel means: energy sum_j N_j/N sum_p mean_pj
    assert img.sum() == pytest.approx(val.sum() / counts.sum() * w * h, rel=0.2)


def test_nonfinite_policies_in_logs(tmp_path, rng):
    w = 6
    b = scenes.render_uniform("flat", width=w, height=w, spp=4, seed=0)
    val = np.array(b.values)
    val[3] = np.nan
    path = write_log(tmp_path / "n.h5", b.positions, val, width=w, height=w)
    with pytest.warns(McreconWarning, match="NaN"):
        img = mcrecon.reconstruct(path, method="splat")
    assert np.isfinite(img).all()
    with pytest.raises(InputError, match="NaN"):
        mcrecon.reconstruct(path, method="splat", nonfinite="raise")


def test_samples_checked_by_the_shared_path(rng):
    """The splatter and splat() check samples with mcrecon.core.samples (the rules and messages of the
    statistics and the log reader), and the offline warning counts each NaN/Inf sample once."""
    w, h = 6, 4
    pos = jittered_positions(np.ones((h, w), int), rng)
    val = rng.random((w * h, 3))
    off = pos.copy()
    off[5] = [6.0, 1.0]
    sp = ProgressiveSplatter(w, h, 3)
    with pytest.raises(InputError, match=r"^r: positions: 1 sample\(s\) off the film \[0, 6\) x \[0, 4\)"):
        sp.add_round(off, val, where="r")
    with pytest.raises(InputError) as e:
        sp.add_round(pos, val[:, :2], where="r")
    assert (e.value.where, e.value.field) == ("r", "values") and "(N, 3)" in e.value.problem
    with pytest.raises(InputError, match="unknown policy 'keep'"):
        sp.add_round(pos, val, nonfinite="keep")
    assert not sp.rounds and sp.spp_total == 0
    with pytest.raises(InputError, match=r"^splat: positions: 1 sample\(s\) off the film"):
        splat(off, val, 2.0, width=w, height=h)
    # Three rounds of 1, 2, 4 spp with four NaN/Inf samples: the later rounds are read
    # twice (counts, then splats), yet each bad sample is counted once.
    rounds = np.repeat([0, 1, 2], [w * h, 2 * w * h, 4 * w * h])
    pos = np.concatenate([jittered_positions(np.full((h, w), n), rng) for n in (1, 2, 4)])
    val = rng.random((len(pos), 3))
    val[[30, 60, 100]] = np.nan                                         # rounds 1 and 2, no pixel emptied
    val[101, 1] = np.inf
    src = mcrecon.SampleSet(pos, val, width=w, height=h, rounds=rounds)
    with pytest.warns(McreconWarning, match=r"4 sample\(s\) with NaN or Inf dropped \(policy nonfinite='drop'\)"):
        rec = mcrecon.reconstruct(src, method="splat", full=True)
    assert np.isfinite(rec.image).all() and rec.run.splatter.n_nonfinite == 4
    with pytest.raises(InputError, match=r"^samples: values: 2 sample\(s\) with NaN or Inf values"):
        mcrecon.reconstruct(src, method="splat", nonfinite="raise")          # refused at round 1


def test_reconstruct_from_stats_is_refused():
    with pytest.raises(InputError, match="individual samples"):
        SplatMethod().reconstruct(MethodInputs(PixelStats(4, 4)))
    with pytest.raises(InputError, match="individual samples"):
        mcrecon.reconstruct(PixelStats(4, 4), method="splat")


# ----------------------------------------------------------------------------
# Guard rails and extreme inputs
# ----------------------------------------------------------------------------

@pytest.mark.parametrize("scene", ["caustic", "hdr"])
def test_extreme_scenes_one_spp_finite_no_warning(scene):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = adapt(scenes.SceneRenderer(scene, width=7, height=5, seed=0), "splat", spp=1, seed=0,
                    track_error=False)
    assert np.isfinite(res.image).all()


def test_guard_rails_all_zero_negative_and_one_pixel(rng):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sp = ProgressiveSplatter(5, 3, 3)
        sp.add_round(jittered_positions(np.ones((3, 5), int), rng), np.zeros((15, 3)))
        assert (sp.image == 0).all()
        # then a huge spike where f = 0: width capped at max_width, energy kept
        sp.add_round(np.array([[2.5, 1.5]] + [[i + 0.5, j + 0.5] for j in range(3) for i in range(5)])[1:],
                     np.vstack([[1e30, 1e30, 1e30], np.zeros((14, 3))]))
        assert sp.rounds[-1]["capped"] == 1
        assert sp.image.sum() == pytest.approx(3e30 / 2, rel=1e-12)  # N_1 / N_total = 1/2
        # negative samples keep their sign; 1x1 film
        one = ProgressiveSplatter(1, 1, 3)
        one.add_round([[0.3, 0.9], [0.5, 0.5]], [[-2.0, 1e-3, 500.0], [0.0, 1.0, 500.0]])
        np.testing.assert_allclose(one.image[0, 0], [-1.0, 0.5005, 500.0])


def test_option_validation():
    for bad in ({"alpha": 0}, {"alpha": 1.5}, {"c": -1}, {"c_prime": float("nan")}, {"min_width": 0.5},
                {"max_width": 0.9}, {"initial_spp": 0}, {"initial_spp": 1.5}, {"boundary": "wrap"},
                {"norm": "l2"}, {"colour": 1}):
        with pytest.raises(InputError):
            SplatMethod(**bad)
    m = SplatMethod(alpha=0.2, c=2, c_prime=10, max_width=64, boundary="renormalize", norm="max")
    assert m.describe()["boundary"] == "renormalize"
    with pytest.raises(InputError, match="luminance"):
        m2 = SplatMethod()
        m2._new_splatter(4, 4, 4)

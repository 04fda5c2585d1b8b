"""The robust default of ``splat`` (issue 12): never worse than the pixel mean of the same samples.

The built-in scenes are *not* used to check the properties here (the
defaults were chosen on them): three procedural scenes of this file are,
each with an exact reference (pixel integrals in closed form):

* ``emitter``: a tiny bright emitter (1000, 2.5 x 1.5 px, not pixel-aligned) on a 1e-3 background;
* ``step``: an HDR step edge (100 | 0.01) at a fractional column, noise in both halves;
* ``fireflies``: a smooth gradient whose samples are, with probability 1/200, worth 200 times the
  integrand (a rare-event estimator: E = 2 x gradient).

Runs are offline (a ``SampleSet``, split into pseudo-rounds by the method)
and adaptive (the driver), 32 x 32 px, fixed seeds; a few seconds in all.
"""

from __future__ import annotations

import contextlib

import numpy as np
import pytest

import mcrecon
from mcrecon.errors import McreconWarning
from mcrecon.adaptive.run import adapt
from mcrecon.methods.splat import ProgressiveSplatter, SplatMethod, doubling_schedule, splat
from mcrecon.methods.splat.kernels import _splat_guided_loop
from mcrecon.core.metrics import relative_mse
from mcrecon.core.requests import jittered_positions
from mcrecon.core.stats import PixelStats

from helpers import jittered_renderer

W = 32
P_FIREFLY = 1 / 200


def _emitter_box():
    return 13.3, 15.8, 10.6, 12.1  # x0, x1, y0, y1


def _overlap(lo, hi, a, b):
    return np.clip(np.minimum(hi, b) - np.maximum(lo, a), 0, None)


def scene_values(name, pos, rng):
    """Per-sample RGB values of the procedural scenes (u ~ U[0,1) noise drawn from ``rng``)."""
    x, y = pos[:, 0], pos[:, 1]
    u = rng.random(len(x))
    if name == "emitter":
        x0, x1, y0, y1 = _emitter_box()
        inside = (x >= x0) & (x < x1) & (y >= y0) & (y < y1)
        lum = np.where(inside, 1000.0, 1e-3 * 2 * u)
    elif name == "step":
        lum = np.where(x < 15.4, 100.0, 0.01) * 2 * u
    elif name == "fireflies":
        g = 0.2 + 0.6 * x / W
        # a firefly worth g / p with probability p, else g * U[0, 2): E = g + g (1 - p) ~ 2 g - p g
        lum = np.where(u < P_FIREFLY, g / P_FIREFLY, g * rng.random(len(x)) * 2 / (1 - P_FIREFLY))
    else:
        raise ValueError(name)
    return lum[:, None] * np.array([1.0, 0.8, 0.6])


def scene_reference(name):
    """Exact pixel integrals."""
    i = np.arange(W, dtype=float)
    if name == "emitter":
        x0, x1, y0, y1 = _emitter_box()
        a = _overlap(i[None, :], i[None, :] + 1, x0, x1) * _overlap(i[:, None], i[:, None] + 1, y0, y1)
        lum = 1000.0 * a + 1e-3 * (1 - a)
    elif name == "step":
        a = _overlap(i, i + 1, -np.inf, 15.4)
        lum = np.broadcast_to(100.0 * a + 0.01 * (1 - a), (W, W))
    else:  # fireflies: 2 g, g linear in x: the pixel mean is g at the pixel centre
        lum = np.broadcast_to(2 * (0.2 + 0.6 * (i + 0.5) / W), (W, W))
    return lum[:, :, None] * np.array([1.0, 0.8, 0.6])


def uniform_samples(name, spp, seed):
    rng = np.random.default_rng([seed, 7])
    pos = jittered_positions(np.full((W, W), spp), rng)
    return pos, scene_values(name, pos, rng)


def renderer(name, seed):
    return jittered_renderer(lambda pos, rng, request: scene_values(name, pos, rng), width=W, height=W, name=name,
                             stream=lambda request: [seed, int(request.seed or 0), int(request.round_index)])


SCENES = ("emitter", "step", "fireflies")


# ----------------------------------------------------------------------------
# never worse than the pixel mean of the same samples
# ----------------------------------------------------------------------------

# The largest ratio of the robust default's relative MSE to the pixel mean's over seeds 0-2 (measured).
_OFFLINE_MEASURED = {"emitter": 0.9997, "step": 0.507, "fireflies": 0.319}


@pytest.mark.parametrize("name", SCENES)
def test_robust_never_worse_than_pixel_mean_offline(name):
    """Relative MSE of the robust default <= that of the pixel mean of the same samples, 3 seeds, and
    within 15 % of the measured ratio (``_OFFLINE_MEASURED``) where that stays below the pixel mean.

    Measured ratios (seeds 0-2, 16 spp): emitter 0.9994-0.9997 (its partly
    covered pixels are told apart from their neighbours: little is spread),
    step 0.47-0.51, fireflies 0.28-0.32; ``variant="outliers"`` (the default
    before issue 26, which moves only the excess of outliers): emitter 1,
    step 1, fireflies 0.28-0.32; the paper's variant on the same samples: emitter
    2e6-6e6, step 5e3-7e3, fireflies 0.010-0.012 (asserted: > 10x worse
    than box on the two HDR scenes, which is why the default departs from it;
    on a smooth gradient its wide kernels win, the price of that default).
    """
    ref = scene_reference(name)
    for seed in range(3):
        pos, val = uniform_samples(name, 16, seed)
        ss = mcrecon.SampleSet(pos, val, width=W, height=W)
        st = PixelStats(W, W)
        st.add(pos, val)
        e_box = relative_mse(st.mean, ref)
        e_rob = relative_mse(mcrecon.reconstruct(ss, method="splat"), ref)
        assert e_rob <= e_box * min(1 + 1e-9, 1.15 * _OFFLINE_MEASURED[name]), (name, seed, e_rob / e_box)
        if name != "fireflies" and seed == 0:
            e_pap = relative_mse(mcrecon.reconstruct(ss, method=SplatMethod(variant="paper")), ref)
            assert e_pap > 10 * e_box


@pytest.mark.parametrize("name", SCENES)
def test_robust_never_worse_than_pixel_mean_adaptive(name):
    """The adaptive (progressive) run against the pixel mean of *its own* samples (res.stats).

    A box run through the driver draws other samples (its rounds differ), so
    its error differs by sampling noise alone; the same samples isolate the
    reconstruction.
    """
    ref = scene_reference(name)
    for seed in range(2):
        res = adapt(renderer(name, seed), "splat", spp=16, seed=seed, track_error=False)
        e_box = relative_mse(res.stats.mean, ref)
        assert relative_mse(res.image, ref) <= e_box * (1 + 1e-9), (name, seed)


# ----------------------------------------------------------------------------
# energy, consistency, no overshoot
# ----------------------------------------------------------------------------

@pytest.mark.parametrize("boundary", ["mirror", "renormalize"])
def test_robust_energy_equals_sample_energy(boundary):
    """sum(image) = sum of the pixel means (uniform spp), relative 1e-9 (float64 rounding ~1e-13)."""
    for name in ("fireflies", "emitter"):
        pos, val = uniform_samples(name, 8, 3)
        ss = mcrecon.SampleSet(pos, val, width=W, height=W)
        rec = mcrecon.reconstruct(ss, method=SplatMethod(boundary=boundary), full=True)
        assert name == "emitter" or sum(r["outliers"] for r in rec.run.splatter.rounds) > 0  # spread
        st = PixelStats(W, W)
        st.add(pos, val)
        np.testing.assert_allclose(rec.image.sum((0, 1)), st.mean.sum((0, 1)), rtol=1e-9)
    res = adapt(renderer("fireflies", 1), "splat", spp=8, seed=1, track_error=False)
    np.testing.assert_allclose(res.image.sum((0, 1)), res.stats.mean.sum((0, 1)), rtol=1e-9)


def test_robust_consistent_error_falls_with_spp():
    """Relative MSE on ``fireflies`` falls towards 0 as spp grows, never above the pixel mean's.

    Mean over 3 seeds at 4, 16, 64, 256 spp; measured: 9.6, 0.95, 0.40,
    0.19 (box: 9.6, 3.2, 0.78, 0.195; at 4 spp no 3x3 window holds the 64
    samples of the outlier test, so it *is* box).  The excess widths shrink
    as N^-1/2 and the method tends to the pixel mean, whose error falls as
    1/N.  Asserted: each 4x step lowers the mean error by >= 1.5x (the
    smallest measured step is 2.1x; the seed spread of a mean is ~12 %).
    """
    ref = scene_reference("fireflies")
    errs, boxes = [], []
    for spp in (4, 16, 64, 256):
        e, bx = [], []
        for seed in range(3):
            pos, val = uniform_samples("fireflies", spp, seed)
            e.append(relative_mse(mcrecon.reconstruct(mcrecon.SampleSet(pos, val, width=W, height=W),
                                                      method="splat"), ref))
            st = PixelStats(W, W)
            st.add(pos, val)
            bx.append(relative_mse(st.mean, ref))
        errs.append(np.mean(e))
        boxes.append(np.mean(bx))
    assert all(b < a / 1.5 for a, b in zip(errs, errs[1:])), errs
    assert all(e <= bx * (1 + 1e-9) for e, bx in zip(errs, boxes)), (errs, boxes)


def test_flat_50_no_overshoot():
    """A region of exactly 50 (zero variance) stays exactly 50; the paper's variant does not.

    Left of column 16 every sample is 50, right of it 1e-3: every pixel of
    the robust result lies within the values its own samples hold (to
    rounding).  The paper's jittered splat footprints do not form a
    partition of unity, so its flat region scatters (measured 35-63).
    """
    rng = np.random.default_rng(0)
    pos = jittered_positions(np.full((W, W), 8), rng)
    val = np.where(pos[:, :1] < 16, 50.0, 1e-3) * np.ones((1, 3))
    ss = mcrecon.SampleSet(pos, val, width=W, height=W)
    img = mcrecon.reconstruct(ss, method="splat")
    np.testing.assert_allclose(img[:, :16], 50.0, rtol=1e-12)
    np.testing.assert_allclose(img[:, 16:], 1e-3, rtol=1e-9)
    pap = mcrecon.reconstruct(ss, method=SplatMethod(variant="paper"))[:, 1:15]
    assert pap.max() > 51 and pap.min() < 49


# ----------------------------------------------------------------------------
# the guided footprint and the variant presets
# ----------------------------------------------------------------------------

def test_guided_footprint_matches_brute_force(rng):
    """Weights (1 - |x|^2) * guide at the covered centres (mirrored at the border), normalised per
    sample; a sample whose covered guide is all zero goes to its own pixel."""
    w, h = 9, 7
    n = 40
    pos = rng.random((n, 2)) * [w, h]
    val = rng.standard_normal((n, 3))
    rad = rng.uniform(0.6, 5, n)
    scale = rng.uniform(0.5, 2, n)
    guide = rng.random((h, w)) * (rng.random((h, w)) > 0.3)
    out = np.zeros((h, w, 3))
    _splat_guided_loop(pos, val, scale, rad, guide, 0, out)
    exp = np.zeros_like(out)
    for (x, y), v, r, s in zip(pos, val, rad, scale):
        pad = int(np.ceil(r)) + 2
        ii, jj = np.meshgrid(np.arange(-pad, w + pad), np.arange(-pad, h + pad))
        q = ((ii + 0.5 - x) ** 2 + (jj + 0.5 - y) ** 2) / r ** 2
        i2, j2 = ii % (2 * w), jj % (2 * h)
        i2 = np.where(i2 >= w, 2 * w - 1 - i2, i2)
        j2 = np.where(j2 >= h, 2 * h - 1 - j2, j2)
        k = np.where(q < 1, 1 - q, 0) * guide[j2, i2]
        if k.sum() == 0:
            exp[int(y), int(x)] += v * s
            continue
        np.add.at(exp, (j2.ravel(), i2.ravel()), (k.ravel() / k.sum())[:, None] * v * s)
    np.testing.assert_allclose(out, exp, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(out.sum((0, 1)), (val * scale[:, None]).sum(0), rtol=1e-12)
    one = np.zeros((h, w, 3))
    _splat_guided_loop(np.array([[4.5, 3.5]]), np.ones((1, 3)), np.ones(1), np.array([1.5]), np.zeros((h, w)),
                       0, one)
    assert one[3, 4].tolist() == [1.0, 1.0, 1.0] and one.sum() == 3.0


def test_variant_presets():
    rob, pap, out = SplatMethod(), SplatMethod(variant="paper"), SplatMethod(variant="outliers")
    assert (rob.params["variant"], rob.params["spread"], rob.params["guide"], rob.params["c"]) == \
        ("robust", "consistent", "local_mean", 2.0)
    assert (out.params["spread"], out.params["guide"], out.params["c"]) == ("outliers", "local_mean", 2.0)
    assert (pap.params["spread"], pap.params["guide"], pap.params["c"]) == ("all", "none", 4.0)
    assert SplatMethod(variant="paper", c=3).params["c"] == 3.0
    # paper variant == the plain Fig. 3 splatter (its defaults are the paper's)
    pos, val = uniform_samples("fireflies", 3, 0)
    sp = ProgressiveSplatter(W, W, 3)
    for p, v in _rank_rounds(pos, val, doubling_schedule(3)):
        sp.add_round(p, v)
    np.testing.assert_array_equal(
        mcrecon.reconstruct(mcrecon.SampleSet(pos, val, width=W, height=W), method=pap), sp.image)


def _rank_rounds(pos, val, schedule):
    pix = np.floor(pos[:, 1]).astype(int) * W + np.floor(pos[:, 0]).astype(int)
    order = np.argsort(pix, kind="stable")
    counts = np.bincount(pix)
    rank = np.empty(len(pix), int)
    rank[order] = np.arange(len(pix)) - np.repeat(np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
    lo = 0
    for n in schedule:
        sel = (rank >= lo) & (rank < lo + n)
        lo += n
        yield pos[sel], val[sel]


def test_robust_resume_and_offline_replay_exact(tmp_path):
    """An interrupted adaptive run resumes to the same image, and the log replays to it offline
    (round by round), with outliers actually spread."""
    from mcrecon.adaptive.run import resume
    r = renderer("fireflies", 4)
    full = adapt(r, "splat", spp=24, seed=4, log=tmp_path / "a.h5", track_error=False)
    assert sum(x["outliers"] for x in full.run.splatter.rounds) > 0
    adapt(r, "splat", spp=24, seed=4, log=tmp_path / "b.h5", max_rounds=2, track_error=False)
    np.testing.assert_array_equal(resume(tmp_path / "b.h5", r, track_error=False).image, full.image)
    np.testing.assert_array_equal(mcrecon.reconstruct(tmp_path / "a.h5", method="splat"), full.image)


@pytest.mark.parametrize("size", [(1, 1), (17, 1), (1, 17), (5, 3)])
def test_robust_guard_rails_small_films_spikes_signs(size, rng):
    """Tiny films, a 1e30 spike among zeros, negative samples: finite, energy exact, signs kept."""
    w, h = size
    pos = jittered_positions(np.full((h, w), 80), rng)
    val = np.where(rng.random((len(pos), 1)) < 0.02, 50.0, 1.0) * rng.standard_normal((len(pos), 3))
    val[0] = 1e30
    val[1:40] = 0.0
    img = mcrecon.reconstruct(mcrecon.SampleSet(pos, val, width=w, height=h), method="splat")
    st = PixelStats(w, h)
    st.add(pos, val)
    assert np.isfinite(img).all()
    np.testing.assert_allclose(img.sum((0, 1)), st.mean.sum((0, 1)), rtol=1e-9)


@pytest.mark.parametrize("scene", ["emitter", "fireflies"])
def test_fused_round_in_memory_is_bit_identical_to_the_streamed_round(scene):
    """``add_round`` (two fused passes, thresholds once per pixel) against ``add_round_stream`` (the
    per-sample window search; one chunk, as ``add_round`` was before: chunk boundaries order the
    additions differently): image, kernel widths and round records bit for bit, over doubling
    rounds with edge pixels, a pixel without samples and unsorted samples."""
    rng = np.random.default_rng(5)
    fused, streamed = ProgressiveSplatter(W, W, 3, **_ROBUST), ProgressiveSplatter(W, W, 3, **_ROBUST)
    for j, spp in enumerate(doubling_schedule(31)):
        counts = np.full((W, W), spp, np.int64)
        counts[3, 4] = 0 if j == 2 else spp  # a round that misses a pixel
        pos = jittered_positions(counts, rng)
        pos = pos[rng.permutation(len(pos))]  # not in pixel order
        val = scene_values(scene, pos, rng)
        with pytest.warns(McreconWarning) if j == 2 else contextlib.nullcontext():
            fused.add_round(pos, val, checked=j % 2 == 1)  # checked: the driver's committed rounds
            streamed.add_round_stream(lambda p=pos, v=val: iter([(p, v)]))
        np.testing.assert_array_equal(fused.image, streamed.image)
        np.testing.assert_array_equal(fused.last_widths, streamed.last_widths)
        assert fused.rounds == streamed.rounds
    assert scene != "fireflies" or sum(r["outliers"] for r in fused.rounds) > 0  # the split was exercised


# the fused pass serves spread="outliers" (initial_spp is the method's schedule, not the splatter's)
_ROBUST = {k: v for k, v in SplatMethod.variants["outliers"].items() if k != "initial_spp"}

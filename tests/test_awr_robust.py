"""Tests of ``awr``'s robust default (issue 12, item 4): the safeguard's formula and
the "never worse than the pixel mean of the same samples" property on scenes
built here, independent of the built-in ones the default was measured on.

The three procedural scenes (each sample = the radiance at a jittered film
position times a noise factor 0.5 + u, u ~ U(0, 1), so the pixel's expected
value is the box integral of the radiance, computed here by a 16 x 16
midpoint rule per pixel):

* ``emitter``: a disk of radius 2.7 px and radiance 1000 at a non-integer
  centre on a 1e-3 background (1e6 contrast, a rim of partially covered
  pixels with bimodal samples);
* ``step``: a diagonal HDR step edge, 0.02 on one side, 50 on the other;
* ``fireflies``: a smooth gradient 0.2 .. 1 in which each sample becomes
  a firefly of radiance 200 with probability 1e-3 (the reference is the
  expectation with them: 0.999 x gradient + 0.2).

Relative MSE, eps 0.01, as everywhere in mcrecon.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import mcrecon
from mcrecon.adaptive.run import adapt
from mcrecon.methods import get_method
from mcrecon.methods.awr import AWRMethod
from mcrecon.methods.awr.reconstruction import awr_reconstruct, log_domain_reconstruct, pixel_variance
from mcrecon.core.safeguard import confidence_clamp, sample_range_bounds
from mcrecon.core.metrics import output_sanity, relative_mse
from mcrecon.core.stats import PixelStats

from helpers import jittered_renderer

SIZE = 48
FIREFLY_P, FIREFLY_L = 1e-3, 200.0


def _radiance(scene, x, y):
    """Noise-free radiance at film position (x, y) in pixels, RGB."""
    if scene == "emitter":
        inside = (x - 20.3) ** 2 + (y - 26.6) ** 2 < 2.7 ** 2
        base = np.where(inside, 1000.0, 1e-3)
    elif scene == "step":
        base = np.where(x + 0.6 * y > 0.8 * SIZE + 0.37, 50.0, 0.02)
    elif scene == "fireflies":
        base = 0.2 + 0.8 * (x / SIZE) * (0.5 + 0.5 * np.sin(y / 7.0))
    else:
        raise ValueError(scene)
    return base[:, None] * np.array([1.0, 0.8, 0.6])


def _reference(scene):
    q = 16
    t = (np.arange(q) + 0.5) / q
    j, i, ty, tx = np.meshgrid(np.arange(SIZE), np.arange(SIZE), t, t, indexing="ij")
    r = _radiance(scene, (i + tx).ravel(), (j + ty).ravel()).reshape(SIZE, SIZE, q * q, 3).mean(axis=2)
    if scene == "fireflies":
        r = (1 - FIREFLY_P) * r + FIREFLY_P * FIREFLY_L * np.array([1.0, 0.8, 0.6])
    return r


def _renderer(scene, seed):
    """A procedural scene behind the renderer protocol (counts, then positions)."""
    def shade(pos, rng, req):
        val = _radiance(scene, pos[:, 0], pos[:, 1]) * (0.5 + rng.random((len(pos), 1)))
        if scene == "fireflies":
            hit = rng.random(len(pos)) < FIREFLY_P
            val[hit] = FIREFLY_L * np.array([1.0, 0.8, 0.6])   # a firefly replaces the sample
        return val
    return jittered_renderer(shade, width=SIZE, height=SIZE, name=f"test:{scene}",
                             stream=lambda req: [seed, req.round_index])


def _uniform_stats(scene, spp, seed):
    r = _renderer(scene, seed)
    from mcrecon.core.requests import SampleRequest
    b = r.render(SampleRequest(SIZE, SIZE, counts=np.full((SIZE, SIZE), spp, np.int64), round_index=0))
    return PixelStats.from_samples(b.positions, b.values, width=SIZE, height=SIZE)


# ------------------------------------------------------------------ formulas

def test_confidence_clamp_formula_analytic():
    """out = clip(image, max(mean - k se, lo), min(mean + k se, hi)), widened to contain mean."""
    mean = np.array([1.0, 1.0, 1.0, 5.0, 0.2, 3.0])
    var = np.array([0.25, 0.25, 0.0, 4.0, 1.0, 1.0])           # se 0.5, 0.5, 0, 2, 1, 1
    image = np.array([3.0, 0.9, 7.0, -2.0, -1.0, 9.0])
    lo = np.array([-np.inf, -np.inf, -np.inf, -np.inf, 0.0, 3.5])   # last: a lower bound above the mean
    hi = np.full(6, np.inf)
    out = confidence_clamp(image, mean, var, 2.0, lo, hi)
    # 3 -> 1 + 2*0.5; 0.9 inside; se = 0 keeps the mean; -2 -> 5 - 2*2;
    # -1 -> max(0.2 - 2, 0) = 0 (sample range: no negative); 9 -> 3 + 2*1 = 5 (the interval
    # [max(1, 3.5), 5] = [3.5, 5] excludes the mean 3: widened to [3, 5]) ...
    np.testing.assert_array_equal(out, [2.0, 0.9, 1.0, 1.0, 0.0, 5.0])
    # ... and an image value below it goes to the mean, not to 3.5
    assert confidence_clamp(np.array([0.0]), np.array([3.0]), np.array([1.0]), 2.0, np.array([3.5]))[0] == 3.0
    np.testing.assert_array_equal(confidence_clamp(image, mean, var, 0.0), mean)
    # an interval wider than every departure, without bounds, is the identity
    np.testing.assert_array_equal(confidence_clamp(image, mean, var + 100.0, 2.0), image)
    # compiled, it is the formula's numpy statement bit for bit (signed zeros, NaN of either sign and inf too)
    r = np.random.default_rng(3)
    image, mean, var = r.normal(size=(3, 40, 50, 3))
    var = np.abs(var)
    lo, hi = mean - r.random(mean.shape), mean + r.random(mean.shape)
    for a, vals in ((image, (-0.0, 0.0, np.nan, -np.nan, np.inf)), (mean, (-0.0, 0.0, np.nan)),
                    (var, (0.0, -0.0, -np.nan)), (lo, (-np.inf, 0.0, -0.0, np.nan)), (hi, (np.inf, -0.0, 0.0, -np.nan))):
        for x in vals:
            a[r.random(a.shape) < 0.05] = x
    for k in (0.0, 4.0):
        half = k * np.sqrt(np.maximum(var, 0.0))
        ref = np.clip(image, np.minimum(np.maximum(mean - half, lo), mean),
                      np.maximum(np.minimum(mean + half, hi), mean))
        got = confidence_clamp(image, mean, var, k, lo, hi)
        np.testing.assert_array_equal(got, ref)
        assert np.array_equal(np.signbit(got), np.signbit(ref))
        inplace = image.copy()
        confidence_clamp(inplace, mean, var, k, lo, hi, out=inplace)
        assert np.array_equal(np.signbit(inplace), np.signbit(ref)) and np.array_equal(inplace, ref, equal_nan=True)


def test_sample_range_bounds_and_log_domain_identities(rng):
    st = _uniform_stats("step", 4, 3)
    lo, hi = sample_range_bounds(st)
    # 3x3 neighbourhood extremes of the per-pixel sample range, by brute force at one pixel
    j, i = 10, 17
    assert lo[j, i, 0] == st.min[j - 1:j + 2, i - 1:i + 2, 0].min()
    assert hi[j, i, 1] == st.max[j - 1:j + 2, i - 1:i + 2, 1].max()
    # log domain: c_s = 0 gives the means back, and scaling radiance by s scales the result by s
    mean = np.exp(rng.normal(0, 3, (24, 28, 2)))
    var = mean ** 2 * rng.random((24, 28, 2))
    np.testing.assert_allclose(log_domain_reconstruct(mean, var, cs=0.0), mean, rtol=1e-12)
    a = log_domain_reconstruct(mean, var, levels=3)
    b = log_domain_reconstruct(1e4 * mean, 1e8 * var, levels=3)
    np.testing.assert_allclose(b, 1e4 * a, rtol=1e-7, atol=1e-9 * np.abs(b).max())
    # a signed channel stays in the linear domain (the paper's shrinkage)
    signed = mean.copy()
    signed[0, 0, 1] = -1.0
    out = log_domain_reconstruct(signed, var, levels=3)
    lin = awr_reconstruct(signed[..., 1:], var[..., 1:], levels=3)[..., 0]
    np.testing.assert_allclose(out[..., 1], lin, rtol=1e-7, atol=1e-9 * np.abs(lin).max())


def test_variants_preset_the_paper_and_explicit_options_win():
    paper = AWRMethod(variant="paper")
    assert (paper.params["variance"], paper.params["domain"], paper.params["safeguard"],
            paper.params["initial_spp"], paper.params["sampling_variance"]) == ("range", "linear", None, 4, "contrast")
    robust = AWRMethod()
    assert (robust.params["variant"], robust.params["variance"], robust.params["domain"],
            robust.params["safeguard"], robust.params["initial_spp"]) == ("robust", "sample", "log", 2.0, 16)
    assert AWRMethod(variant="paper", safeguard=2.0).params["safeguard"] == 2.0
    # paper variant = the paper's reconstruction, nothing else on top
    st = _uniform_stats("step", 8, 1)
    img = mcrecon.reconstruct(st, method=paper)
    np.testing.assert_array_equal(img, awr_reconstruct(st.mean, pixel_variance(st, "range")))


# ---------------------------------------------------- robust <= box, no negatives

SCENES = ["emitter", "step", "fireflies"]
SEEDS = list(range(11, 19))


@pytest.mark.parametrize("scene", SCENES)
def test_robust_offline_never_worse_than_box_and_no_negative_pixels(scene):
    """Offline, 48^2, 16 spp, 8 seeds: robust AWR / box of the same samples < 1 on average.

    Margin from the spread: the mean ratio over the seeds plus 2 standard
    errors of that mean must stay below 1.  Measured (seeds 11-18): emitter
    0.80 +- 0.087 (per seed 0.39 - 1.16: two seeds of this 1e6-contrast
    disk at 16 spp lose, see docs/methods/awr.md), step 0.77 +- 0.026,
    fireflies 0.287 +- 0.002; the paper's variant: 1e6x, 3e3x, 0.017x.
    Every output stays inside the range of the samples around it.
    """
    ref = _reference(scene)
    ratios, paper = [], []
    for seed in SEEDS:
        st = _uniform_stats(scene, 16, seed)
        box = relative_mse(st.mean, ref)
        img = mcrecon.reconstruct(st, method=AWRMethod())
        ratios.append(relative_mse(img, ref) / box)
        if seed in SEEDS[:2]:
            paper.append(relative_mse(mcrecon.reconstruct(st, method=AWRMethod(variant="paper")), ref) / box)
        sanity = output_sanity(img, st)
        assert sanity["negative_pixels"] == 0 and sanity["overshoot_pixels"] == 0 and sanity["nonfinite_pixels"] == 0
    r = np.array(ratios)
    print(f"\n{scene}: robust/box {np.round(r, 3)}, paper/box {np.round(paper, 3)}")
    assert r.mean() + 2 * r.std(ddof=1) / math.sqrt(len(r)) < 1.0, r


@pytest.mark.parametrize("scene, measured", [("emitter", 0.976), ("step", 0.678), ("fireflies", 0.090)])
def test_robust_adaptive_never_worse_than_uniform_box(scene, measured):
    """Adaptive robust AWR (its sampler + reconstruction) vs uniform box at equal
    spp (48^2, 32 spp), 2 seeds (one adaptive run costs ~1 s; the offline test
    above carries the seed statistics).  ``measured``: the larger ratio to box
    of the two seeds (emitter 0.976 and 0.553, step 0.678 and 0.486, fireflies
    0.069 and 0.090); each seed must stay below it + 15 % and below box."""
    ref = _reference(scene)
    for seed in SEEDS[:2]:
        box = relative_mse(_uniform_stats(scene, 32, seed).mean, ref)
        res = adapt(_renderer(scene, seed), get_method("awr"), spp=32, seed=seed, progress=False, track_error=False)
        assert int(res.counts.sum()) == 32 * SIZE * SIZE
        err = relative_mse(res.image, ref)
        print(f"\n{scene} seed {seed}: adaptive robust {err:.4g} vs uniform box {box:.4g} ({err / box:.3f})")
        assert err < min(1.0, 1.15 * measured) * box
        assert output_sanity(res.image, res.stats)["negative_pixels"] == 0

"""Tests of the built-in scenes (mcrecon.renderers.scenes).

The central property: each scene's closed-form ``expected`` is the mean
of its ``radiance`` over the random dimensions, and ``reference_image`` is
the pixel average of ``expected``.  Both are checked against Monte Carlo
with tolerances from the sample standard deviation (fixed seeds), so a
wrong penumbra, blur, time-overlap or probability formula fails.
"""

import numpy as np
import pytest

from mcrecon.errors import InputError
from mcrecon.renderers import scenes as S
from mcrecon.renderers.scenes import base as S_base
from mcrecon.renderers.scenes import catalog as S_catalog
from mcrecon.core.requests import SampleRequest, validate_reply
from mcrecon.core.samples import pixel_index

pytestmark = pytest.mark.filterwarnings("error")

NAMES = ["soft_shadow", "depth_of_field", "motion_blur", "caustic", "hdr", "flat", "checker_wall", "checker_spot",
         "checker_dof"]

# Tolerance in standard errors for a single comparison.  With ~3000
# comparisons per test a Gaussian |z| > 5.5 happens with probability
# 3000 * 3.8e-8 ~ 1e-4: a failure means a wrong formula, not bad luck.
Z_MAX = 5.5


def _z_check(samples, expected, *, extra_tol=0.0, rare=False):
    """Compare Monte Carlo means with expected values.

    samples : (K, n, C) n samples of K points (or pixels).
    Returns the z-scores |mean - expected| / se of the comparisons whose
    samples vary; where all n samples are equal (deterministic) the mean
    must equal expected to rounding.  ``extra_tol`` (K, C) is a
    deterministic error allowance (quadrature) subtracted from
    |mean - expected| before dividing.

    se is the sample standard error, except with ``rare=True``: when a
    value occurs rarely (a caustic hit, or a bright emitter clipping the
    corner of a pixel) the n samples may miss it and their spread says
    nothing about it.  Values are >= 0, so Var(L) <= E[L^2] <= sup(L) E[L]
    and se = max(sample se, sqrt(sup(L) E[L] / n)), sup(L) estimated by the
    batch's largest value (the peaks are sampled many times in a batch).
    Missing k of lambda expected rare hits then deviates by at most
    sqrt(lambda) bound-se units (large only where lambda >= 30 and missing
    hits is improbable); extra hits are seen by the sample se.
    """
    n = samples.shape[1]
    mean = samples.mean(axis=1)
    se = samples.std(axis=1, ddof=1) / np.sqrt(n)
    diff = np.abs(mean - expected)
    excess = (diff - np.broadcast_to(extra_tol, diff.shape)).clip(0)
    if rare:
        se = np.maximum(se, np.sqrt(samples.max() * np.abs(expected) / n))
        det = se == 0
    else:
        det = samples.max(axis=1) == samples.min(axis=1)
    assert np.all(excess[det] <= 1e-12 * (1.0 + np.abs(expected[det]))), \
        f"deterministic points differ by up to {excess[det].max() if det.any() else 0}"
    z = excess[~det] / se[~det]
    assert np.all(z < Z_MAX), f"max z = {z.max():.2f} at {np.argmax(z)}"
    return z


def test_scene_names_and_registry():
    assert S.scene_names() == NAMES
    assert list(S_catalog.SCENES) == NAMES
    for name in NAMES:
        sc = S.get_scene(name)
        assert isinstance(sc, S_catalog.Scene)
        assert sc.name == name
        assert tuple(sc.channels) == ("R", "G", "B")
        assert sc.n_dims >= 1 and sc.description
    sc = S.get_scene("hdr")
    assert S.get_scene(sc) is sc


def test_unknown_scene_lists_valid_names():
    with pytest.raises(InputError) as exc:
        S.get_scene("cornell")
    msg = str(exc.value)
    assert "cornell" in msg
    for name in NAMES:
        assert name in msg
    with pytest.raises(InputError):
        S.SceneRenderer("nope")
    with pytest.raises(InputError):
        S.reference_image("nope", 4, 4)


@pytest.mark.parametrize("name", NAMES)
def test_expected_is_mean_of_radiance(name):
    """E_u[radiance] == expected at fixed points (grid + random points).

    n_u = 3000 random-number rows per point; the z-score of each point
    mean uses the sample std of its 3000 values.  Beyond the per-point
    bound we check the aggregate: mean z^2 over k comparisons is 1 with
    standard deviation sqrt(2/k) for a correct formula; a bias of even a
    fraction of a standard error in many points moves it.
    """
    sc = S.get_scene(name)
    rng = np.random.default_rng(20261123)
    g = (np.arange(24) + 0.5) / 24
    gx, gy = np.meshgrid(g, g)
    px = np.concatenate([gx.ravel(), rng.random(300)])
    py = np.concatenate([gy.ravel(), rng.random(300)])
    n_u = 3000
    x = np.repeat(px, n_u)
    y = np.repeat(py, n_u)
    u = rng.random((x.size, sc.n_dims))
    v = sc.radiance(x, y, u).reshape(px.size, n_u, 3)
    assert v.dtype == np.float64 and np.isfinite(v).all()
    assert v.min() >= 0.0, "radiance must be non-negative"
    e = sc.expected(px, py)
    assert e.shape == (px.size, 3) and e.dtype == np.float64
    z = _z_check(v, e)
    if z.size > 30:
        # Sample-std z-scores are t-like; for heavy-tailed (caustic) or
        # bimodal values their second moment is still ~1 at n = 3000.
        k = z.size
        assert abs(np.mean(z ** 2) - 1.0) < 6.0 * np.sqrt(2.0 / k) + 0.05, np.mean(z ** 2)


@pytest.mark.parametrize("name", NAMES)
def test_reference_is_midpoint_rule_of_expected(name):
    """reference_image equals a brute-force midpoint average of expected()."""
    sc = S.get_scene(name)
    w, h, q = 5, 3, 6
    ref = S.reference_image(name, w, h, quadrature=q)
    assert ref.shape == (h, w, 3) and ref.dtype == np.float64
    brute = np.empty((h, w, 3))
    off = (np.arange(q) + 0.5) / q
    for j in range(h):
        for i in range(w):
            xx, yy = np.meshgrid((i + off) / w, (j + off) / h)
            brute[j, i] = sc.expected(xx.ravel(), yy.ravel()).mean(axis=0)
    np.testing.assert_allclose(ref, brute, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("name", NAMES)
def test_rendered_pixel_means_match_reference(name):
    """Pixel means of jittered samples agree with the reference image.

    8 x 8 pixels (each covers 1/8 of the film: lots of structure per
    pixel) at 2000 spp.  The reference's own quadrature error at q = 64 is
    bounded by |ref_16 - ref_64|: the midpoint rule's error falls at
    least like 1/q (discontinuities), so err_64 ~ err_16 / 4 and
    |ref_16 - ref_64| ~ 3 err_64 is a safe allowance.
    """
    w = h = 8
    spp = 2000
    batch = S.render_uniform(name, width=w, height=h, spp=spp, seed=3)
    idx = pixel_index(batch.positions, w)
    order = np.argsort(idx, kind="stable")
    vals = batch.values[order].reshape(h * w, spp, 3)
    ref64 = S.reference_image(name, w, h, quadrature=64).reshape(h * w, 3)
    ref16 = S.reference_image(name, w, h, quadrature=16).reshape(h * w, 3)
    _z_check(vals, ref64, extra_tol=np.abs(ref16 - ref64) + 1e-12, rare=True)


def test_reference_default_size_finite_and_cached():
    for name in NAMES:
        ref = S.reference_image(name, 64, 64)
        assert ref.shape == (64, 64, 3)
        assert np.isfinite(ref).all() and ref.min() >= 0.0
        ref[0, 0, 0] = -1.0  # a copy: must not poison the cache
        again = S.reference_image(name, 64, 64)
        assert again[0, 0, 0] != -1.0
        assert again.flags.writeable


def test_reference_quadrature_converges():
    # At q = 32 the reference differs from q = 128 by at most jump / (2 q)
    # per discontinuity crossing a pixel; for the [0, 1]-range scenes the
    # jumps are < 1.2, so 2 crossings give 1.2 / 32 = 0.0375 at most.
    for name in ["soft_shadow", "depth_of_field", "motion_blur"]:
        a = S.reference_image(name, 16, 16, quadrature=32)
        b = S.reference_image(name, 16, 16, quadrature=128)
        assert np.abs(a - b).max() < 1.2 / 32


def test_soft_shadow_has_sharp_edges_and_soft_penumbra():
    sc = S.get_scene("soft_shadow")
    # A checker edge at x = 0.9 (10 squares) in the lit region, far from
    # both shadows: the expectation jumps by the full albedo contrast.
    y = np.array([0.05, 0.05])
    x = np.array([0.9 - 1e-9, 0.9 + 1e-9])
    e = sc.expected(x, y)
    lit = (S_catalog._SS_AMBIENT + S_catalog._SS_LIGHT)
    np.testing.assert_allclose(np.abs(e[0] - e[1]), np.abs(S_catalog._SS_A0 - S_catalog._SS_A1) * lit, rtol=1e-12)
    # Across the left edge a = 0.12 of occluder 1's shadow (at y = 0.25,
    # well inside its y range): fully lit where x + w(x)/2 < a, umbra where
    # x - w(x)/2 > a, exactly half visible at x = a, monotone in between.
    a = 0.12
    x_lit = (a - 0.005 - 1e-9) / 1.055      # x + (0.01 + 0.11 x)/2 = a - 1e-9
    x_umbra = (a + 0.005 + 1e-9) / 0.945    # x - (0.01 + 0.11 x)/2 = a + 1e-9
    xs = np.sort(np.append(np.linspace(x_lit, x_umbra, 41), a))
    assert S_base._checker(x_lit, 0.25, 10.0) == S_base._checker(x_umbra, 0.25, 10.0)  # one albedo cell
    ev = sc.expected(xs, np.full(xs.size, 0.25))[:, 0]
    alb = S_catalog._SS_A0[0] if S_base._checker(a, 0.25, 10.0) == 0 else S_catalog._SS_A1[0]
    vis = (ev / alb - S_catalog._SS_AMBIENT) / S_catalog._SS_LIGHT[0]
    assert vis[0] == pytest.approx(1.0, abs=1e-12) and vis[-1] == pytest.approx(0.0, abs=1e-12)
    assert vis[xs == a][0] == pytest.approx(0.5, abs=1e-12)
    assert np.all(np.diff(vis) < 0)
    assert S_catalog.SoftShadowScene.penumbra_width(1.0) * 128 == pytest.approx(15.36)


def test_depth_of_field_blur_range():
    sc = S.get_scene("depth_of_field")
    R = S_catalog.DepthOfFieldScene.blur_width
    assert R(0.5) == 0.0 and R(0.6) == 0.0
    assert R(0.0) * 128 == pytest.approx(8.0)
    # In focus, samples are deterministic: the texture itself.
    x = np.linspace(0.01, 0.99, 50)
    y = np.full(50, 0.5)
    a = sc.radiance(x, y, np.zeros((50, 2)))
    b = sc.radiance(x, y, np.full((50, 2), 0.999))
    np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(sc.expected(x, y), a, rtol=1e-12)


def test_dof_box_averages_match_quadrature():
    # The antiderivative formulas against a dense midpoint average in s.
    z, width = 0.437, 0.09
    s = z + width * ((np.arange(200000) + 0.5) / 200000 - 0.5)
    sq = np.where((6 * s) % 1.0 < 0.5, 1.0, -1.0).mean()
    assert S_base._box_square_wave(z, 6.0, width) == pytest.approx(sq, abs=1e-4)
    s2 = z + width * ((np.arange(4000) + 0.5) / 4000 - 0.5)
    wv = np.array([S_base._wave(3 * t + 1 / 3) for t in s2]).mean()
    assert S_base._box_wave(z, 3.0, 1 / 3, width) == pytest.approx(wv, abs=1e-5)


def test_motion_blur_objects_never_overlap():
    boxes = S_catalog.MotionBlurScene.swept_boxes()
    for i in range(len(boxes)):
        for j in range(i):
            a, b = boxes[i], boxes[j]
            assert not (a[0] < b[1] and b[0] < a[1] and a[2] < b[3] and b[2] < a[3])
    # A point swept by the red square for exactly part of the shutter:
    # square [0.05 + 0.35 t, 0.23 + 0.35 t) covers x = 0.3 for t in (0.2, 0.714].
    sc = S.get_scene("motion_blur")
    e = sc.expected([0.3], [0.15])[0]
    frac = (0.25 / 0.35) - (0.07 / 0.35)
    b = S_catalog._MB_BACKGROUND * (0.55 + 0.45 * S_base._checker(0.3, 0.15, 16.0))
    np.testing.assert_allclose(e, b + frac * (S_catalog._MB_OBJECTS[0, 6:9] - b), rtol=1e-12)


def test_caustic_zero_fraction_and_rare_huge_samples():
    sc = S.get_scene("caustic")
    rng = np.random.default_rng(7)
    n = 200_000
    # Points inside the ring's glow, well above the table: every sample is
    # zero unless u1 < p.  Binomial sd of the zero fraction:
    # sqrt(0.97 * 0.03 / n) = 3.8e-4; 5 sd = 1.9e-3.
    ang = rng.random(n) * 2 * np.pi
    rad = 0.1 * np.sqrt(rng.random(n))
    x = 0.5 + rad * np.cos(ang)
    y = 0.45 + rad * np.sin(ang)
    v = sc.radiance(x, y, rng.random((n, 2)))
    zero = np.all(v == 0.0, axis=1)
    assert abs(zero.mean() - 0.97) < 5 * np.sqrt(0.97 * 0.03 / n)
    assert (sc.expected(x, y) > 0).all()
    # Above the table a non-zero sample is exactly C / p: p times it is the
    # expectation (this pins p, which the 10 %-relative Monte Carlo error of
    # a 3 % event cannot resolve).
    np.testing.assert_allclose(v[~zero] * 0.03, sc.expected(x[~zero], y[~zero]), rtol=1e-12)
    # Over a whole rendered film, above the table: >= 97% zeros (each sample
    # is zero with probability >= 0.97; sd of the fraction <= 3.8e-4 here).
    b = S.render_uniform("caustic", width=64, height=64, spp=64, seed=1)
    above = b.positions[:, 1] < 0.85 * 64
    frac = np.all(b.values[above] == 0.0, axis=1).mean()
    assert frac > 0.97 - 5 * np.sqrt(0.97 * 0.03 / above.sum())
    # Rare samples are huge: the ring's peak (<= 4.5) divided by p = 0.03.
    assert b.values.max() > 100.0
    ref = S.reference_image("caustic", 64, 64)
    assert b.values.max() / ref.max() > 20.0


def test_hdr_dynamic_range_and_bimodal_rim():
    ref = S.reference_image("hdr", 128, 128)
    assert ref.max() >= 400.0
    assert ref.min() > 0.0 and ref.min() < 2e-3
    assert ref.max() / ref.min() >= 1e5
    # Mid-level region ~0.5.
    mid = ref[:, int(0.7 * 128):, 0]
    assert 0.3 < mid.mean() < 0.6
    # A pixel on the emitter's rim sees both ~500 and dim values.
    cx, cy, r = S_catalog.HDRScene.emitter
    px, py = int((cx + r) * 128), int(cy * 128)
    counts = np.zeros((128, 128), np.int64)
    counts[py, px] = 400
    rnd = S.SceneRenderer("hdr", seed=5).render(SampleRequest(128, 128, counts=counts))
    lum = rnd.values[:, 0]
    assert (lum > 100).any() and (lum < 0.1).any()


def test_flat_noise_mean_and_variance():
    b = S.render_uniform("flat", width=64, height=64, spp=64, seed=2)
    v = b.values
    n = v.shape[0]
    # U[0, 1): mean 1/2 (sd 1/sqrt(12 n)), variance 1/12 (sd of the sample
    # variance sqrt((mu4 - sigma^4) / n) with mu4 = 1/80).
    assert np.all(np.abs(v.mean(axis=0) - 0.5) < 5 / np.sqrt(12 * n))
    assert np.all(np.abs(v.var(axis=0, ddof=1) - 1 / 12) < 5 * np.sqrt((1 / 80 - 1 / 144) / n))
    assert v.min() >= 0.0 and v.max() < 1.0
    np.testing.assert_array_equal(S.reference_image("flat", 3, 2), np.full((2, 3, 3), 0.5))


def test_renderer_determinism_and_seeds():
    r = S.SceneRenderer("soft_shadow", width=16, height=12, seed=4)
    counts = np.random.default_rng(0).integers(0, 5, (12, 16))
    req = SampleRequest(16, 12, counts=counts, round_index=2, seed=9)
    a, b = r.render(req), r.render(req)
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.values, b.values)
    c = S.SceneRenderer("soft_shadow", width=16, height=12, seed=4).render(req)
    np.testing.assert_array_equal(a.values, c.values)
    for other in (SampleRequest(16, 12, counts=counts, round_index=3, seed=9),
                  SampleRequest(16, 12, counts=counts, round_index=2, seed=10)):
        assert not np.array_equal(r.render(other).positions, a.positions)
    d = S.SceneRenderer("soft_shadow", width=16, height=12, seed=5).render(req)
    assert not np.array_equal(d.positions, a.positions)


@pytest.mark.parametrize("name", NAMES)
def test_counts_honoured(name):
    w, h = 13, 11
    counts = np.random.default_rng(1).integers(0, 6, (h, w))
    counts[0, 0] = 0
    r = S.SceneRenderer(name, width=w, height=h)
    req = SampleRequest(w, h, counts=counts, seed=1)
    b = r.render(req)
    assert b.values.shape == (counts.sum(), 3) and b.values.dtype == np.float64
    assert np.isfinite(b.values).all()
    got = np.bincount(pixel_index(b.positions, w), minlength=w * h).reshape(h, w)
    np.testing.assert_array_equal(got, counts)
    validate_reply(req, b, n_channels=3, renderer=r.name)


def test_explicit_positions_answered_in_order():
    # Where samples are deterministic (lit region right of both shadows in
    # soft_shadow; the in-focus band of depth_of_field) each answered value
    # must be the radiance at *its* requested position.
    w, h = 64, 48
    rng = np.random.default_rng(3)
    m = 200
    for name, xs, ys in (("soft_shadow", (0.95 + 0.05 * rng.random(m)) * w, rng.random(m) * h),
                         ("depth_of_field", rng.random(m) * w, (0.42 + 0.16 * rng.random(m)) * h)):
        pos = np.stack([np.minimum(xs, w - 1e-9), ys], axis=1)
        counts = np.ones((h, w), np.int64)
        req = SampleRequest(w, h, counts=counts, positions=pos, seed=2)
        b = S.SceneRenderer(name, width=w, height=h).render(req)
        assert len(b) == w * h + m
        np.testing.assert_array_equal(b.positions[w * h:], pos)
        sc = S.get_scene(name)
        e = sc.expected(pos[:, 0] / w, pos[:, 1] / h)
        np.testing.assert_allclose(b.values[w * h:], e, rtol=1e-12)
        # Values differ along the list, so any other order would fail.
        assert not np.allclose(b.values[w * h:], e[::-1])
        validate_reply(req, b, n_channels=3)
    # Positions only.
    req = SampleRequest(w, h, positions=pos[:5])
    b = S.SceneRenderer("flat", width=w, height=h).render(req)
    np.testing.assert_array_equal(b.positions, pos[:5])


@pytest.mark.parametrize("size", [(1, 1), (1, 7), (7, 1), (13, 11)])
@pytest.mark.parametrize("name", NAMES)
def test_tiny_films(name, size):
    w, h = size
    b = S.render_uniform(name, width=w, height=h, spp=3, seed=0)
    assert b.values.shape == (3 * w * h, 3) and np.isfinite(b.values).all()
    assert (b.positions[:, 0] < w).all() and (b.positions[:, 1] < h).all()
    ref = S.reference_image(name, w, h, quadrature=4)
    assert ref.shape == (h, w, 3) and np.isfinite(ref).all()


def test_bad_arguments():
    with pytest.raises(InputError, match="width"):
        S.SceneRenderer("flat", width=0)
    with pytest.raises(InputError, match="seed"):
        S.SceneRenderer("flat", seed=-1)
    with pytest.raises(InputError, match="spp"):
        S.render_uniform("flat", width=4, height=4, spp=0)
    with pytest.raises(InputError, match="quadrature"):
        S.reference_image("flat", 4, 4, quadrature=0)
    with pytest.raises(InputError, match="height"):
        S.reference_image("flat", 4, 2.5)
    r = S.SceneRenderer("flat", width=4, height=4)
    with pytest.raises(InputError, match="width/height"):
        r.render(SampleRequest(5, 4, counts=np.ones((4, 5), np.int64)))
    with pytest.raises(InputError, match="u"):
        S.get_scene("hdr").radiance([0.5], [0.5], np.zeros((1, 2)))


def test_write_scene_log_round_trip(tmp_path):
    from mcrecon.io import read_log

    p = S.write_scene_log("caustic", tmp_path / "c.h5", width=9, height=7, spp=5, seed=11)
    log = read_log(p)
    assert (log.width, log.height) == (9, 7)
    assert tuple(log.channels) == ("R", "G", "B")
    assert log.n_samples == 9 * 7 * 5
    assert log.metadata["renderer"] == "mcrecon.scenes"
    assert log.metadata["scene"] == "caustic"
    assert log.metadata["seed"] == 11
    assert log.metadata["settings"]["spp"] == 5
    np.testing.assert_array_equal(log.reference(), S.reference_image("caustic", 9, 7))
    chunk = log.read_all()
    b = S.render_uniform("caustic", width=9, height=7, spp=5, seed=11)
    np.testing.assert_array_equal(chunk.values, b.values.astype(np.float32))  # scene logs are float32
    np.testing.assert_allclose(np.asarray(chunk.positions, np.float64), b.positions, rtol=1e-6)
    p2 = S.write_scene_log("flat", tmp_path / "f.h5", width=3, height=2, spp=1, reference=False)
    assert not read_log(p2).has_reference


class _Ramp(S_catalog.Scene):
    """A user-defined numpy scene: L = (x + u, y, x y), E = (x + 1/2, y, x y)."""

    name = "ramp"
    n_dims = 1

    def _radiance(self, x, y, u):
        return np.stack([x + u[:, 0], y, x * y], axis=1)

    def _expected(self, x, y):
        return np.stack([x + 0.5, y, x * y], axis=1)


def test_user_scene_and_empty_requests():
    sc = _Ramp()
    # The midpoint rule is exact for the bilinear expectation: pixel centres.
    ref = S.reference_image(sc, 5, 3, quadrature=3)
    cx = (np.arange(5) + 0.5) / 5
    cy = (np.arange(3) + 0.5) / 3
    np.testing.assert_allclose(ref[..., 0], np.broadcast_to(cx + 0.5, (3, 5)), rtol=1e-12)
    np.testing.assert_allclose(ref[..., 2], np.outer(cy, cx), rtol=1e-12)
    b = S.SceneRenderer(sc, width=5, height=3).render(SampleRequest(5, 3, counts=np.ones((3, 5), np.int64)))
    assert b.values.shape == (15, 3)
    with pytest.raises(NotImplementedError):
        S_catalog.Scene().expected([0.5], [0.5])
    # A request for no samples gets an empty, well-shaped reply.
    for name in NAMES:
        r = S.SceneRenderer(name, width=4, height=3)
        b = r.render(SampleRequest(4, 3, counts=np.zeros((3, 4), np.int64)))
        assert b.positions.shape == (0, 2) and b.values.shape == (0, 3)

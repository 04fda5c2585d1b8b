"""Per-sample features of the built-in scenes and the textured scenes (checker_wall, checker_dof).

What is checked, each against something independent of the code under test:

* the features' Monte Carlo means over the random dimensions converge to
  ``expected_features`` (fixed points, z-scores from the sample spread) and
  their per-pixel means to ``feature_reference`` (jittered samples through
  :class:`PixelStats`, the quadrature error bounded as in test_scenes);
* ``feature_reference`` is the midpoint rule of ``expected_features``;
* the textured scenes' colour is albedo x shading sample by sample, and
  their reference's texture edges are sharp where the scene is in focus and
  blurred exactly where it is not;
* the older scenes' default outputs are bit-identical to those of commit
  c0d503a (digests computed there), and turning features on changes no
  colour bit;
* renderer replies carry features row by row, logs round-trip them, the CLI
  writes and lists them.
"""

import hashlib
import json

import numpy as np
import pytest

from mcrecon.core.requests import SampleRequest, validate_reply
from mcrecon.core.stats import PixelStats
from mcrecon.errors import InputError
from mcrecon.io import read_log
from mcrecon.renderers import scenes as S
from mcrecon.renderers.scenes import catalog as S_catalog
from mcrecon.renderers.scenes import textured as S_tex

pytestmark = pytest.mark.filterwarnings("error")

OLD = ["soft_shadow", "depth_of_field", "motion_blur", "caustic", "hdr", "flat"]
TEXTURED = ["checker_wall", "checker_spot", "checker_dof"]
ALL = OLD + TEXTURED
LAYOUT = {"albedo": 3, "normal": 3, "depth": 1}
# as in test_scenes: ~4000 comparisons per test, a Gaussian |z| > 5.5 has probability ~1e-4 overall
Z_MAX = 5.5


def _stack(feats):
    return np.concatenate([feats[k] for k in LAYOUT], axis=-1)


def _z_check(samples, expected, extra_tol=0.0):
    """|mean - expected| (less a deterministic allowance) in standard errors.

    The standard error is the samples' own, floored at range / n (range:
    of that component over the whole batch): an event of probability p
    that n samples all miss (likely only for p < ~3/n) shifts the mean by
    at most p * range < 3 range / n without showing in the spread.  Where
    nothing is random the floor alone makes the check near-exact.
    """
    n = samples.shape[1]
    mean = samples.mean(axis=1)
    span = samples.max(axis=(0, 1)) - samples.min(axis=(0, 1))
    raw = samples.std(axis=1, ddof=1) / np.sqrt(n)
    floor = np.maximum(span, 1e-9) / n
    excess = (np.abs(mean - expected) - extra_tol).clip(0)
    z = excess / np.maximum(raw, floor)
    assert np.all(z < Z_MAX), f"max z {z.max():.2f} at {np.unravel_index(np.argmax(z), z.shape)}"
    # the z-scores of well-sampled comparisons (the floor would bias their spread), for aggregate checks
    return z[raw > 3.0 * floor]


@pytest.mark.parametrize("name", ALL)
def test_feature_means_are_expected_features(name):
    """Mean of features(x, y, u) over 1000 u rows at 300 fixed points == expected_features(x, y)."""
    sc = S.get_scene(name)
    assert sc.feature_names == ("albedo", "normal", "depth")
    rng = np.random.default_rng(20261202)
    g = (np.arange(12) + 0.5) / 12
    gx, gy = np.meshgrid(g, g)
    px = np.concatenate([gx.ravel(), rng.random(156)])
    py = np.concatenate([gy.ravel(), rng.random(156)])
    n_u = 1000
    x, y = np.repeat(px, n_u), np.repeat(py, n_u)
    u = rng.random((x.size, sc.n_dims))
    f = sc.features(x, y, u)
    assert {k: v.shape for k, v in f.items()} == {k: (x.size, n) for k, n in LAYOUT.items()}
    samples = _stack(f).reshape(px.size, n_u, 7)
    e = _stack(sc.expected_features(px, py))
    z = _z_check(samples, e)
    # unit normals per sample; albedo in [0, 1]; depth > 0
    np.testing.assert_allclose(np.linalg.norm(f["normal"], axis=1), 1.0, rtol=1e-12)
    assert f["albedo"].min() >= 0.0 and f["albedo"].max() <= 1.0 and f["depth"].min() > 0.0
    if z.size > 30:
        assert abs(np.mean(z ** 2) - 1.0) < 6.0 * np.sqrt(2.0 / z.size) + 0.05, np.mean(z ** 2)
    if name in ("depth_of_field", "motion_blur", "checker_dof"):
        assert z.size > 60, "the lens / shutter must make the features of some points random"


@pytest.mark.parametrize("name", ALL)
def test_feature_reference_is_midpoint_rule(name):
    sc = S.get_scene(name)
    w, h, q = 5, 3, 6
    ref = S.feature_reference(name, w, h, quadrature=q)
    assert {k: v.shape for k, v in ref.items()} == {k: (h, w, n) for k, n in LAYOUT.items()}
    off = (np.arange(q) + 0.5) / q
    for j in range(h):
        for i in range(w):
            xx, yy = np.meshgrid((i + off) / w, (j + off) / h)
            brute = _stack(sc.expected_features(xx.ravel(), yy.ravel())).mean(axis=0)
            np.testing.assert_allclose(_stack(ref)[j, i], brute, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("name", ["motion_blur", "checker_wall", "checker_dof"])
def test_pixel_feature_means_converge_to_reference(name):
    """Per-pixel feature means (PixelStats, 8x8 pixels, 1500 jittered spp) == feature_reference.

    The reference's own quadrature error at q = 64 is allowed for by
    |ref_16 - ref_64| (the midpoint rule's error falls at least like 1/q).
    """
    w = h = 8
    spp = 1500
    b = S.render_uniform(name, width=w, height=h, spp=spp, seed=4, features=True)
    st = PixelStats.from_samples(b.positions, b.values, width=w, height=h, features=b.features)
    for fname in LAYOUT:
        np.testing.assert_array_equal(st.features[fname].count, spp)
    order = np.argsort(np.floor(b.positions[:, 1]) * w + np.floor(b.positions[:, 0]), kind="stable")
    samples = _stack(b.features)[order].reshape(h * w, spp, 7)
    # the statistics' means are those of the samples
    np.testing.assert_allclose(_stack({k: st.features[k].mean for k in LAYOUT}).reshape(h * w, 7),
                               samples.mean(axis=1), rtol=1e-10, atol=1e-12)
    r64 = _stack(S.feature_reference(name, w, h, quadrature=64)).reshape(h * w, 7)
    r16 = _stack(S.feature_reference(name, w, h, quadrature=16)).reshape(h * w, 7)
    _z_check(samples, r64, extra_tol=np.abs(r16 - r64) + 1e-12)


@pytest.mark.parametrize("name", TEXTURED)
def test_textured_colour_reference_against_monte_carlo(name):
    """Pixel means of 3000 spp at 6x6 against the colour reference, z from the standard error."""
    w = h = 6
    spp = 3000
    b = S.render_uniform(name, width=w, height=h, spp=spp, seed=9)
    order = np.argsort(np.floor(b.positions[:, 1]) * w + np.floor(b.positions[:, 0]), kind="stable")
    vals = b.values[order].reshape(h * w, spp, 3)
    r64 = S.reference_image(name, w, h, quadrature=64).reshape(h * w, 3)
    r16 = S.reference_image(name, w, h, quadrature=16).reshape(h * w, 3)
    _z_check(vals, r64, extra_tol=np.abs(r16 - r64) + 1e-12)


def test_textured_colour_is_albedo_times_shading():
    """Sample by sample: colour / albedo is one scalar per sample (grey shading) for checker_dof, and
    albedo x (sky 2 k u3 + light l V) for checker_wall, with V in {0, 1}."""
    rng = np.random.default_rng(5)
    n = 20000
    x, y = rng.random(n), rng.random(n)
    sc = S.get_scene("checker_dof")
    u = rng.random((n, 3))
    col, f = sc.radiance(x, y, u), sc.features(x, y, u)
    ratio = col / f["albedo"]
    np.testing.assert_allclose(ratio, ratio[:, :1] * np.ones(3), rtol=1e-12)
    e = {p[0]: p[13] for p in S_tex._CD_PLANES}          # depth -> irradiance of that plane
    expect = np.array([e[d] for d in f["depth"][:, 0]]) * (0.5 + u[:, 2])
    np.testing.assert_allclose(ratio[:, 0], expect, rtol=1e-12)
    sc = S.get_scene("checker_wall")
    col, f = sc.radiance(x, y, u), sc.features(x, y, u)
    shade = col / f["albedo"] - S_tex._CW_SKY * 2.0 * u[:, 2:3]
    vis = shade / S_tex._CW_LIGHT
    assert np.all((np.abs(vis) < 1e-12) | (np.abs(vis - 1.0) < 1e-12))
    assert 0.05 < np.mean(vis < 0.5) < 0.5, "the occluder must shadow part of the wall"


def test_random_features_belong_to_their_sample():
    """Where features are random (lens, shutter) they are those of the sample's own hit, not merely right
    on average: depth_of_field's colour is 1.25 x albedo and its depth that of the lens ray's row t;
    motion_blur's colour is its albedo and its depth the wall's exactly where no object covers it."""
    rng = np.random.default_rng(12)
    n = 20000
    x, y = rng.random(n), rng.random(n)
    u = rng.random((n, 2))
    sc = S.get_scene("depth_of_field")
    col, f = sc.radiance(x, y, u), sc.features(x, y, u)
    np.testing.assert_allclose(col, 1.25 * f["albedo"], rtol=1e-12)
    t = y + S_catalog.DepthOfFieldScene.blur_width(y) * (u[:, 1] - 0.5)
    np.testing.assert_allclose(f["depth"][:, 0], 2.0 + 2.0 * (t - 0.5), rtol=1e-12)
    sc = S.get_scene("motion_blur")
    col, f = sc.radiance(x, y, u[:, :1]), sc.features(x, y, u[:, :1])
    np.testing.assert_array_equal(col, f["albedo"])
    wall = f["depth"][:, 0] == 3.0
    bg = S_catalog._MB_BACKGROUND * (0.55 + 0.45 * ((np.floor(16 * x) + np.floor(16 * y)) % 2))[:, None]
    np.testing.assert_allclose(col[wall], bg[wall], rtol=1e-12)
    assert np.all(np.abs(col[~wall] - bg[~wall]).max(axis=1) > 0) and 0.02 < np.mean(~wall) < 0.5


def test_checker_spot_small_light_is_rare_and_huge():
    """checker_spot: colour / albedo - sky is 0 or l f V / p sample by sample, the light found with
    probability p (binomial: 5 standard deviations), and its texture (features) is checker_wall's."""
    rng = np.random.default_rng(8)
    n = 40000
    x, y = rng.random(n), rng.random(n)
    u = rng.random((n, 4))
    sc = S.get_scene("checker_spot")
    col, f = sc.radiance(x, y, u), sc.features(x, y, u)
    light = col / f["albedo"] - S_tex._CS_SKY * 2.0 * u[:, 3:4]
    fall = 1.0 / (1.0 + ((x - S_tex._CS_CX) ** 2 + (y - S_tex._CS_CY) ** 2) / S_tex._CS_S2)
    on = light[:, 0] > 1e-9
    np.testing.assert_allclose(light[on], S_tex._CS_LIGHT * fall[on, None] / S_tex._CS_P, rtol=1e-12)
    assert np.all(np.abs(light[~on]) < 1e-12)
    assert np.all(u[on, 0] < S_tex._CS_P)          # only light-finding samples carry the light
    p = S_tex._CS_P
    hit = np.mean(u[:, 0] < p)
    assert abs(np.mean(on) - hit) <= hit and abs(hit - p) < 5 * np.sqrt(p * (1 - p) / n)
    assert col.max() > 10 * sc.expected(x, y).mean(), "rare samples must be much larger than the mean"
    for k in LAYOUT:
        np.testing.assert_array_equal(S.feature_reference("checker_spot", 32, 32)[k],
                                      S.feature_reference("checker_wall", 32, 32)[k])


def test_checker_wall_texture_is_sharp_in_the_reference():
    """At 128 px the squares are pixel-aligned: across every square edge outside the penumbra the
    reference jumps by the full albedo contrast times the shading, with no intermediate pixel."""
    ref = S.reference_image("checker_wall", 128, 128, quadrature=8)
    alb = S.feature_reference("checker_wall", 128, 128, quadrature=8)["albedo"]
    a0, a1 = S_tex._CW_COARSE_ALBEDO
    lit = S_tex._CW_SKY + S_tex._CW_LIGHT
    # row 8 (y ~ 0.07) is lit everywhere (the shadow starts at y = 0.28 minus at most 7.5 px of penumbra)
    row = ref[8, :64]
    squares = (np.arange(64) // 16) % 2      # row 8 is in the first square row: A0 at columns 0-15
    np.testing.assert_allclose(row, np.where(squares[:, None] == 0, a0, a1) * lit, rtol=1e-12)
    np.testing.assert_allclose(alb[8, :64], np.where(squares[:, None] == 0, a0, a1), rtol=1e-12)
    # the fine quadrant (x, y >= 1/2): 4-px squares, also exact per pixel, in the lit rows 110-127
    b0, b1 = S_tex._CW_FINE_ALBEDO
    fine = ((np.arange(64, 128)[None, :] // 4) + (np.arange(110, 128)[:, None] // 4)) % 2
    np.testing.assert_allclose(alb[110:, 64:], np.where(fine[..., None] == 0, b0, b1), rtol=1e-12)
    np.testing.assert_allclose(ref[110:, 64:], alb[110:, 64:] * lit, rtol=1e-12)
    # the shadow is soft: colour / albedo (the shading) changes by < 0.8 / 2.6 px per pixel in the penumbra
    shade = (ref / alb)[:, :, 0]
    assert shade.min() == pytest.approx(S_tex._CW_SKY, abs=1e-12)       # the umbra sees only the sky
    assert np.abs(np.diff(shade, axis=1)).max() < S_tex._CW_LIGHT[0] / 2.0


def test_checker_dof_sharp_in_focus_blurred_off_focus():
    """The card in focus keeps exact pixel-aligned 4-px squares; the near card's 8-px squares are blurred
    by its 8-px square aperture image: no pixel pair jumps by the full contrast there."""
    ref = S.reference_image("checker_dof", 128, 128, quadrature=8)   # enough: the checks are per-pixel exact or loose
    alb = S.feature_reference("checker_dof", 128, 128, quadrature=8)
    p_near, p_mid, p_wall = S_tex._CD_PLANES
    # mid card: columns 60..115, rows 4..50 (inside [13/32, 30/32] x [2/32, 17/32], away from the near
    # card's blur, which ends at x = 15/32 + 1/32 -> column 64, y >= 14/32 - 1/32 -> row 52)
    a0, a1 = p_mid[7:10], p_mid[10:13]
    cols, rows = np.arange(68, 116), np.arange(12, 50)
    chk = ((cols[None, :] // 4) + (rows[:, None] // 4)) % 2
    np.testing.assert_allclose(alb["albedo"][12:50, 68:116], np.where(chk[..., None] == 0, a0, a1), rtol=1e-12)
    np.testing.assert_allclose(ref[12:50, 68:116], p_mid[13] * alb["albedo"][12:50, 68:116], rtol=1e-12)
    np.testing.assert_allclose(alb["depth"][12:50, 68:116], 2.0, rtol=1e-12)
    # near card interior (rows 70..110, columns 16..50): blurred over 8 px, so adjacent pixels differ by at
    # most ~1/8 of the contrast (+ quadrature), never the full jump; its depth is exactly 1 there
    near = ref[70:110, 16:50]
    jump = np.abs(p_near[10:13] - p_near[7:10]) * p_near[13]
    assert np.abs(np.diff(near, axis=1)).max() < 0.2 * jump.max()
    assert np.ptp(near[..., 2]) > 0.5 * jump[2], "blurred, not averaged away"
    np.testing.assert_allclose(alb["depth"][70:110, 16:50], 1.0, rtol=1e-12)
    # at the near card's edge over the wall the depth feature is blurred: fractional hit probability
    d = alb["depth"][90, 0:16, 0]
    assert d[0] == pytest.approx(3.0) and 1.0 < d[8] < 3.0 and d[15] == pytest.approx(1.0)


# digests of (render_uniform 12x10 3 spp seed 7, a SceneRenderer reply with counts and positions, the
# reference at q = 8, a written log's positions/values/reference/metadata), computed with commit c0d503a
# (before scenes had features) by the same _digests below; the log's digest is that of its float32 samples
# (scene logs are float32, like the bridges')
PINNED = {
    "soft_shadow": ["c5c5d8648f3f7766", "67c513e5f77a5780", "3ef4169833cd3ac6", "e968819bf567099a"],
    "depth_of_field": ["ece40d28991205e8", "a82a7b3770d08a94", "50a1aa46d73dc8b0", "af97e6602ecf81ee"],
    "motion_blur": ["9a865244ac0f3b9d", "a792f77a4398db9d", "7f2688afd430bb52", "d4b1f66b2e599001"],
    "caustic": ["0e9f79f458ed76cf", "ec4387b50feb98c9", "d70e7358ac61bf36", "9712e9ac3445ecf9"],
    "hdr": ["50f94c4a51716fb0", "5e745df1987acd1f", "2af5dc010f2db4bc", "a76af48dd80cb422"],
    "flat": ["e824af877bee21d7", "c87efe8c9e0de40d", "b69657bc69e7b6cd", "64b043c8c285bd7e"],
}


def _dig(*arrs):
    h = hashlib.sha256()
    for a in arrs:
        a = np.ascontiguousarray(a)
        h.update(str(a.dtype).encode())
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def _request():
    return SampleRequest(12, 10, counts=np.arange(120).reshape(10, 12) % 3,
                         positions=np.array([[0.5, 0.25], [11.9, 9.99]]), round_index=1, seed=4)


def _digests(name, tmp_path, **kw):
    b = S.render_uniform(name, width=12, height=10, spp=3, seed=7, **kw)
    rb = S.SceneRenderer(name, width=12, height=10, seed=2, **kw).render(_request())
    ref = S.reference_image(name, 12, 10, quadrature=8)
    log = read_log(S.write_scene_log(name, tmp_path / f"{name}.h5", width=12, height=10, spp=2, seed=1,
                                     quadrature=4, **kw))
    d = log.read_all()
    ld = (_dig(d.positions, d.values, log.reference()) + json.dumps(log.metadata, sort_keys=True)
          + str(log.feature_names))
    return [_dig(b.positions, b.values), _dig(rb.positions, rb.values), _dig(ref),
            hashlib.sha256(ld.encode()).hexdigest()[:16]], b, rb


@pytest.mark.parametrize("name", OLD)
def test_old_scenes_bit_identical_and_features_opt_in(name, tmp_path):
    digests, b, rb = _digests(name, tmp_path)
    assert digests == PINNED[name]
    assert not S.get_scene(name).features_default and b.features == {} and rb.features == {}
    # features on: the same positions and colour, bit for bit (no extra random numbers are drawn)
    b2 = S.render_uniform(name, width=12, height=10, spp=3, seed=7, features=True)
    rb2 = S.SceneRenderer(name, width=12, height=10, seed=2, features=True).render(_request())
    for x, y in ((b, b2), (rb, rb2)):
        np.testing.assert_array_equal(x.positions, y.positions)
        np.testing.assert_array_equal(x.values, y.values)
        assert {k: v.shape[1] for k, v in y.features.items()} == LAYOUT


def test_renderer_replies_carry_features_row_by_row():
    r = S.SceneRenderer("checker_wall", width=12, height=10, seed=3)
    assert r.features and r.feature_names == ("albedo", "normal", "depth")
    req = _request()
    batch = r.render(req)
    checked = validate_reply(req, batch, n_channels=3, renderer=r.name)
    assert set(checked.features) == set(LAYOUT) and len(checked.features["depth"]) == req.total
    # checker_wall's features are deterministic per point: each row is that of its own position
    e = S.get_scene("checker_wall").expected_features(batch.positions[:, 0] / 12, batch.positions[:, 1] / 10)
    for k in LAYOUT:
        np.testing.assert_array_equal(batch.features[k], e[k])
    off = S.SceneRenderer("checker_wall", width=12, height=10, seed=3, features=False).render(req)
    assert off.features == {}
    np.testing.assert_array_equal(off.values, batch.values)
    assert "features=False" in repr(S.SceneRenderer("checker_wall", features=False))


def test_bad_feature_arguments():
    with pytest.raises(InputError, match="features.*True, False or None"):
        S.SceneRenderer("checker_wall", features="yes")

    class NoFeatures(S_catalog.Scene):
        name = "nofeat"
        n_dims = 1

        def _radiance(self, x, y, u):
            return np.repeat(u, 3, axis=1)

        def _expected(self, x, y):
            return np.full((x.size, 3), 0.5)

    sc = NoFeatures()
    with pytest.raises(InputError, match="no per-sample features"):
        S.SceneRenderer(sc, features=True)
    with pytest.raises(InputError, match="no per-sample features"):
        S.feature_reference(sc, 4, 4)
    assert S.SceneRenderer(sc).features is False      # default: none, no error


def test_log_round_trip_of_features(tmp_path):
    path = S.write_scene_log("checker_dof", tmp_path / "cd.h5", width=10, height=8, spp=5, seed=2)
    log = read_log(path)
    assert log.feature_names == ("albedo", "depth", "normal")
    assert log.metadata["settings"]["features"] == ["albedo", "normal", "depth"]
    d = log.read_all(features=log.feature_names)
    b = S.render_uniform("checker_dof", width=10, height=8, spp=5, seed=2)
    np.testing.assert_array_equal(d.values, b.values.astype(np.float32))  # scene logs are float32
    for k in LAYOUT:
        np.testing.assert_array_equal(np.asarray(d.features[k]).reshape(b.features[k].shape),
                                      b.features[k].astype(np.float32))
    st = PixelStats.from_log(log, features="all")
    ref = PixelStats.from_samples(b.positions, b.values, width=10, height=8, features=b.features)
    for k in LAYOUT:
        np.testing.assert_allclose(st.features[k].mean, ref.features[k].mean, rtol=1e-6)
    # an older scene: no features unless asked; asked, the log has them and the same colour
    plain = read_log(S.write_scene_log("soft_shadow", tmp_path / "ss.h5", width=6, height=4, spp=2))
    asked = read_log(S.write_scene_log("soft_shadow", tmp_path / "ss2.h5", width=6, height=4, spp=2,
                                       features=True))
    assert plain.feature_names == () and "features" not in plain.metadata["settings"]
    assert asked.feature_names == ("albedo", "depth", "normal")
    np.testing.assert_array_equal(plain.read_all().values, asked.read_all().values)


def test_cli_scenes_lists_features_and_render_log_writes_them(tmp_path, capsys):
    from mcrecon.cli import main

    assert main(["scenes"]) == 0
    lines = {ln.split()[0]: ln for ln in capsys.readouterr().out.splitlines()}
    assert set(ALL) <= set(lines)
    for name in TEXTURED:
        assert "features: on" in lines[name]
    for name in OLD:
        assert "features: opt-in" in lines[name]
    out = tmp_path / "cw.h5"
    assert main(["render-log", "--scene", "checker_wall", "--spp", "2", "--size", "8x6", "-o", str(out)]) == 0
    assert read_log(out).feature_names == ("albedo", "depth", "normal")
    out2 = tmp_path / "ss.h5"
    assert main(["render-log", "--scene", "soft_shadow", "--spp", "2", "--size", "8x6", "--features",
                 "-o", str(out2)]) == 0
    assert read_log(out2).feature_names == ("albedo", "depth", "normal")
    out3 = tmp_path / "cw_plain.h5"
    assert main(["render-log", "--scene", "checker_wall", "--spp", "2", "--size", "8x6", "--no-features",
                 "-o", str(out3)]) == 0
    assert read_log(out3).feature_names == ()


def test_cli_demo_on_checker_wall(tmp_path, capsys):
    from mcrecon.cli import main

    assert main(["demo", "--scene", "checker_wall", "--size", "16x16", "--spp", "4", "--methods", "box",
                 "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "checker_wall" in out and "features" in out
    assert read_log(tmp_path / "checker_wall.h5").feature_names == ("albedo", "depth", "normal")


def test_a_feature_method_gets_the_scene_features_offline_and_adaptive(tmp_path):
    """A method declaring features="required" reads the scenes' features from a log and from a SceneRenderer
    in an adaptive run.  At 32 px checker_wall's squares (4 px and 1 px) are pixel-aligned, so the pixel
    means of its (deterministic) albedo equal the feature reference to rounding, whatever the jitter."""
    import mcrecon
    from mcrecon.methods import Method, Requirements

    class AlbedoProbe(Method):
        name = "albedo_probe"
        requires = Requirements(features="required")

        def reconstruct_run(self, run, inputs):
            return inputs.stats.features["albedo"].mean

    ref = S.feature_reference("checker_wall", 32, 32)["albedo"]
    log = S.write_scene_log("checker_wall", tmp_path / "cw.h5", width=32, height=32, spp=3, seed=1)
    np.testing.assert_allclose(mcrecon.reconstruct(log, method=AlbedoProbe()), ref, rtol=1e-6)  # float32 log
    res = mcrecon.adapt(S.SceneRenderer("checker_wall", width=32, height=32, seed=2), method=AlbedoProbe(), spp=4)
    np.testing.assert_allclose(res.image, ref, rtol=1e-12)
    with pytest.raises(InputError, match="feature"):   # an older scene's default log has none to give
        mcrecon.reconstruct(S.write_scene_log("flat", tmp_path / "f.h5", width=4, height=4, spp=2),
                            method=AlbedoProbe())

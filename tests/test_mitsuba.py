"""Tests of the Mitsuba 3 bridge (mcrecon.renderers.mitsuba).

Everything that renders is marked ``mitsuba`` and skipped, with the reason
from :func:`mitsuba_available` (a subprocess probe), when Mitsuba's llvm
variant cannot load here.  Option validation runs without Mitsuba.
Films are 16-32 pixels wide and use a few spp, so the file runs in seconds.
"""

from __future__ import annotations

import numpy as np
import pytest

from mcrecon.errors import InputError, RendererError
from mcrecon.renderers.mitsuba import (MitsubaRenderer, _to_float32_positions, dump_uniform_log,
                                    mitsuba_available, render_reference)
from mcrecon.core.requests import SampleRequest, validate_reply
from mcrecon.core.samples import pixel_index

_OK, _REASON = mitsuba_available()
needs_mitsuba = pytest.mark.skipif(not _OK, reason=f"Mitsuba bridge unavailable: {_REASON}")

# Emitted radiance of the test quad: direct views of it are exactly this.
LE = np.array([3.0, 2.0, 1.0])


def quad_scene(width=24, height=16):
    """A single emitting square in the upper right of a black view.

    Asymmetric under both flips and non-square, so an x/y swap, a flipped
    axis or a W/H mix-up in the bridge moves lit samples off the quad.  A
    camera ray either hits the quad (radiance exactly LE: the plane cannot
    see itself and nothing else is in the scene) or escapes (exactly 0).
    """
    import mitsuba as mi

    T = mi.ScalarTransform4f
    return {"type": "scene",
            "integrator": {"type": "path", "max_depth": 4},
            "sensor": {"type": "perspective", "fov": 40,
                       "to_world": T().look_at(origin=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0]),
                       "sampler": {"type": "independent"},
                       "film": {"type": "hdrfilm", "width": width, "height": height,
                                "rfilter": {"type": "box"}}},
            "quad": {"type": "rectangle", "to_world": T().translate([0.6, 0.5, 0]).scale(0.5),
                     "emitter": {"type": "area", "radiance": {"type": "rgb", "value": LE.tolist()}}}}


def mi_render(scene_dict, spp, seed):
    """``mi.render`` of a scene dict with a box pixel filter, as (H, W, 3) float64."""
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    return np.asarray(mi.render(mi.load_dict(scene_dict), spp=spp, seed=seed), dtype=np.float64)


@pytest.fixture(scope="module")
def cornell32():
    return MitsubaRenderer(None, width=32, height=32)


# ------------------------------------------------------------ validation

@pytest.mark.parametrize("kwargs, field", [
    ({"variant": "scalar_rgb"}, "variant"),
    ({"variant": 3}, "variant"),
    ({"spp_per_pass": 0}, "spp_per_pass"),
    ({"spp_per_pass": 2.5}, "spp_per_pass"),
    ({"max_depth": 0}, "max_depth"),
    ({"width": 0}, "width"),
    ({"height": True}, "height"),
    ({"scene": 42}, "scene"),
    ({"scene": "/no/such/scene.xml"}, "scene"),
    ({"params": {"resx": 8}}, "params"),
])
def test_bad_options_name_the_field(kwargs, field):
    # Validated before Mitsuba is imported: runs without Mitsuba.
    scene = kwargs.pop("scene", None)
    with pytest.raises(InputError) as exc:
        MitsubaRenderer(scene, **kwargs)
    assert field in exc.value.field


def test_float32_positions_stay_in_their_pixels():
    # i + (1 - 2^-40) rounds to i + 1 in float32: the clamp must keep it in pixel i.
    pos = np.array([[3 + (1 - 2.0**-40), 7 + (1 - 2.0**-40)], [0.0, 0.25], [511.99999999, 2.5]])
    p32 = _to_float32_positions(pos)
    assert p32.dtype == np.float32
    np.testing.assert_array_equal(np.floor(p32.astype(np.float64)), np.floor(pos))
    assert np.abs(p32 - pos).max() < 1e-4


def test_availability_reports_a_reason():
    ok, reason = mitsuba_available()
    assert isinstance(ok, bool) and isinstance(reason, str) and reason
    if ok:
        assert "mitsuba" in reason and "llvm_ad_rgb" in reason


# --------------------------------------------------------------- samples

@pytest.mark.mitsuba
@needs_mitsuba
def test_counts_are_honoured_inside_their_pixels(cornell32):
    r = cornell32
    assert (r.width, r.height) == (32, 32) and tuple(r.channels) == ("R", "G", "B")
    counts = np.random.default_rng(1).integers(0, 5, size=(32, 32))
    counts[3, 5] = 0
    counts[0, 0] = 9
    req = SampleRequest(32, 32, counts=counts, seed=11, round_index=2)
    batch = r.render(req)
    validate_reply(req, batch, n_channels=3, renderer=r.name)
    assert batch.positions.shape == (counts.sum(), 2) and batch.values.shape == (counts.sum(), 3)
    got = np.bincount(pixel_index(batch.positions, 32), minlength=32 * 32).reshape(32, 32)
    np.testing.assert_array_equal(got, counts)
    assert np.isfinite(batch.values).all() and (batch.values >= 0).all()
    assert (batch.values.sum(axis=1) > 0).mean() > 0.5  # the Cornell box is mostly lit


@pytest.mark.mitsuba
@needs_mitsuba
def test_explicit_positions_in_order_and_orientation():
    # Ground truth from mi.render: interior pixels whose 3x3 neighbourhood is
    # uniformly lit (exactly LE) or uniformly black (exactly 0); any position
    # inside them must return exactly that value, in request order.
    ref = mi_render(quad_scene(), spp=16, seed=5)
    lit = np.all(ref == LE, axis=-1)
    dark = np.all(ref == 0, axis=-1)
    assert lit.any() and dark.any()
    # The scene is asymmetric, so a flipped bridge would fail below.
    assert not np.array_equal(lit, lit[::-1]) and not np.array_equal(lit, lit[:, ::-1])
    pad = lambda m: np.pad(m, 1, constant_values=False)
    inner = lambda m: np.all([pad(m)[1 + dy:1 + dy + m.shape[0], 1 + dx:1 + dx + m.shape[1]]
                              for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0)
    sure_lit, sure_dark = inner(lit), inner(dark)
    assert sure_lit.sum() >= 10 and sure_dark.sum() >= 10
    rng = np.random.default_rng(7)
    ys, xs = np.nonzero(sure_lit | sure_dark)
    pick = rng.integers(0, ys.size, 300)
    pos = np.stack([xs[pick], ys[pick]], axis=1) + rng.random((300, 2))
    r = MitsubaRenderer(quad_scene(), spp_per_pass=1)  # 384 samples per pass: 300 fit in one
    assert (r.width, r.height) == (24, 16)
    req = SampleRequest(24, 16, positions=pos, seed=3)
    batch = r.render(req)
    validate_reply(req, batch, n_channels=3)
    np.testing.assert_array_equal(batch.positions, pos)
    expect = np.where(sure_lit[ys[pick], xs[pick]][:, None], LE, 0.0)
    np.testing.assert_allclose(batch.values, expect, rtol=1e-6, atol=0)


@pytest.mark.mitsuba
@needs_mitsuba
def test_counts_then_positions_and_determinism(cornell32):
    r = cornell32
    counts = np.full((32, 32), 2)
    pos = np.array([[16.5, 20.25], [0.1, 31.9], [31.5, 0.5]])
    req = SampleRequest(32, 32, counts=counts, positions=pos, seed=5, round_index=1)
    a = r.render(req)
    b = r.render(req)
    validate_reply(req, a, n_channels=3)
    np.testing.assert_array_equal(a.positions[-3:], pos)
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.values, b.values)
    # Another seed (or round) changes the noise: a path tracer's samples of
    # the same 2048 positions cannot all coincide.
    c = r.render(SampleRequest(32, 32, counts=counts, positions=pos, seed=6, round_index=1))
    assert not np.array_equal(a.values, c.values)
    assert not np.array_equal(a.positions, c.positions)


@pytest.mark.mitsuba
@needs_mitsuba
def test_prepare_in_another_thread_gives_the_same_reply():
    """prepare() (the pipelined driver's toolkit thread) computes the film positions ahead;
    render() of that request returns exactly the reply it returns without it, over several passes."""
    import threading

    r = MitsubaRenderer(None, width=24, height=16, spp_per_pass=2)
    rng = np.random.default_rng(3)
    counts = rng.integers(0, 5, (16, 24))
    pos = rng.random((700, 2)) * [24, 16]
    for kw in ({"counts": counts}, {"positions": pos}, {"counts": counts, "positions": pos}):
        req = SampleRequest(24, 16, seed=7, round_index=2, **kw)
        plain = r.render(req)
        t = threading.Thread(target=r.prepare, args=(req,))
        t.start()
        t.join()
        ahead = r.render(req)
        np.testing.assert_array_equal(ahead.positions, plain.positions)
        np.testing.assert_array_equal(ahead.values, plain.values)
        assert ahead.values.dtype == np.float32 and ahead.positions.dtype == np.float64
        # a prepared result is used once, by that request object only
        other = SampleRequest(24, 16, seed=8, round_index=2, **kw)
        r.prepare(req)
        np.testing.assert_array_equal(r.render(other).values, r.render(other).values)
        assert not np.array_equal(r.render(other).values, plain.values)
    # the positions are those of the protocol's jittered_positions with the request's stream
    from mcrecon.core.requests import jittered_positions

    req = SampleRequest(24, 16, counts=counts, seed=5, round_index=9)
    np.testing.assert_array_equal(r.render(req).positions, jittered_positions(counts, np.random.default_rng([5, 9])))


@pytest.mark.mitsuba
@needs_mitsuba
def test_passes_get_distinct_random_streams():
    # spp_per_pass=1 on 8x8: 64 samples per kernel launch.  The same position
    # repeated 256 times spans 4 passes; repeated seeds would repeat values.
    import mitsuba as mi

    d = mi.cornell_box()
    r = MitsubaRenderer(d, width=8, height=8, spp_per_pass=1)
    assert r.pass_size == 64
    pos = np.tile([[4.5, 5.5]], (256, 1))
    batch = r.render(SampleRequest(8, 8, positions=pos, seed=9))
    v = batch.values.reshape(4, 64, 3)
    assert np.isfinite(v).all()
    for i in range(4):
        for j in range(i + 1, 4):
            assert not np.array_equal(v[i], v[j])
    # Empty request: no kernel, an empty reply.
    empty = r.render(SampleRequest(8, 8, counts=np.zeros((8, 8), np.int64)))
    assert empty.positions.shape == (0, 2) and empty.values.shape == (0, 3)


@pytest.mark.mitsuba
@needs_mitsuba
def test_time_accounting(cornell32):
    import time

    r = cornell32
    before = r.total_render_seconds
    t0 = time.perf_counter()
    r.render(SampleRequest(32, 32, counts=np.full((32, 32), 4), seed=1))
    wall = time.perf_counter() - t0
    # Consistency, not speed: the Mitsuba share is positive and part of the call.
    assert 0 < r.last_render_seconds <= r.last_call_seconds <= wall
    assert r.total_render_seconds == pytest.approx(before + r.last_render_seconds)


# ------------------------------------------- agreement with mi.render

def _block_z(img, ref, var_img, var_ref, block):
    """z-scores of block means of (img - ref) per channel.

    Pixel errors are independent across pixels, so the variance of a block
    mean of differences is the sum of per-pixel variances over block^2
    pixels divided by block^4.  With 64 pixels x 64 spp per block the CLT
    makes z standard normal under the null.
    """
    h, w, c = img.shape
    sh = (h // block, block, w // block, block, c)
    d = (img - ref).reshape(sh).mean(axis=(1, 3))
    v = (var_img + var_ref).reshape(sh).sum(axis=(1, 3)) / block**4
    return d / np.sqrt(v)


@pytest.mark.mitsuba
@needs_mitsuba
def test_bridge_mean_matches_mi_render(cornell32):
    import mitsuba as mi

    spp, spp_ref, n = 64, 1024, 32
    r = cornell32
    batch = r.render(SampleRequest(n, n, counts=np.full((n, n), spp), seed=21))
    idx = pixel_index(batch.positions, n)
    order = np.argsort(idx, kind="stable")
    vals = batch.values[order].astype(np.float64).reshape(n, n, spp, 3)
    mean = vals.mean(axis=2)
    s2 = vals.var(axis=2, ddof=1)  # per-sample variance, unbiased
    d = mi.cornell_box()
    d["sensor"]["film"].update(width=n, height=n, rfilter={"type": "box"})
    ref = mi_render(d, spp=spp_ref, seed=77)
    # Tolerance: |z| < 5 per 8x8 block and channel (48 tests, two-sided
    # p = 5.7e-7 each, family-wise false alarm < 3e-5).  mi.render's
    # per-sample variance is that of the same integrand: s2 / spp_ref.
    z = _block_z(mean, ref, s2 / spp, s2 / spp_ref, 8)
    assert np.abs(z).max() < 5, z
    # Whole-image mean per channel, 65536 samples: also within 5 sigma.
    zall = (mean - ref).mean(axis=(0, 1)) / np.sqrt((s2 / spp + s2 / spp_ref).sum(axis=(0, 1)) / n**4)
    assert np.abs(zall).max() < 5, zall
    # The test has power: a vertically or horizontally flipped bridge fails it.
    assert np.abs(_block_z(mean[::-1], ref, s2 / spp, s2 / spp_ref, 8)).max() > 5
    assert np.abs(_block_z(mean[:, ::-1], ref, s2 / spp, s2 / spp_ref, 8)).max() > 5
    # render_reference (through the bridge, another seed) agrees as well.
    rr = render_reference(r, spp=spp, seed=1234)  # film size taken from the renderer
    assert rr.dtype == np.float64 and rr.shape == (n, n, 3)
    assert np.abs(_block_z(rr, ref, s2 / spp, s2 / spp_ref, 8)).max() < 5
    with pytest.raises(InputError):
        render_reference(r, width=n + 1, height=n, spp=1)


# ------------------------------------------------------------- the log

@pytest.mark.mitsuba
@needs_mitsuba
def test_dump_uniform_log_reads_back(tmp_path):
    from mcrecon.io import read_log
    from mcrecon.core.stats import PixelStats

    path = tmp_path / "cornell.h5"
    out = dump_uniform_log(path, None, width=16, height=12, spp=5, seed=3, reference_spp=8, spp_per_pass=2)
    assert out == path and path.exists()
    assert not list(tmp_path.glob("*.partial"))
    log = read_log(path)
    assert (log.width, log.height, tuple(log.channels)) == (16, 12, ("R", "G", "B"))
    assert log.n_samples == 16 * 12 * 5
    assert log.n_rounds == 3  # passes of 2, 2 and 1 spp
    assert log.metadata["renderer"] == "mitsuba" and log.metadata["spp"] == 5
    assert log.metadata["seed"] == 3 and log.metadata["variant"] == "llvm_ad_rgb"
    ref = log.reference()
    assert ref.shape == (12, 16, 3) and np.isfinite(ref).all()
    # The stored reference is render_reference with the derived independent seed:
    # recompute it through the public function to check it is the one stored.
    ref_seed = int(np.random.SeedSequence([3, 0x726566]).generate_state(1, np.uint32)[0])
    again = render_reference(None, width=16, height=12, spp=8, seed=ref_seed, spp_per_pass=2)
    np.testing.assert_allclose(ref, again, rtol=0, atol=0)
    stats = PixelStats.from_log(log)
    np.testing.assert_array_equal(stats.count, np.full((12, 16), 5))
    assert np.isfinite(stats.mean).all()
    # The logged samples are not the reference's samples (independent seeds).
    assert not np.allclose(stats.mean, ref)


@pytest.mark.mitsuba
@needs_mitsuba
def test_scene_file_and_size_mismatch(tmp_path):
    xml = tmp_path / "quad.xml"
    xml.write_text("""<scene version="3.0.0">
  <default name="resx" value="20"/>
  <default name="resy" value="10"/>
  <integrator type="path"><integer name="max_depth" value="3"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0, 0, 5" target="0, 0, 0" up="0, 1, 0"/></transform>
    <sampler type="independent"/>
    <film type="hdrfilm"><integer name="width" value="$resx"/><integer name="height" value="$resy"/></film>
  </sensor>
  <shape type="rectangle">
    <transform name="to_world"><scale value="0.5"/><translate value="0.6, 0.5, 0"/></transform>
    <emitter type="area"><rgb name="radiance" value="3, 2, 1"/></emitter>
  </shape>
</scene>
""")
    r = MitsubaRenderer(xml)
    assert (r.width, r.height) == (20, 10)
    r2 = MitsubaRenderer(xml, width=12, height=6, params={"resx": 12, "resy": 6})
    assert (r2.width, r2.height) == (12, 6)
    batch = r2.render(SampleRequest(12, 6, counts=np.ones((6, 12), np.int64)))
    vals = batch.values
    # Only exact zeros or exact LE (direct view of the emitter): no other light path exists.
    hit = np.all(vals == LE.astype(np.float32), axis=1)
    assert hit.any() and (hit | np.all(vals == 0, axis=1)).all()
    with pytest.raises(InputError) as exc:
        MitsubaRenderer(xml, width=30, height=10)
    assert "width/height" in exc.value.field and "20x10" in exc.value.problem
    with pytest.raises(InputError):
        r.render(SampleRequest(12, 6, counts=np.ones((6, 12), np.int64)))
    # the command line: without --size a scene file renders at its own film size (the default
    # 128x128 was forced on it, and nothing could be omitted); a --size that differs is refused
    from mcrecon.cli import main
    from mcrecon.io import read_log

    assert main(["mitsuba", "log", "--scene", str(xml), "--spp", "1", "-o", str(tmp_path / "q.h5")]) == 0
    assert (read_log(tmp_path / "q.h5").width, read_log(tmp_path / "q.h5").height) == (20, 10)
    assert main(["adapt", "--mitsuba", str(xml), "--spp", "2", "--method", "gem", "--log", str(tmp_path / "a.h5"),
                 "-o", str(tmp_path / "a.exr"), "--no-progress"]) == 0
    log = read_log(tmp_path / "a.h5")
    assert (log.width, log.height, log.n_samples) == (20, 10, 400)
    assert main(["adapt", "--mitsuba", str(xml), "--size", "30x10", "--spp", "2", "-o",
                 str(tmp_path / "b.exr")]) == 2
    assert not (tmp_path / "b.exr").exists()
    # without --size the one-renderer rule still holds (the film-size path skipped it)
    assert main(["adapt", "--mitsuba", str(xml), "--scene", "flat", "--spp", "2", "-o",
                 str(tmp_path / "c.exr")]) == 2


# ------------------------------------------------- the availability probe

def test_probe_failure_is_reported_not_fatal(monkeypatch):
    # A libLLVM that cannot be found: the probe subprocess fails, this
    # process gets (False, reason) naming the cause.  The per-process cache
    # is swapped for a fresh dict so later tests see the real answer.
    import mcrecon.renderers.mitsuba as mb

    if not _OK:
        pytest.skip(f"Mitsuba bridge unavailable: {_REASON}")
    monkeypatch.setattr(mb, "_PROBE_CACHE", {})
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", "/nonexistent/libLLVM-none.so")
    ok, reason = mb.mitsuba_available(refresh=True)
    assert not ok and "probe" in reason and "LLVM" in reason
    with pytest.raises(RendererError) as exc:
        MitsubaRenderer(None, width=4, height=4)
    assert exc.value.field == "mitsuba"


def test_probe_survives_an_aborting_llvm(monkeypatch):
    # libLLVM 15 makes Dr.Jit abort the process on its first kernel; the
    # probe must turn that into (False, reason) and leave us running.
    import glob

    import mcrecon.renderers.mitsuba as mb

    old = sorted(glob.glob("/usr/lib/*/libLLVM-15.so*") + glob.glob("/usr/lib/*/libLLVM-16.so*"))
    if not _OK or not old:
        pytest.skip("reproduces the abort of an old libLLVM: needs a working bridge and libLLVM 15 or 16 installed "
                    "beside it (apt-get install libllvm15)")
    monkeypatch.setattr(mb, "_PROBE_CACHE", {})
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", old[0])
    ok, reason = mb.mitsuba_available(refresh=True)
    assert not ok and "SIGABRT" in reason and "libllvm19" in reason


# ------------------------------------------------------------ features
# A 2x2 texture of distinct colours on a plane facing the camera at distance D,
# a glass sphere in front of it, and a constant environment elsewhere.
TEXELS = np.array([[[0.9, 0.1, 0.1], [0.1, 0.8, 0.2]],
                   [[0.2, 0.3, 0.7], [0.5, 0.5, 0.5]]], np.float32)
D, FOV = 5.0, 40.0


def feature_scene(width=24, height=16, integrator=None, tilt=0.0):
    """The textured plane (rotated by ``tilt`` degrees about y) and a glass sphere."""
    import mitsuba as mi

    T = mi.ScalarTransform4f
    return {"type": "scene", "integrator": integrator or {"type": "path", "max_depth": 3},
            "sensor": {"type": "perspective", "fov": FOV,
                       "to_world": T().look_at(origin=[0, 0, D], target=[0, 0, 0], up=[0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"}}},
            "plane": {"type": "rectangle", "to_world": T().rotate([0, 1, 0], tilt).scale([1.2, 1.0, 1.0]),
                      "bsdf": {"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": mi.Bitmap(TEXELS),
                                                                  "filter_type": "nearest"}}},
            "glass": {"type": "sphere", "center": [1.3, 0.75, 1.0], "radius": 0.3, "bsdf": {"type": "dielectric"}},
            "env": {"type": "constant"}}


def _uniform_batch(r, spp=4, seed=2):
    counts = np.full((r.height, r.width), spp, np.int64)
    return r.render(SampleRequest(r.width, r.height, counts=counts, seed=seed))


def test_feature_option_is_validated():
    from mcrecon.renderers.mitsuba import check_mitsuba_features

    assert check_mitsuba_features("all") == ("albedo", "normal", "depth")
    assert check_mitsuba_features("none") == () == check_mitsuba_features([])
    assert check_mitsuba_features("depth,albedo") == ("albedo", "depth")
    for bad in ("colour", "albedo,albedo", 3, ["normal", None]):
        with pytest.raises(InputError, match="features"):
            check_mitsuba_features(bad)
    with pytest.raises(InputError, match="unknown feature 'colour'"):
        MitsubaRenderer(None, features="albedo,colour", probe=False)


@pytest.mark.mitsuba
@needs_mitsuba
def test_features_albedo_normal_depth_of_known_surfaces():
    r = MitsubaRenderer(feature_scene(), spp_per_pass=2)
    assert r.features == ("albedo", "normal", "depth")
    b = _uniform_batch(r)
    n = len(b)
    assert set(b.features) == {"albedo", "normal", "depth"}
    assert b.features["albedo"].shape == (n, 3) and b.features["normal"].shape == (n, 3)
    assert b.features["depth"].shape == (n,)
    assert all(f.dtype == np.float32 for f in b.features.values())
    alb, nor, dep = b.features["albedo"], b.features["normal"], b.features["depth"]
    # Every sample either misses (all features 0), hits glass (albedo 1: no diffuse lobe) or hits
    # the plane (albedo exactly one of the texels, normal +z toward the camera).
    texel = np.any(np.all(alb[:, None, :] == TEXELS.reshape(1, 4, 3), axis=2), axis=1)
    glass = np.all(alb == 1.0, axis=1)
    miss = dep == 0
    assert texel.sum() > n // 4 and glass.sum() > 10 and miss.sum() > n // 10
    assert np.all(texel | glass | miss)
    np.testing.assert_array_equal(alb[miss], 0.0)
    np.testing.assert_array_equal(nor[miss], 0.0)
    for k in range(4):  # every texel is seen
        assert np.all(alb == TEXELS.reshape(4, 3)[k], axis=1).sum() > 10
    np.testing.assert_allclose(nor[texel], np.broadcast_to([0, 0, 1], (texel.sum(), 3)), atol=1e-6)
    # Depth is camera-space z: D on the whole plane z = 0 facing the camera.
    np.testing.assert_allclose(dep[texel], D, rtol=1e-6)
    # Glass sphere: unit normals, the hit c + r n on the side facing the camera, at depth D - z.
    ng = nor[glass].astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(ng, axis=1), 1.0, rtol=1e-5)
    hit = np.array([1.3, 0.75, 1.0]) + 0.3 * ng
    assert np.all(np.sum(ng * (np.array([0, 0, D]) - hit), axis=1) > 0)
    np.testing.assert_allclose(dep[glass], D - hit[:, 2], rtol=1e-4)


@pytest.mark.mitsuba
@needs_mitsuba
def test_albedo_matches_mitsuba_aov_image_where_the_pixel_is_uniform():
    # Mitsuba's own aov integrator as the ground truth of where each texel is on the film:
    # samples inside pixels whose 3x3 neighbourhood has one albedo must have exactly it.
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    aov = feature_scene(integrator={"type": "aov", "aovs": "a:albedo"})
    img = np.asarray(mi.render(mi.load_dict(aov), spp=16, seed=1))[..., :3]
    r = MitsubaRenderer(feature_scene(), features="albedo")
    b = _uniform_batch(r, spp=2)
    assert set(b.features) == {"albedo"}
    pad = np.pad(img, ((1, 1), (1, 1), (0, 0)), mode="edge")
    same = np.all([np.all(pad[1 + dy:17 + dy, 1 + dx:25 + dx] == img, axis=-1)
                   for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0)
    texel_px = same & np.any(np.all(img[:, :, None, :] == TEXELS.reshape(1, 1, 4, 3), axis=-1), axis=-1)
    assert texel_px.sum() > 40
    px = pixel_index(b.positions, r.width)
    sel = texel_px.ravel()[px]
    np.testing.assert_array_equal(b.features["albedo"][sel], img.reshape(-1, 3)[px[sel]])


@pytest.mark.mitsuba
@needs_mitsuba
def test_normal_of_a_tilted_plane():
    tilt = 30.0
    r = MitsubaRenderer(feature_scene(tilt=tilt), features=["normal", "depth"])
    b = _uniform_batch(r, spp=2)
    assert set(b.features) == {"normal", "depth"}
    nor, dep = b.features["normal"], b.features["depth"]
    on_plane = (dep > 0) & (np.abs(nor[:, 0]) > 0.1) & (np.abs(nor[:, 1]) < 1e-4)  # not the sphere
    assert on_plane.sum() > len(b) // 4
    expect = [np.sin(np.radians(tilt)), 0.0, np.cos(np.radians(tilt))]  # R_y(tilt) (0, 0, 1)
    np.testing.assert_allclose(nor[on_plane], np.broadcast_to(expect, (on_plane.sum(), 3)), atol=1e-5)
    # Camera-space depth of the tilted plane x sin + z cos = 0 seen from (0, 0, D) along -z: the
    # hit (x, y, z) has depth D - z and x = -z cot(tilt); with the film's x offset u = x / depth
    # (the sign of u is the camera's mirror image: |u| is what the geometry fixes)
    # z = -u (D - z) tan(tilt) gives depth = D / (1 - u tan(tilt)) for one sign of u.
    t = np.tan(np.radians(FOV / 2))
    u = np.abs(2 * b.positions[:, 0] / r.width - 1) * t
    d = dep[on_plane]
    cand = np.stack([D / (1 - u * np.tan(np.radians(tilt))), D / (1 + u * np.tan(np.radians(tilt)))])[:, on_plane]
    assert np.all(np.min(np.abs(cand - d) / d, axis=0) < 1e-5)


@pytest.mark.mitsuba
@needs_mitsuba
def test_log_has_features_by_default_and_none_on_request(tmp_path):
    from mcrecon.io import read_log
    from mcrecon.core.stats import PixelStats

    r = MitsubaRenderer(feature_scene(12, 8), spp_per_pass=2)
    path = dump_uniform_log(tmp_path / "f.h5", r, spp=3, seed=4)
    log = read_log(path)
    assert set(log.feature_names) == {"albedo", "normal", "depth"}  # (HDF5 lists them by name)
    assert log.metadata["features"] == "albedo,normal,depth"
    st = PixelStats.from_log(log, features="all")
    # The per-pixel means of the logged features are the renderer's, for the same seed.
    bs = [r.render(SampleRequest(12, 8, counts=np.full((8, 12), m, np.int64), round_index=k, seed=4))
          for k, m in enumerate((2, 1))]  # the passes of 2 and 1 spp
    again = PixelStats.from_samples(np.concatenate([x.positions for x in bs]), np.concatenate([x.values for x in bs]),
                                    width=12, height=8,
                                    features={f: np.concatenate([x.features[f] for x in bs]) for f in r.features})
    for f in r.features:
        np.testing.assert_allclose(st.features[f].mean, again.features[f].mean, rtol=1e-6, atol=1e-7)
    # a renderer's own features by default; a feature it does not send is refused
    r_depth = MitsubaRenderer(feature_scene(12, 8), features="depth")
    assert read_log(dump_uniform_log(tmp_path / "d.h5", r_depth, spp=1)).feature_names == ("depth",)
    with pytest.raises(InputError, match="albedo asked for, but this renderer was built with features='depth'"):
        dump_uniform_log(tmp_path / "e.h5", r_depth, spp=1, features="albedo,depth")
    none = dump_uniform_log(tmp_path / "n.h5", feature_scene(12, 8), spp=2, seed=4, features="none")
    log = read_log(none)
    assert tuple(log.feature_names) == () and log.metadata["features"] == "none"
    # the colour is the same with or without features (same random numbers)
    with_f = read_log(dump_uniform_log(tmp_path / "w.h5", feature_scene(12, 8), spp=2, seed=4))
    np.testing.assert_array_equal(PixelStats.from_log(log).mean, PixelStats.from_log(with_f).mean)


def test_mitsuba_spec_records_features():
    from mcrecon.renderers.spec import check_spec, mitsuba_spec

    assert mitsuba_spec(None, width=4, height=4)["features"] == "albedo,normal,depth"
    assert mitsuba_spec(None, width=4, height=4, features="none")["features"] == "none"
    # a spec recorded before features existed rendered none
    assert check_spec({"kind": "mitsuba", "scene": None, "width": 4, "height": 4})["features"] == "none"
    with pytest.raises(InputError, match="features"):
        check_spec({"kind": "mitsuba", "scene": None, "width": 4, "height": 4, "features": "colour"})


@pytest.mark.mitsuba
@needs_mitsuba
def test_cli_mitsuba_log_and_adapt_features(tmp_path, capsys):
    from mcrecon.cli import main
    from mcrecon.io import read_log

    base = ["mitsuba", "log", "--size", "8x8", "--spp", "2"]
    assert main(base + ["-o", str(tmp_path / "a.h5")]) == 0
    assert set(read_log(tmp_path / "a.h5").feature_names) == {"albedo", "normal", "depth"}
    capsys.readouterr()
    assert main(["info", str(tmp_path / "a.h5")]) == 0
    out = capsys.readouterr().out
    for line in ("albedo                 3 component(s) R,G,B, float32",
                 "normal                 3 component(s) X,Y,Z, float32",
                 "depth                  1 component(s) Z, float32"):
        assert line in out
    assert main(["info", "--json", str(tmp_path / "a.h5")]) == 0
    import json
    det = json.loads(capsys.readouterr().out)["feature_details"]
    assert {d["name"]: (d["components"], d["dtype"]) for d in det} == {
        "albedo": (["R", "G", "B"], "float32"), "normal": (["X", "Y", "Z"], "float32"), "depth": (["Z"], "float32")}
    assert main(base + ["--features", "none", "-o", str(tmp_path / "b.h5")]) == 0
    assert read_log(tmp_path / "b.h5").feature_names == ()
    assert main(base + ["--features", "depth", "-o", str(tmp_path / "c.h5")]) == 0
    assert read_log(tmp_path / "c.h5").feature_names == ("depth",)
    # adapt --mitsuba stores what the bridge sends, every round
    assert main(["adapt", "--mitsuba", "--size", "8x8", "--spp", "4", "--features", "albedo,normal",
                 "--log", str(tmp_path / "d.h5"), "-o", str(tmp_path / "d.exr"), "--no-progress"]) == 0
    log = read_log(tmp_path / "d.h5")
    assert set(log.feature_names) == {"albedo", "normal"}
    assert log.n_samples == 4 * 64
    capsys.readouterr()
    assert main(["adapt", "--renderer-cmd", "x {request} {reply}", "--size", "8x8", "--spp", "2", "--features",
                 "none", "-o", str(tmp_path / "e.exr")]) != 0
    assert "--features: chooses the per-sample features of the Mitsuba bridge" in capsys.readouterr().err


@pytest.mark.mitsuba
@needs_mitsuba
def test_renderer_from_spec_sends_the_recorded_features():
    from mcrecon.renderers.spec import mitsuba_spec, renderer_from_spec

    assert renderer_from_spec(mitsuba_spec(None, width=8, height=8, features="depth")).features == ("depth",)
    old = {"kind": "mitsuba", "scene": None, "width": 8, "height": 8}  # recorded before features existed
    assert renderer_from_spec(old).features == ()

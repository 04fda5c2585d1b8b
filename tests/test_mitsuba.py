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
        pytest.skip("needs a working bridge and a libLLVM 15/16 on this machine to reproduce the abort")
    monkeypatch.setattr(mb, "_PROBE_CACHE", {})
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", old[0])
    ok, reason = mb.mitsuba_available(refresh=True)
    assert not ok and "SIGABRT" in reason and "libllvm19" in reason

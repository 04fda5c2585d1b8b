"""Pixel-statistics EXRs (pbrt-v4 GBufferFilm, Mitsuba 3 moment integrator, explicit mapping) -> denoise."""

import subprocess
import sys
import textwrap

import numpy as np
import pytest

import mcrecon
from mcrecon import InputError, PixelStats
from mcrecon.io import read_exr, read_pixel_stats_exr
from mcrecon.errors import McreconWarning
from mcrecon.io.pixel_exr import MITSUBA_XYZ_TO_SRGB, read_half_buffer_exrs, xyz_from_rgb_matrix

from helpers import run_cli

H, W, SPP = 12, 16, 8

# pbrt-v4 GBufferFilm::GetImage's channel list (src/pbrt/film.cpp), in its order.
PBRT_CHANNELS = ("R", "G", "B", "Albedo.R", "Albedo.G", "Albedo.B", "P.X", "P.Y", "P.Z", "dzdx", "dzdy",
                 "N.X", "N.Y", "N.Z", "Ns.X", "Ns.Y", "Ns.Z", "u", "v", "Variance.R", "Variance.G", "Variance.B",
                 "RelativeVariance.R", "RelativeVariance.G", "RelativeVariance.B")


def write_channels(path, channels: dict, dtype=np.float32, **attrs):
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **attrs}
    data = {k: np.ascontiguousarray(v, dtype=dtype) for k, v in channels.items()}
    with OpenEXR.File(header, data) as f:
        f.write(str(path))
    return path


def samples(seed=0, h=H, w=W, spp=SPP):
    """Per-pixel samples (H, W, spp, 3) of a smooth image with noise."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    base = np.stack([0.5 + 0.4 * np.sin(xx / 3.0), 0.3 + 0.2 * yy / h, 0.6 + 0.0 * xx], axis=-1)
    return base[:, :, None, :] * rng.gamma(4.0, 0.25, (h, w, spp, 3))


def pbrt_exr(path, s, *, dtype=np.float32, spp_attr=True, extra=True):
    """A pbrt-v4 GBufferFilm-like EXR of samples ``s`` (sensor = XYZ, output = sRGB, box filter)."""
    xyz_from_rgb = xyz_from_rgb_matrix()
    rgb_from_xyz = np.linalg.inv(xyz_from_rgb)
    xyz = s @ xyz_from_rgb.T                     # what pbrt's default sensor adds: XYZ per sample
    mean_xyz = xyz.mean(axis=2)
    var_xyz = xyz.var(axis=2, ddof=1)             # VarianceEstimator::Variance(): S / (n - 1)
    rgb = mean_xyz @ rgb_from_xyz.T
    rng = np.random.default_rng(7)
    ch = {}
    for name in PBRT_CHANNELS if extra else ("R", "G", "B", "Variance.R", "Variance.G", "Variance.B"):
        ch[name] = rng.random(s.shape[:2])        # AOVs: noise that must be ignored
    for i, c in enumerate("RGB"):
        ch[c] = rgb[..., i]
        ch[f"Variance.{c}"] = var_xyz[..., i]
        ch[f"RelativeVariance.{c}"] = var_xyz[..., i] / np.maximum(mean_xyz[..., i], 1e-6)
    attrs = {"samplesPerPixel": s.shape[2]} if spp_attr else {}
    write_channels(path, ch, dtype=dtype, **attrs)
    return mean_xyz, var_xyz, rgb


def mitsuba_exr(path, s, *, prefix="nested"):
    """A Mitsuba 3 moment-integrator-like EXR (film.bitmap() names) of samples ``s``."""
    srgb_to_xyz = np.linalg.inv(MITSUBA_XYZ_TO_SRGB)
    xyz = s @ srgb_to_xyz.T
    m1, m2 = xyz.mean(axis=2), (xyz ** 2).mean(axis=2)
    ch = {c: s.mean(axis=2)[..., i] for i, c in enumerate("RGB")}
    for i, a in enumerate("XYZ"):
        ch[f"{prefix}.{a}"] = m1[..., i]
        ch[f"m2_{prefix}.{a}"] = m2[..., i]
    write_channels(path, ch)
    return m1, xyz.var(axis=2, ddof=1)


# ------------------------------------------------------------------ statistics
def test_pbrt_statistics_equal_from_moments(tmp_path):
    s = samples()
    mean_xyz, var_xyz, _ = pbrt_exr(tmp_path / "pbrt.exr", s)
    pix = read_pixel_stats_exr(tmp_path / "pbrt.exr")
    assert pix.layout == "pbrt-v4" and pix.count_source.startswith("header attribute samplesPerPixel")
    ref = PixelStats.from_moments(mean_xyz, var_xyz, SPP, channels=("X", "Y", "Z"))
    np.testing.assert_allclose(pix.stats.mean, ref.mean, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(pix.stats.m2, ref.m2, rtol=1e-5, atol=1e-7)
    assert (pix.stats.count == SPP).all() and not pix.stats.has_range
    assert pix.output_channels == ("R", "G", "B")
    # box on these statistics is the file's own R,G,B
    rgb_file = read_exr(tmp_path / "pbrt.exr")[0][..., :3]
    np.testing.assert_allclose(pix.output_image(pix.stats.mean), rgb_file, rtol=1e-5, atol=1e-6)


def test_pbrt_variance_is_of_the_samples_not_the_mean(tmp_path):
    """pbrt writes S/(n-1): the statistics' variance of the mean is that over n."""
    s = samples(1)
    _, var_xyz, _ = pbrt_exr(tmp_path / "p.exr", s)
    pix = read_pixel_stats_exr(tmp_path / "p.exr", layout="pbrt-v4")
    np.testing.assert_allclose(pix.stats.mean_variance(), var_xyz / SPP, rtol=1e-5, atol=1e-9)


def test_mitsuba_statistics_equal_from_moments(tmp_path):
    s = samples(2)
    m1, var = mitsuba_exr(tmp_path / "mi.exr", s)
    pix = read_pixel_stats_exr(tmp_path / "mi.exr", spp=SPP)
    assert pix.layout == "mitsuba-moment"
    assert pix.sources == {"mean": ("nested.X", "nested.Y", "nested.Z"),
                           "second_moment": ("m2_nested.X", "m2_nested.Y", "m2_nested.Z"), "features": {}}
    ref = PixelStats.from_moments(m1, var, SPP, channels=("X", "Y", "Z"))
    np.testing.assert_allclose(pix.stats.mean, ref.mean, rtol=1e-6)
    np.testing.assert_allclose(pix.stats.m2, ref.m2, rtol=2e-4, atol=1e-6)  # float32 m2 - m1^2
    np.testing.assert_allclose(pix.output_image(pix.stats.mean), s.mean(axis=2), rtol=1e-4, atol=1e-6)


def test_explicit_mapping_count_channel_and_variance_of_mean(tmp_path):
    rng = np.random.default_rng(3)
    mean = rng.random((H, W, 3))
    var = rng.random((H, W, 3)) * 0.1
    n = rng.integers(2, 9, (H, W)).astype(np.float32)
    ch = {"col.r": mean[..., 0], "col.g": mean[..., 1], "col.b": mean[..., 2],
          "v.r": var[..., 0], "v.g": var[..., 1], "v.b": var[..., 2], "N": n, "junk": rng.random((H, W))}
    write_channels(tmp_path / "x.exr", ch)
    pix = read_pixel_stats_exr(tmp_path / "x.exr", mean="col.r,col.g,col.b", variance="v.r,v.g,v.b",
                               count="N", variance_of="mean")
    ref = PixelStats.from_moments(mean, var, n, channels=("col.r", "col.g", "col.b"), variance_of="mean")
    np.testing.assert_allclose(pix.stats.m2, ref.m2, rtol=1e-5, atol=1e-7)
    assert (pix.stats.count == n).all() and pix.output_matrix is None and pix.layout == "explicit"


# ------------------------------------------------------------------ the command
@pytest.mark.parametrize("layout", ["pbrt-v4", "mitsuba-moment"])
@pytest.mark.parametrize("method", ["gem", "awr", "box"])
def test_denoise_command_equals_reconstruct(tmp_path, capsys, layout, method):
    s = samples(4, h=32, w=32)
    path = tmp_path / f"{layout}.exr"
    extra = []
    if layout == "pbrt-v4":
        pbrt_exr(path, s)
    else:
        mitsuba_exr(path, s)
        extra = ["--spp", s.shape[2]]
    out = tmp_path / "out.exr"
    code, stdout, err = run_cli(["denoise", path, "-o", out, "--method", method, "--layout", layout, *extra], capsys)
    assert code == 0, err
    assert f"layout {layout}" in err and "wrote" in stdout
    if method == "awr":  # its default 'sample' estimator takes pixel statistics as they are: nothing to change
        assert "--variance sample" not in err
    img, names = read_exr(out)
    assert names == ("R", "G", "B") and img.shape == (32, 32, 3)
    pix = read_pixel_stats_exr(path, layout=layout, spp=None if layout == "pbrt-v4" else s.shape[2])
    opts = {"variance": "sample"} if method == "awr" else {}
    expect = pix.output_image(mcrecon.reconstruct(pix.stats, method=method, **opts))
    np.testing.assert_allclose(img, expect.astype(np.float32), rtol=1e-6, atol=1e-7)
    assert np.isfinite(img).all()


def test_denoise_explicit_mapping(tmp_path, capsys):
    s = samples(5)
    ch = {"C.r": s.mean(axis=2)[..., 0], "C.g": s.mean(axis=2)[..., 1], "C.b": s.mean(axis=2)[..., 2]}
    v = s.var(axis=2, ddof=1)
    ch.update({"V.r": v[..., 0], "V.g": v[..., 1], "V.b": v[..., 2]})
    write_channels(tmp_path / "e.exr", ch, spp=SPP)
    code, _, err = run_cli(["denoise", tmp_path / "e.exr", "-o", tmp_path / "o.exr", "--method", "gem",
                            "--mean", "C.r,C.g,C.b", "--variance-channels", "V.r,V.g,V.b"], capsys)
    assert code == 0, err
    assert "header attribute spp" in err
    img, names = read_exr(tmp_path / "o.exr")
    assert names == ("C.r", "C.g", "C.b")
    st = PixelStats.from_moments(s.mean(axis=2), v, SPP, channels=("C.r", "C.g", "C.b"))
    np.testing.assert_allclose(img, mcrecon.reconstruct(st, method="gem").astype(np.float32), rtol=1e-5, atol=1e-6)


# ------------------------------------------------------------------ errors
def one_line_error(capsys, args):
    code, _, err = run_cli(args, capsys)
    assert code == 2 and err.count("\n") == 1 and err.startswith("mcrecon: error:"), err
    return err


def test_missing_channel_names_file_channel_and_present(tmp_path, capsys):
    pbrt_exr(tmp_path / "p.exr", samples(), extra=False)
    err = one_line_error(capsys, ["denoise", tmp_path / "p.exr", "-o", tmp_path / "o.exr",
                                  "--layout", "pbrt-v4", "--variance-channels", "Var.R,Var.G,Var.B"])
    assert "p.exr" in err and "'Var.R' missing" in err and "Variance.G" in err  # channels present listed


def test_no_count_says_pass_spp(tmp_path, capsys):
    pbrt_exr(tmp_path / "p.exr", samples(), spp_attr=False)
    err = one_line_error(capsys, ["denoise", tmp_path / "p.exr", "-o", tmp_path / "o.exr"])
    assert "--spp" in err and "sample count" in err
    mitsuba_exr(tmp_path / "m.exr", samples())
    err = one_line_error(capsys, ["denoise", tmp_path / "m.exr", "-o", tmp_path / "o.exr", "--method", "gem"])
    assert "--spp" in err


def test_spp_contradicting_the_header_is_refused(tmp_path, capsys):
    pbrt_exr(tmp_path / "p.exr", samples())
    err = one_line_error(capsys, ["denoise", tmp_path / "p.exr", "-o", tmp_path / "o.exr", "--spp", "4"])
    assert "samplesPerPixel" in err and "8" in err and "4" in err


@pytest.mark.parametrize("bad", [np.nan, np.inf, -0.5])
def test_bad_variances_refused(tmp_path, capsys, bad):
    s = samples()
    pbrt_exr(tmp_path / "p.exr", s)
    import OpenEXR

    f = OpenEXR.File(str(tmp_path / "p.exr"), separate_channels=True)
    ch = {k: np.array(v.pixels) for k, v in f.channels().items()}
    ch["Variance.G"][3, 4] = bad
    write_channels(tmp_path / "b.exr", ch, samplesPerPixel=SPP)
    err = one_line_error(capsys, ["denoise", tmp_path / "b.exr", "-o", tmp_path / "o.exr"])
    assert "b.exr" in err and "Variance.G" in err
    assert ("negative" in err) if bad < 0 else ("NaN or Inf" in err)


def test_half_float_saturation_warns_and_half_inf_variance_explains(tmp_path, capsys):
    s = samples()
    pbrt_exr(tmp_path / "p.exr", s, dtype=np.float16)
    import OpenEXR

    f = OpenEXR.File(str(tmp_path / "p.exr"), separate_channels=True)
    ch = {k: np.array(v.pixels) for k, v in f.channels().items()}
    ch["R"][0, 0] = 65504.0  # pbrt's clamp with savefp16
    write_channels(tmp_path / "sat.exr", ch, dtype=np.float16, samplesPerPixel=SPP)
    code, _, err = run_cli(["denoise", tmp_path / "sat.exr", "-o", tmp_path / "o.exr"], capsys)
    assert code == 0 and "warning" in err and "65504" in err and "savefp16" in err
    ch["R"][0, 0] = 1.0
    ch["Variance.B"][1, 1] = np.inf  # a variance above 65504 overflows in half
    write_channels(tmp_path / "inf.exr", ch, dtype=np.float16, samplesPerPixel=SPP)
    err = one_line_error(capsys, ["denoise", tmp_path / "inf.exr", "-o", tmp_path / "o.exr"])
    assert "Variance.B" in err and "savefp16" in err


@pytest.mark.parametrize("args, why", [(["--method", "splat"], "individual samples"),
                                       (["--method", "gem", "--subpixel-exact-below", "2"], "subpixel")])
def test_methods_needing_samples_refuse(tmp_path, capsys, args, why):
    pbrt_exr(tmp_path / "p.exr", samples())
    err = one_line_error(capsys, ["denoise", tmp_path / "p.exr", "-o", tmp_path / "o.exr", *args])
    assert why in err and "pixel-statistics EXR" in err


def test_awr_range_estimator_chosen_explicitly_is_refused(tmp_path, capsys):
    pbrt_exr(tmp_path / "p.exr", samples())
    err = one_line_error(capsys, ["denoise", tmp_path / "p.exr", "-o", tmp_path / "o.exr", "--method", "awr",
                                  "--variance", "range"])
    assert "minimum and maximum" in err


def test_unrecognised_layout_and_flags_on_a_log(tmp_path, capsys):
    write_channels(tmp_path / "plain.exr", {"R": np.ones((4, 4)), "G": np.ones((4, 4)), "B": np.ones((4, 4))})
    err = one_line_error(capsys, ["denoise", tmp_path / "plain.exr", "-o", tmp_path / "o.exr", "--spp", "4"])
    assert "not recognised" in err and "--mean" in err
    code, _, err = run_cli(["render-log", "--scene", "soft_shadow", "--spp", "2", "--size", "8x8", "-o",
                            tmp_path / "l.h5"], capsys)
    err = one_line_error(capsys, ["denoise", tmp_path / "l.h5", "-o", tmp_path / "o.exr", "--spp", "4"])
    assert "--spp" in err and ".exr" in err


def test_python_api_errors():
    with pytest.raises(InputError, match="layout"):
        read_pixel_stats_exr("x.exr", layout="blender")
    with pytest.raises(InputError, match="does not exist"):
        read_pixel_stats_exr("/nonexistent/x.exr", spp=4)


# ------------------------------------------------------------------ a real Mitsuba render
_RENDER = textwrap.dedent("""
    import os, sys
    from mcrecon.renderers.mitsuba import drjit_cache_dir
    os.environ.setdefault("DRJIT_CACHE_DIR", drjit_cache_dir())
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    d = mi.cornell_box()
    d["sensor"]["film"].update(width=24, height=16, rfilter={"type": "box"})
    d["integrator"] = {"type": "moment", "nested": {"type": "path", "max_depth": 4}}
    scene = mi.load_dict(d)
    img = mi.render(scene, spp=int(sys.argv[2]), seed=1)
    film = scene.sensors()[0].film()
    mi.util.write_bitmap(sys.argv[1] + "/film.exr", film.bitmap(), write_async=False)   # names kept
    mi.util.write_bitmap(sys.argv[1] + "/tensor.exr", img, write_async=False)          # ch0 ... ch8
    # moment of an aov integrator: the colour and the features' moments (nested.albedo.R, m2_...)
    d["integrator"] = {"type": "moment", "nested": {"type": "aov", "aovs": "albedo:albedo,nn:sh_normal,dd:depth",
                                                    "inner": {"type": "path", "max_depth": 4}}}
    scene = mi.load_dict(d)
    mi.render(scene, spp=int(sys.argv[2]), seed=1)
    mi.util.write_bitmap(sys.argv[1] + "/aov.exr", scene.sensors()[0].film().bitmap(), write_async=False)
""")


@pytest.fixture(scope="module")
def mitsuba_moment_exrs(tmp_path_factory):
    from mcrecon.renderers.mitsuba import mitsuba_available

    ok, reason = mitsuba_available()
    if not ok:
        pytest.skip(f"Mitsuba 3 unavailable: {reason}")
    d = tmp_path_factory.mktemp("mitsuba_moment")
    proc = subprocess.run([sys.executable, "-c", _RENDER, str(d), "16"], capture_output=True, text=True,
                          timeout=600)
    if proc.returncode != 0:
        pytest.fail(f"Mitsuba moment render failed: {proc.stderr[-2000:]}")
    return d


def test_real_mitsuba_moment_output(mitsuba_moment_exrs, capsys):
    d = mitsuba_moment_exrs
    film = read_pixel_stats_exr(d / "film.exr", spp=16)
    assert film.layout == "mitsuba-moment" and film.sources["mean"] == ("nested.X", "nested.Y", "nested.Z")
    rgb = read_exr(d / "film.exr")[0][..., :3]  # R, G, B first
    # the moment AOVs are the sRGB radiance in XYZ: box on them gives the film's RGB back
    np.testing.assert_allclose(film.output_image(film.stats.mean), rgb, rtol=1e-4, atol=1e-5)
    assert (film.stats.m2 >= 0).all() and film.stats.m2.max() > 0
    tensor = read_pixel_stats_exr(d / "tensor.exr", layout="mitsuba-moment", spp=16)
    np.testing.assert_array_equal(tensor.stats.mean, film.stats.mean)
    np.testing.assert_array_equal(tensor.stats.m2, film.stats.m2)
    for method in ("gem", "awr", "box"):
        out = d / f"{method}.exr"
        code, _, err = run_cli(["denoise", d / "film.exr", "-o", out, "--method", method, "--spp", "16"], capsys)
        assert code == 0, err
        opts = {"variance": "sample"} if method == "awr" else {}
        expect = film.output_image(mcrecon.reconstruct(film.stats, method=method, **opts))
        np.testing.assert_allclose(read_exr(out)[0], expect.astype(np.float32), rtol=1e-6, atol=1e-7)


# ------------------------------------------------------------------ features
def _feature_images(seed=5, h=H, w=W):
    rng = np.random.default_rng(seed)
    return {"albedo": rng.uniform(0, 1, (h, w, 3)), "normal": rng.normal(size=(h, w, 3)),
            "geo": rng.normal(size=(h, w, 3)), "depth": rng.uniform(1, 9, (h, w))}


def test_pbrt_gbuffer_features_albedo_shading_normal_and_depth(tmp_path):
    s = samples(6)
    f = _feature_images()
    path = tmp_path / "g.exr"
    pbrt_exr(path, s)
    from mcrecon.io.images import open_exr
    ch = dict(open_exr(path)[0])
    for i, c in enumerate("RGB"):
        ch[f"Albedo.{c}"] = f["albedo"][..., i]
    for i, c in enumerate("XYZ"):
        ch[f"Ns.{c}"], ch[f"N.{c}"], ch[f"P.{c}"] = f["normal"][..., i], f["geo"][..., i], f["depth"] * (i + 1) / 3
    write_channels(path, ch, samplesPerPixel=SPP)
    pix = read_pixel_stats_exr(path)
    st = pix.stats
    assert st.feature_names == ("albedo", "normal", "depth")
    assert pix.sources["features"] == {"albedo": ("Albedo.R", "Albedo.G", "Albedo.B"),
                                       "normal": ("Ns.X", "Ns.Y", "Ns.Z"), "depth": ("P.Z",)}
    f32 = lambda a: np.asarray(a, np.float32).astype(np.float64)  # noqa: E731 (the file stores float32)
    np.testing.assert_array_equal(st.features["albedo"].mean, f32(f["albedo"]))
    np.testing.assert_array_equal(st.features["normal"].mean, f32(f["normal"]))  # Ns, not N
    np.testing.assert_array_equal(st.features["depth"].mean[..., 0], f32(f["depth"]))  # P.Z
    assert st.features["albedo"].channels == ("R", "G", "B") and st.features["depth"].channels == ("Z",)
    np.testing.assert_array_equal(st.features["albedo"].m2, 0.0)  # pbrt writes no feature variance
    # the colour is what it was without features
    plain = read_pixel_stats_exr(path, features="none")
    assert plain.stats.feature_names == () and plain.sources["features"] == {}
    np.testing.assert_array_equal(plain.stats.mean, st.mean)
    np.testing.assert_array_equal(plain.stats.m2, st.m2)
    # without the shading normal, the geometric one
    del ch["Ns.X"], ch["Ns.Y"], ch["Ns.Z"]
    write_channels(path, ch, samplesPerPixel=SPP)
    np.testing.assert_array_equal(read_pixel_stats_exr(path).stats.features["normal"].mean, f32(f["geo"]))


def test_mitsuba_moment_of_aov_features_give_their_variances(tmp_path):
    """moment(aov(albedo, nn, dd) + path): P.albedo.R ... with m2_: the features' sample variances."""
    s = samples(7)
    rng = np.random.default_rng(8)
    per = {"albedo": rng.uniform(0, 1, s.shape), "nn": rng.normal(size=s.shape), "dd": rng.uniform(1, 5, s.shape[:3])}
    path = tmp_path / "m.exr"
    m1, var = mitsuba_exr(path, s)
    from mcrecon.io.images import open_exr
    ch = dict(open_exr(path)[0])
    comps = {"albedo": "RGB", "nn": "XYZ", "dd": "T"}
    for name, x in per.items():
        x = x.reshape(s.shape[:3] + (-1,))
        for i, c in enumerate(comps[name]):
            ch[f"nested.{name}.{c}"] = x[..., i].mean(axis=2)
            ch[f"m2_nested.{name}.{c}"] = (x[..., i] ** 2).mean(axis=2)
    # the inner integrator's own image as an AOV: not a feature, not a second colour output
    for c in "RGBA":
        ch[f"nested.inner.{c}"] = ch[f"m2_nested.inner.{c}"] = np.ones((H, W))
    write_channels(path, ch)
    pix = read_pixel_stats_exr(path, spp=SPP)
    assert pix.layout == "mitsuba-moment" and pix.sources["mean"] == ("nested.X", "nested.Y", "nested.Z")
    assert pix.sources["features"] == {"albedo": ("nested.albedo.R", "nested.albedo.G", "nested.albedo.B"),
                                       "normal": ("nested.nn.X", "nested.nn.Y", "nested.nn.Z"),
                                       "depth": ("nested.dd.T",)}
    for feat, name in (("albedo", "albedo"), ("normal", "nn"), ("depth", "dd")):
        x = per[name].reshape(s.shape[:3] + (-1,))
        fs = pix.stats.features[feat]
        np.testing.assert_allclose(fs.mean, x.mean(axis=2), rtol=1e-6, atol=1e-7)
        # n/(n-1) (m2 - m1^2) from float32 moments: the brute-force unbiased variance
        np.testing.assert_allclose(fs.sample_variance(), x.var(axis=2, ddof=1), rtol=2e-3, atol=2e-5)


def test_mitsuba_aov_names_with_an_explicit_colour_mapping(tmp_path):
    rng = np.random.default_rng(9)
    f = _feature_images(10)
    ch = {c: rng.random((H, W)) for c in ("R", "G", "B", "vR", "vG", "vB")}
    for i, c in enumerate("RGB"):
        ch[f"albedo.{c}"] = f["albedo"][..., i]
    for i, c in enumerate("XYZ"):
        ch[f"sh_normal.{c}"] = f["normal"][..., i]
    ch["dd.y.T"] = f["depth"]
    write_channels(tmp_path / "a.exr", ch)
    pix = read_pixel_stats_exr(tmp_path / "a.exr", mean="R,G,B", variance="vR,vG,vB", spp=4)
    assert pix.sources["features"] == {"albedo": ("albedo.R", "albedo.G", "albedo.B"),
                                       "normal": ("sh_normal.X", "sh_normal.Y", "sh_normal.Z"),
                                       "depth": ("dd.y.T",)}
    np.testing.assert_allclose(pix.stats.features["depth"].mean[..., 0], f["depth"], rtol=1e-6)
    # two normals (sh_normal and nn) are ambiguous: refused naming both, a mapping chooses
    for i, c in enumerate("XYZ"):
        ch[f"nn.{c}"] = f["geo"][..., i]
    write_channels(tmp_path / "b.exr", ch)
    with pytest.raises(InputError, match=r"features/normal: ambiguous: sh_normal.X,sh_normal.Y,sh_normal.Z and "
                                         r"nn.X,nn.Y,nn.Z .*features=\{'normal'"):
        read_pixel_stats_exr(tmp_path / "b.exr", mean="R,G,B", variance="vR,vG,vB", spp=4)
    pix = read_pixel_stats_exr(tmp_path / "b.exr", mean="R,G,B", variance="vR,vG,vB", spp=4,
                               features={"normal": "nn.X,nn.Y,nn.Z", "albedo": "albedo.R,albedo.G,albedo.B"})
    assert pix.stats.feature_names == ("normal", "albedo")
    np.testing.assert_allclose(pix.stats.features["normal"].mean, f["geo"], rtol=1e-6)
    with pytest.raises(InputError, match="features/normal: channel 'nope.X' missing"):
        read_pixel_stats_exr(tmp_path / "b.exr", mean="R,G,B", variance="vR,vG,vB", spp=4,
                             features={"normal": "nope.X,nope.Y,nope.Z"})
    with pytest.raises(InputError, match="features: 'some'; valid: 'auto', 'none'"):
        read_pixel_stats_exr(tmp_path / "b.exr", mean="R,G,B", variance="vR,vG,vB", spp=4, features="some")


def test_nonfinite_feature_values_are_zeroed_and_warned(tmp_path):
    s = samples(11)
    path = tmp_path / "n.exr"
    pbrt_exr(path, s)
    from mcrecon.io.images import open_exr
    ch = dict(open_exr(path)[0])
    depth = np.full((H, W), 3.0)
    depth[2, 3] = np.inf  # a ray that left the scene
    depth[4, 1] = np.nan
    depth[5, 5] = np.finfo(np.float32).max  # a float32 writer's "no hit"
    ch["P.Z"] = depth
    write_channels(path, ch, samplesPerPixel=SPP)
    with pytest.warns(McreconWarning, match=r"3 pixel\(s\) with NaN, Inf or beyond \+-1e\+30 feature values set to 0"):
        pix = read_pixel_stats_exr(path)
    d = pix.stats.features["depth"].mean[..., 0]
    assert d[2, 3] == 0 and d[4, 1] == 0 and d[5, 5] == 0
    assert np.all(np.delete(d.ravel(), [2 * W + 3, 4 * W + 1, 5 * W + 5]) == 3.0)
    np.testing.assert_array_equal(pix.stats.mean, read_pixel_stats_exr(path, features="none").stats.mean)


def test_a_partial_feature_is_said_not_dropped_silently(tmp_path):
    s = samples(12)
    path = tmp_path / "p.exr"
    pbrt_exr(path, s)
    from mcrecon.io.images import open_exr
    ch = dict(open_exr(path)[0])
    del ch["Albedo.B"]
    write_channels(path, ch, samplesPerPixel=SPP)
    with pytest.warns(McreconWarning, match=r"features/albedo: Albedo.R, Albedo.G present without Albedo.B: "
                                             r"the albedo is left out"):
        pix = read_pixel_stats_exr(path)
    assert "albedo" not in pix.stats.features and "normal" in pix.stats.features


def test_half_buffer_pair_keeps_features(tmp_path):
    from mcrecon.core.halves import merge_halves

    paths = []
    for k in (0, 1):
        s = samples(20 + k)
        p = tmp_path / f"h{k}.exr"
        pbrt_exr(p, s)
        from mcrecon.io.images import open_exr
        ch = dict(open_exr(p)[0])
        for i, c in enumerate("RGB"):
            ch[f"Albedo.{c}"] = np.full((H, W), 0.25 * (k + 1) + 0.1 * i)
        write_channels(p, ch, samplesPerPixel=SPP)
        paths.append(p)
    a, b = read_half_buffer_exrs(*paths)
    assert a.stats.feature_names == b.stats.feature_names == ("albedo", "normal", "depth")
    m = merge_halves(a.stats, b.stats)
    # equal counts: the merged albedo mean is the halves' average
    np.testing.assert_allclose(m.features["albedo"].mean[0, 0], [0.375, 0.475, 0.575], rtol=1e-6)
    # one half without the albedo: refused, naming the features of both
    from mcrecon.io.images import open_exr
    ch = {k: v for k, v in open_exr(paths[1])[0].items() if not k.startswith("Albedo.")}
    write_channels(paths[1], ch, samplesPerPixel=SPP)
    with pytest.raises(InputError, match=r"features: the halves carry different features: albedo \(Albedo.R,"
                                         r"Albedo.G,Albedo.B\), normal .* vs normal"):
        read_half_buffer_exrs(*paths)
    a, b = read_half_buffer_exrs(*paths, features="none")
    assert a.stats.feature_names == b.stats.feature_names == ()


def test_denoise_command_reads_pbrt_features(tmp_path, capsys):
    s = samples(12)
    path = tmp_path / "g.exr"
    pbrt_exr(path, s, extra=True)  # Albedo, N, Ns, P among the channels
    code, _, err = run_cli(["denoise", path, "-o", tmp_path / "o.exr", "--method", "box"], capsys)
    assert code == 0, err
    assert "features albedo (Albedo.R,Albedo.G,Albedo.B), normal (Ns.X,Ns.Y,Ns.Z), depth (P.Z)" in err


def test_info_lists_the_features_of_an_exr(tmp_path, capsys):
    import json

    s = samples(13)
    path = tmp_path / "m.exr"
    mitsuba_exr(path, s)
    from mcrecon.io.images import open_exr
    ch = dict(open_exr(path)[0])
    for c in "RGB":
        ch[f"nested.albedo.{c}"] = ch[f"m2_nested.albedo.{c}"] = np.full((H, W), 0.5)
    ch["nested.dd.T"] = ch["m2_nested.dd.T"] = np.ones((H, W))
    write_channels(path, ch)
    code, out, err = run_cli(["info", path], capsys)
    assert code == 0, err
    assert "layout                   mitsuba-moment" in out
    assert "count                    none in the file (pass --spp N)" in out
    assert ("feature albedo           nested.albedo.R,nested.albedo.G,nested.albedo.B (variance from "
            "m2_nested.albedo.R,m2_nested.albedo.G,m2_nested.albedo.B)") in out
    assert "feature depth            nested.dd.T (variance from m2_nested.dd.T)" in out
    code, out, _ = run_cli(["info", "--json", path], capsys)
    info = json.loads(out)
    assert [f["name"] for f in info["features"]] == ["albedo", "depth"]
    assert (info["width"], info["height"]) == (W, H)
    # pbrt: its names, its count attribute, no feature variances
    pbrt_exr(tmp_path / "p.exr", s)
    code, out, _ = run_cli(["info", tmp_path / "p.exr"], capsys)
    assert "layout                   pbrt-v4" in out and f"samplesPerPixel = {SPP}" in out
    assert "feature normal           Ns.X,Ns.Y,Ns.Z (no variance)" in out
    assert "feature depth            P.Z (no variance)" in out


def test_real_mitsuba_moment_of_aov_features(mitsuba_moment_exrs, capsys):
    d = mitsuba_moment_exrs
    pix = read_pixel_stats_exr(d / "aov.exr", spp=16)
    assert pix.layout == "mitsuba-moment" and pix.sources["mean"] == ("nested.X", "nested.Y", "nested.Z")
    assert pix.sources["features"] == {"albedo": ("nested.albedo.R", "nested.albedo.G", "nested.albedo.B"),
                                       "normal": ("nested.nn.X", "nested.nn.Y", "nested.nn.Z"),
                                       "depth": ("nested.dd.T",)}
    st = pix.stats
    a = st.features["albedo"].mean
    assert a.min() >= 0 and a.max() <= 1 and a.max() > 0.1  # the Cornell box's diffuse walls
    # a 24x16 film shows the box and black beyond its sides (depth 0 there: nothing hit); pixel means
    # of unit normals have length <= 1, 1 inside a face
    depth = st.features["depth"].mean[..., 0]
    assert (depth >= 0).all() and (depth > 0).mean() > 0.5
    length = np.linalg.norm(st.features["normal"].mean, axis=-1)
    assert length.max() <= 1 + 1e-5 and np.median(length[depth > 0]) > 0.98  # 24x16: many edge pixels
    assert (st.features["albedo"].sample_variance() >= 0).all()
    code, _, err = run_cli(["denoise", d / "aov.exr", "-o", d / "aov_box.exr", "--spp", "16"], capsys)
    assert code == 0 and "features albedo (nested.albedo.R" in err, err


def test_a_multi_part_exr_says_what_it_does_not_read(tmp_path):
    # a renderer's feature part (part 1) was dropped without a word
    import OpenEXR

    path = tmp_path / "mp.exr"
    head = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File([OpenEXR.Part({**head, "name": "beauty"}, {"RGB": np.ones((4, 5, 3), np.float32)}),
                  OpenEXR.Part({**head, "name": "aux"}, {"Albedo": np.ones((4, 5, 3), np.float32)})]).write(str(path))
    from mcrecon.io.images import open_exr
    with pytest.warns(McreconWarning, match=r"2 parts; only the first is read, not the channels of the others "
                                             r"\(Albedo.B, Albedo.G, Albedo.R\)"):
        arrays = open_exr(path)[0]
    assert sorted(arrays) == ["B", "G", "R"]

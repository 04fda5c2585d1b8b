"""Blender Cycles' multilayer EXRs: the cycles layout, what one render gives, and real renders by bpy."""

import importlib.util
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import mcrecon
from mcrecon import InputError
from mcrecon.io import read_pixel_stats_exr

from helpers import run_cli

H, W = 6, 7
L = "ViewLayer"


def _write(path, channels: dict, header: dict | None = None):
    import OpenEXR

    head = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **(header or {})}
    with OpenEXR.File(head, {k: np.ascontiguousarray(v, np.float32) for k, v in channels.items()}) as f:
        f.write(str(path))
    return path


def cycles_exr(path, *, seed=0, denoised=False, spp="8", layer=L, features=True, nan=False):
    """A file named as Cycles names its passes; Combined is a constant 99 when 'denoised' (so a test sees
    which image was read)."""
    rng = np.random.default_rng(seed)
    noisy = rng.uniform(0.2, 1.0, (H, W, 3))
    if nan:
        noisy[2, 3, 1] = np.nan
    ch = {}
    for i, c in enumerate("RGBA"):
        ch[f"{layer}.Combined.{c}"] = np.full((H, W), 99.0) if denoised else (noisy[..., i] if i < 3 else 1.0 + 0 * noisy[..., 0])
        if denoised:
            ch[f"{layer}.Noisy Image.{c}"] = noisy[..., i] if i < 3 else np.ones((H, W))
    if features:
        for i, c in enumerate("RGB"):
            ch[f"{layer}.Denoising Albedo.{c}"] = np.full((H, W), 0.1 * (i + 1))
        for i, c in enumerate("XYZ"):
            ch[f"{layer}.Denoising Normal.{c}"] = np.full((H, W), float(i == 2))
        ch[f"{layer}.Denoising Depth.Z"] = np.full((H, W), 3.0)
    header = {f"cycles.{layer}.samples": spp} if spp is not None else {}
    _write(path, ch, header)
    return noisy


def test_one_render_is_read_as_means_with_features_and_the_header_count(tmp_path):
    noisy = cycles_exr(tmp_path / "a.exr")
    f = read_pixel_stats_exr(tmp_path / "a.exr")
    assert f.layout == "cycles" and not f.has_variance
    assert f.sources["mean"] == (f"{L}.Combined.R", f"{L}.Combined.G", f"{L}.Combined.B")
    assert f.count_source == f"header attribute cycles.{L}.samples = 8"
    assert f.output_channels == ("R", "G", "B") and f.output_matrix is None
    np.testing.assert_allclose(f.stats.mean, noisy.astype(np.float32), rtol=0, atol=0)
    assert (f.stats.count == 8).all()
    assert f.stats.feature_names == ("albedo", "normal", "depth")
    np.testing.assert_allclose(f.stats.features["depth"].mean, 3.0)


def test_when_cycles_denoised_the_noisy_image_is_the_input_never_combined(tmp_path):
    noisy = cycles_exr(tmp_path / "d.exr", denoised=True)
    f = read_pixel_stats_exr(tmp_path / "d.exr")
    assert f.sources["mean"] == (f"{L}.Noisy Image.R", f"{L}.Noisy Image.G", f"{L}.Noisy Image.B")
    np.testing.assert_allclose(f.stats.mean, noisy.astype(np.float32), rtol=0, atol=0)
    with pytest.raises(InputError, match="denoised; the raw image is ViewLayer.Noisy Image"):
        read_pixel_stats_exr(tmp_path / "d.exr", layout="cycles",
                             mean=f"{L}.Combined.R,{L}.Combined.G,{L}.Combined.B")


def test_several_view_layers_are_named_and_one_can_be_chosen(tmp_path):
    cycles_exr(tmp_path / "a.exr")
    import OpenEXR

    with OpenEXR.File(str(tmp_path / "a.exr"), separate_channels=True) as f:
        ch = {k: np.asarray(v.pixels) for k, v in f.channels().items()}
    ch.update({k.replace(L, "Fg"): v for k, v in ch.items()})
    _write(tmp_path / "two.exr", ch, {f"cycles.{L}.samples": "8"})
    with pytest.raises(InputError, match="several view layers \\(Fg, ViewLayer\\)"):
        read_pixel_stats_exr(tmp_path / "two.exr")
    f = read_pixel_stats_exr(tmp_path / "two.exr", layout="cycles", mean="Fg.Combined.R,Fg.Combined.G,Fg.Combined.B")
    assert f.sources["features"]["albedo"][0] == "Fg.Denoising Albedo.R"


def test_one_render_serves_the_pixel_mean_and_refuses_methods_that_need_a_variance(tmp_path, capsys):
    noisy = cycles_exr(tmp_path / "a.exr")
    img = mcrecon.reconstruct(str(tmp_path / "a.exr"), method="box")
    np.testing.assert_allclose(img, noisy.astype(np.float32), rtol=0, atol=0)
    for method in ("gem", "auto", "awr"):
        with pytest.raises(InputError, match="no variance, which .* needs; render the frame K >= 2 times with "
                                             "different seeds"):
            mcrecon.reconstruct(str(tmp_path / "a.exr"), method=method)
    out = tmp_path / "out.exr"
    code, _, err = run_cli(["reconstruct", tmp_path / "a.exr", "-o", out, "--method", "gem"], capsys)
    assert code == 2 and not out.exists()
    assert err.count("\n") == 1 and "'shot.seed*.exr'" in err and "Traceback" not in err


def test_without_a_count_attribute_spp_is_asked_for(tmp_path):
    cycles_exr(tmp_path / "a.exr", spp=None)
    with pytest.raises(InputError, match="pass --spp N"):
        read_pixel_stats_exr(tmp_path / "a.exr")
    assert (read_pixel_stats_exr(tmp_path / "a.exr", spp=4).stats.count == 4).all()
    cycles_exr(tmp_path / "b.exr", spp="8")
    with pytest.raises(InputError, match="8 samples per pixel, but --spp says 4"):
        read_pixel_stats_exr(tmp_path / "b.exr", spp=4)


def test_nan_in_a_render_is_one_line_naming_the_file_and_channel(tmp_path):
    cycles_exr(tmp_path / "a.exr", nan=True)
    with pytest.raises(InputError) as exc:
        read_pixel_stats_exr(tmp_path / "a.exr")
    assert str(tmp_path / "a.exr") in str(exc.value) and f"{L}.Combined.G" in str(exc.value)


def test_info_names_the_layout_count_and_features(tmp_path, capsys):
    cycles_exr(tmp_path / "a.exr", denoised=True)
    code, out, _ = run_cli(["info", tmp_path / "a.exr"], capsys)
    assert code == 0
    assert "cycles" in out and f"cycles.{L}.samples = 8" in out and f"{L}.Denoising Albedo.R" in out


# ------------------------------------------------------------------ real renders (bpy)
_RENDER = textwrap.dedent('''
    import sys, bpy
    out_dir = sys.argv[1]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    sc.render.engine = "CYCLES"; sc.cycles.device = "CPU"
    sc.render.threads_mode = "FIXED"; sc.render.threads = 2
    sc.render.resolution_x = sc.render.resolution_y = 32; sc.render.resolution_percentage = 100
    sc.cycles.samples = 4; sc.cycles.use_adaptive_sampling = False
    sc.view_settings.view_transform = "Standard"
    sc.cycles.sample_clamp_direct = sc.cycles.sample_clamp_indirect = 0
    sc.view_layers[0].cycles.denoising_store_passes = True
    bpy.ops.mesh.primitive_plane_add(size=10)
    bpy.ops.mesh.primitive_uv_sphere_add(radius=1, location=(0, 0, 1))
    bpy.ops.object.light_add(type="AREA", location=(2, -2, 4)); bpy.context.object.data.energy = 500
    bpy.ops.object.camera_add(location=(0, -6, 3), rotation=(1.15, 0, 0)); sc.camera = bpy.context.object
    sc.render.image_settings.file_format = "OPEN_EXR_MULTILAYER"
    sc.render.image_settings.color_depth = "32"
    sc.render.use_persistent_data = True
    for seed in range(3):
        sc.cycles.seed = seed
        sc.cycles.use_denoising = seed == 2
        sc.render.filepath = f"{out_dir}/shot.seed{seed}.exr"
        bpy.ops.render.render(write_still=True)
''')


@pytest.mark.skipif(importlib.util.find_spec("bpy") is None, reason="needs bpy: pip install 'mcrecon[blender]'")
def test_real_cycles_renders_are_read_and_reconstructed_as_a_seed_set(tmp_path):
    """Three 32x32 renders at 4 spp by Blender's own Cycles; the third denoised (so it has a Noisy Image)."""
    subprocess.run([sys.executable, "-c", _RENDER, str(tmp_path)], check=True, capture_output=True, timeout=120)
    plain = read_pixel_stats_exr(tmp_path / "shot.seed0.exr")
    assert plain.layout == "cycles" and not plain.has_variance
    assert plain.sources["mean"][0] == "ViewLayer.Combined.R"
    assert plain.sources["features"] == {
        "albedo": ("ViewLayer.Denoising Albedo.R", "ViewLayer.Denoising Albedo.G", "ViewLayer.Denoising Albedo.B"),
        "normal": ("ViewLayer.Denoising Normal.X", "ViewLayer.Denoising Normal.Y", "ViewLayer.Denoising Normal.Z"),
        "depth": ("ViewLayer.Denoising Depth.Z",)}
    assert (plain.stats.count == 4).all()  # cycles.ViewLayer.samples
    denoised = read_pixel_stats_exr(tmp_path / "shot.seed2.exr")
    assert denoised.sources["mean"][0] == "ViewLayer.Noisy Image.R"
    # the denoised file's passes differ from the plain ones' (Noisy Image): a set of the two plain ones
    with pytest.raises(InputError, match="channels"):
        mcrecon.reconstruct(str(tmp_path / "shot.seed*.exr"), method="gem")
    rec = mcrecon.reconstruct([tmp_path / "shot.seed0.exr", tmp_path / "shot.seed1.exr"], method="gem", full=True)
    assert rec.image.shape == (32, 32, 3) and np.isfinite(rec.image).all()
    assert int(rec.inputs.stats.count[0, 0]) == 8


def test_two_renders_given_as_a_pair_are_a_seed_set_of_two(tmp_path, capsys):
    x = np.stack([cycles_exr(tmp_path / f"s{i}.exr", seed=i) for i in range(2)]).astype(np.float32).astype(float)
    for method in ("gem", "auto"):
        rec = mcrecon.reconstruct((str(tmp_path / "s0.exr"), str(tmp_path / "s1.exr")), method=method, full=True)
        assert rec.files[0].renders == 2 and (rec.inputs.stats.count == 16).all()
        np.testing.assert_allclose(rec.inputs.stats.mean, x.mean(0), rtol=1e-12)
    out = tmp_path / "out.exr"
    code, _, err = run_cli(["reconstruct", tmp_path / "s0.exr", "--half-buffer", tmp_path / "s1.exr", "-o", out,
                            "--method", "auto"], capsys)
    assert code == 0 and out.exists() and "(2 renders)" in err


def test_a_glob_with_a_half_buffer_and_an_unquoted_glob_are_one_line_each(tmp_path, capsys):
    for i in range(3):
        cycles_exr(tmp_path / f"s{i}.exr", seed=i)
    out = tmp_path / "out.exr"
    code, _, err = run_cli(["reconstruct", tmp_path / "s*.exr", "--half-buffer", tmp_path / "s0.exr", "-o", out,
                            "--method", "auto"], capsys)
    assert code == 2 and "a glob is a seed set, which gives its own half buffers" in err and not out.exists()
    code, _, err = run_cli(["reconstruct", tmp_path / "s0.exr", tmp_path / "s1.exr", "-o", out], capsys)
    assert code == 2 and "quote a seed set's glob" in err and err.count("\n") == 1

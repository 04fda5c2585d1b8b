"""The Blender Cycles bridge (``mcrecon blender log|reference``): Cycles' own samples in a sample log.

The scene is built in bpy inside the test (a subprocess: bpy stays out of the test process) and saved
as a .blend: an orthographic camera looking down on a grey floor lit by a point light, with an
emitting quad in the top-left corner whose right edge falls at film x = 20.3, so a sample's colour
says on which side of x = 20.3 it was traced.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest

from helpers import cli_env, run_cli_process
from mcrecon.cli import main
from mcrecon.io import read_exr, read_log
from mcrecon.renderers import blender as bl

NEEDS_BPY = pytest.mark.skipif(not bl.bpy_available(), reason="needs bpy: pip install 'mcrecon[blender]'")
W, H, EDGE, SPP = 64, 48, 20.3, 8
EMIT = (4.0, 2.0, 1.0)

SCENE = textwrap.dedent("""
    import sys
    import bpy
    w, h, edge, path = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]), sys.argv[4]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    sc.render.resolution_x, sc.render.resolution_y, sc.render.resolution_percentage = w, h, 100
    cam = bpy.data.cameras.new("cam"); cam.type = "ORTHO"; cam.ortho_scale = 2.0
    co = bpy.data.objects.new("cam", cam); co.location = (0, 0, 10)
    sc.collection.objects.link(co); sc.camera = co
    world = bpy.data.worlds.new("w"); world.use_nodes = True; sc.world = world
    world.node_tree.nodes["Background"].inputs[0].default_value = (0.05, 0.05, 0.05, 1)
    def quad(name, x0, x1, y0, y1, z, mat):
        me = bpy.data.meshes.new(name)
        me.from_pydata([(x0, y0, z), (x1, y0, z), (x1, y1, z), (x0, y1, z)], [], [(0, 1, 2, 3)])
        ob = bpy.data.objects.new(name, me); sc.collection.objects.link(ob); ob.data.materials.append(mat)
    em = bpy.data.materials.new("em"); em.use_nodes = True
    nt = em.node_tree; nt.nodes.clear()
    e = nt.nodes.new("ShaderNodeEmission"); e.inputs[0].default_value = (4, 2, 1, 1)
    o = nt.nodes.new("ShaderNodeOutputMaterial"); nt.links.new(e.outputs[0], o.inputs[0])
    dif = bpy.data.materials.new("dif"); dif.use_nodes = True
    dif.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (0.6, 0.6, 0.6, 1)
    quad("light", -1.5, edge / (w / 2) - 1, 0.2, 1.5, 0.0, em)   # film rows 0 .. 17.6 (the top)
    quad("floor", -3, 3, -3, 3, -1.0, dif)
    lt = bpy.data.lights.new("pt", "POINT"); lt.energy = 300; lt.shadow_soft_size = 0.5
    lo = bpy.data.objects.new("pt", lt); lo.location = (0.5, -0.3, 1.0); sc.collection.objects.link(lo)
    bpy.ops.wm.save_as_mainfile(filepath=path)
""")


def _mcrecon(*args):
    return run_cli_process(args, timeout=600)


@pytest.fixture(scope="module")
def cycles(tmp_path_factory):
    """The test scene, its log (SPP samples, 2 threads) and Cycles' own SPP-sample render of it."""
    d = tmp_path_factory.mktemp("cycles")
    blend = d / "edge.blend"
    subprocess.run([sys.executable, "-c", SCENE, str(W), str(H), str(EDGE), str(blend)], check=True,
                   capture_output=True, env=cli_env(), timeout=300)
    r = _mcrecon("blender", "log", blend, "--spp", SPP, "--threads", 2, "-o", d / "log.h5")
    assert r.returncode == 0, r.stderr
    r = _mcrecon("blender", "reference", blend, "--spp", SPP, "--threads", 2, "-o", d / "ref.exr")
    assert r.returncode == 0, r.stderr
    return blend, read_log(d / "log.h5"), read_exr(d / "ref.exr")[0]


def _pixel_stats(log):
    c = log.read_all(features=("albedo", "normal", "depth"))
    idx = np.floor(c.positions[:, 1]).astype(int) * log.width + np.floor(c.positions[:, 0]).astype(int)
    n = np.bincount(idx, minlength=log.width * log.height)
    mean = np.stack([np.bincount(idx, weights=c.values[:, k], minlength=n.size) for k in range(3)], 1) / n[:, None]
    sq = np.stack([np.bincount(idx, weights=c.values[:, k].astype(np.float64) ** 2, minlength=n.size)
                   for k in range(3)], 1) / n[:, None]
    return c, idx, n, mean.reshape(log.height, log.width, 3), np.maximum(sq - mean ** 2, 0).reshape(log.height, log.width, 3)


@NEEDS_BPY
def test_log_mean_is_cycles_own_render_far_within_the_noise(cycles):
    _, log, ref = cycles
    c, idx, n, mean, var = _pixel_stats(log)
    assert (log.width, log.height) == (W, H) and np.all(n == SPP) and log.n_rounds == SPP
    err = np.abs(mean - ref[..., :3])
    # Cycles' renders are not bit-reproducible (differences up to 2e-4), but the log's samples are the
    # render's samples: the mean agrees far within one sample's noise over N (independent samples' spread)
    assert err.max() < 2e-3
    noisy = var > 1e-4
    assert noisy.sum() > 1000
    assert np.mean(err[noisy]) < 0.01 * np.mean(np.sqrt(var[noisy] / SPP))


@NEEDS_BPY
def test_positions_are_where_cycles_traced_each_sample(cycles):
    _, log, ref = cycles
    c, idx, n, mean, var = _pixel_stats(log)
    # each pixel's k-th sample is in that pixel (rounds in pixel order, row 0 the top), sample 0 at the centre
    assert np.array_equal(idx, np.tile(np.arange(W * H), SPP))
    assert np.abs(c.positions[: W * H] - np.floor(c.positions[: W * H]) - 0.5).max() < 2e-3
    frac = c.positions[W * H:] - np.floor(c.positions[W * H:])
    assert frac.std(axis=0).min() > 0.2  # the other samples spread over the pixel
    # the emitter's edge at film x = 20.3 splits column 20: a sample left of it sees the emitter
    col = (np.floor(c.positions[:, 0]) == 20) & (c.positions[:, 1] < 17)
    x, emit = c.positions[col, 0], np.all(c.values[col] == EMIT, axis=1)
    assert np.all(emit[x < EDGE - 2e-3]) and not np.any(emit[x > EDGE + 2e-3])
    assert 0.1 < emit.mean() < 0.6
    # the top-left corner is the emitter in the log and in Cycles' own render: row 0 is the top
    assert np.all(mean[:16, :20] == EMIT) and np.all(ref[:16, :20, :3] == EMIT)
    assert not np.any(np.all(mean[20:, :20] == EMIT, axis=-1))


@NEEDS_BPY
def test_features_and_settings_are_stored(cycles):
    _, log, _ = cycles
    c = log.read_all(features=("albedo", "normal", "depth"))
    assert c.features["albedo"].shape == (SPP * W * H, 3) and c.features["depth"].shape == (SPP * W * H,)
    on_emitter = np.all(c.values == EMIT, axis=1)
    # the emitter's albedo is its radiance, stored as given (above 1); depth is larger on the floor below
    assert np.allclose(c.features["albedo"][on_emitter], EMIT)
    assert c.features["depth"][~on_emitter].mean() > c.features["depth"][on_emitter].mean() > 0
    meta = log.metadata
    assert meta["renderer"] == "blender-cycles" and meta["view_transform"] == "Standard"
    assert meta["pixel_filter_type"] == "BOX" and meta["filter_width"] == 1.0 and meta["spp"] == SPP
    assert meta["sample_clamp_direct"] == meta["sample_clamp_indirect"] == 0 and meta["film_transparent"] is False


@NEEDS_BPY
def test_bad_input_is_one_line_naming_the_flag(cycles, tmp_path):
    blend = cycles[0]
    r = _mcrecon("blender", "log", blend, "--spp", 2, "--camera", "nope", "-o", tmp_path / "a.h5")
    assert r.returncode == 2 and "--camera" in r.stderr and "'cam'" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "a.h5").exists()
    r = _mcrecon("blender", "log", blend, "--spp", 1, "--features", "none", "-o", tmp_path / "b.h5")
    assert r.returncode == 0 and read_log(tmp_path / "b.h5").feature_names == ()


@pytest.mark.parametrize("args, where", [
    (["missing.blend", "--spp", "2"], "missing.blend"),
    (["scene.txt", "--spp", "2"], "scene.txt"),
    (["fake.blend", "--spp", "0"], "--spp"),
    (["fake.blend", "--spp", "two"], "--spp"),
    (["fake.blend", "--spp", "2", "--features", "colour"], "--features"),
    (["notblend.blend", "--spp", "2"], "notblend.blend"),
])
def test_bad_input_without_rendering(tmp_path, capsys, monkeypatch, args, where):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "scene.txt").write_text("x")
    (tmp_path / "fake.blend").write_bytes(b"BLENDER-v405" + bytes(64))
    (tmp_path / "notblend.blend").write_text("hello")
    assert main(["blender", "log", *args, "-o", "out.h5"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and where in err
    assert not (tmp_path / "out.h5").exists()


def test_missing_bpy_says_how_to_install(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(bl, "bpy_available", lambda: False)
    (tmp_path / "fake.blend").write_bytes(b"BLENDER-v405" + bytes(64))
    assert main(["blender", "reference", str(tmp_path / "fake.blend"), "--spp", "2",
                 "-o", str(tmp_path / "r.exr")]) == 2
    assert "pip install 'mcrecon[blender]'" in capsys.readouterr().err


def test_existing_log_needs_overwrite(tmp_path, capsys):
    (tmp_path / "fake.blend").write_bytes(b"BLENDER-v405" + bytes(64))
    (tmp_path / "out.h5").write_bytes(b"keep")
    assert main(["blender", "log", str(tmp_path / "fake.blend"), "--spp", "2", "-o", str(tmp_path / "out.h5")]) == 2
    assert "--overwrite" in capsys.readouterr().err and (tmp_path / "out.h5").read_bytes() == b"keep"

"""Bad input on the feature surfaces: logs, pixel-statistics EXRs, Mitsuba scenes and renderer replies.

Each case ended in a traceback, an allocation of terabytes, a silently dropped feature, a documented
input refused, or an error of more than one line (or without the field it is about).  Every refusal is
one line naming the file and the field, with the fix; legitimate input gives its result.
"""

import ast
import json
import os
import subprocess
import sys
import textwrap
import warnings

import h5py
import numpy as np
import pytest

from mcrecon import InputError
from mcrecon.io import append_log, read_log, write_exr, write_log

from helpers import ROOT, cli_env, jittered_renderer, run_cli

W, H, SPP = 12, 10, 4


def _one_line(code, err, *matches):
    assert code == 2, err
    assert err.count("\n") == 1 and err.startswith("mcrecon: error: ") and "Traceback" not in err, err
    for m in matches:
        assert m in err, err


def _log(path, *, features=None, reference=None):
    rng = np.random.default_rng(0)
    n = W * H * SPP
    feats = {"depth": rng.random(n).astype(np.float32), "albedo": rng.random((n, 3))} if features is None \
        else features
    return write_log(path, rng.random((n, 2)) * [W, H], rng.random((n, 3)).astype(np.float32), width=W, height=H,
                     features=feats, reference=reference, metadata={"renderer": "test"})


# ------------------------------------------------------------------ a feature declared billions wide
_BOUNDED = textwrap.dedent("""
    import contextlib, io, json, resource, sys, traceback
    limit = 6 << 30  # a memory limit far below what reading one row of the feature takes (32 GB)
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    from mcrecon.cli import main
    out = []
    for argv in json.loads(sys.argv[1]):
        o, e = io.StringIO(), io.StringIO()
        try:
            with contextlib.redirect_stdout(o), contextlib.redirect_stderr(e):
                code = main(argv)
        except BaseException:
            code, e = "traceback", io.StringIO(traceback.format_exc())
        out.append({"code": code, "out": o.getvalue(), "err": e.getvalue()})
    print(json.dumps(out))
""")


def test_a_feature_declared_billions_wide_is_named_from_its_metadata_not_read(tmp_path):
    """`info` read a whole row of each feature for its dtype (killed for memory), splat asked for 14 TiB,
    nfor and auto blamed the film size: the width is known from the dataset's metadata."""
    path = _log(tmp_path / "wide.h5")
    with h5py.File(path, "r+") as f:  # declared, never written: the file stays small
        f["features"].create_dataset("wide", shape=(W * H * SPP, 4_000_000_000), dtype="f8", chunks=(1, 1 << 17))
    assert path.stat().st_size < 1 << 20
    log = read_log(path)
    assert log.feature_dtypes["wide"] == np.float64 and log.feature_shapes["wide"] == (4_000_000_000,)
    out = tmp_path / "o.exr"
    runs = [["info", path]] + [["reconstruct", path, "--method", m, "-o", out] for m in ("splat", "nfor", "auto",
                                                                                         "box")]
    p = subprocess.run([sys.executable, "-c", _BOUNDED, json.dumps([[str(a) for a in r] for r in runs])],
                       capture_output=True, text=True, env=cli_env(), timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    info, *recs, box = json.loads(p.stdout)
    assert info["code"] == 0, info["err"]
    assert "wide" in info["out"] and "shape (4000000000,), float64" in info["out"], info["out"]
    for r in recs:
        _one_line(r["code"], r["err"], str(path), "features/wide", "4000000000 components, at most 64")
        assert "GiB" not in r["err"]  # the feature, not the film size, is named
    assert box["code"] == 0, box["err"]


def test_the_component_limit_is_applied_where_usable_features_are_chosen(tmp_path):
    from mcrecon.core.features import source_layout, usable_names

    path = _log(tmp_path / "w.h5", features={"z": np.zeros((W * H * SPP, 65), np.float32),
                                             "depth": np.zeros(W * H * SPP, np.float32)})
    log = read_log(path)
    with pytest.raises(InputError, match=r"w\.h5: features/z: per-sample shape \(65,\): 65 components, at most 64"):
        usable_names(log)
    with pytest.raises(InputError, match=r"features/z: .*65 components"):
        source_layout(log, ["z"])
    assert source_layout(log, ["depth"]) == {"depth": 1}


# ------------------------------------------------------------------ Mitsuba scenes
def _mitsuba_ok():
    from mcrecon.renderers.mitsuba import mitsuba_available

    return mitsuba_available()


def _scene(path, width, height):
    path.write_text(f"""<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="2"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="45"/>
    <transform name="to_world"><lookat origin="0,0,4" target="0,0,0" up="0,1,0"/></transform>
    <film type="hdrfilm"><integer name="width" value="{width}"/><integer name="height" value="{height}"/></film>
  </sensor>
  <shape type="sphere"><bsdf type="diffuse"/></shape>
  <emitter type="constant"/>
</scene>
""")
    return path


@pytest.mark.mitsuba
@pytest.mark.parametrize("size", [(0, 8), (70000, 70000)])
def test_a_mitsuba_film_no_log_can_hold_is_refused_first(tmp_path, capsys, size):
    """A film of width 0: ZeroDivisionError traceback.  70000x70000: the disk check came first, and its
    advice (lower --spp or --size) could not work for a scene file."""
    ok, reason = _mitsuba_ok()
    if not ok:
        pytest.skip(f"Mitsuba bridge unavailable: {reason}")
    xml = _scene(tmp_path / "s.xml", *size)
    code, _, err = run_cli(["mitsuba", "log", "--scene", xml, "--spp", "1", "-o", tmp_path / "s.h5"], capsys)
    _one_line(code, err, str(xml), "film width/height", f"{size[0]}x{size[1]}", "set the film's width and height "
              "in the scene")
    assert not (tmp_path / "s.h5").exists()


def test_the_disk_check_advises_what_can_work(tmp_path):
    from mcrecon.io.writer import check_log_fits

    st = os.statvfs(tmp_path)
    free = st.f_bavail * st.f_frsize
    pixels = int(free // (4 * 5)) // 3 + 1  # about a third of the disk per spp (3 channels: 20 B a sample)
    with pytest.raises(InputError, match=r"lower --spp to at most [23], or free disk space"):
        check_log_fits(tmp_path / "a.h5", 100 * pixels, 3, where="mitsuba log", spp=100)
    with pytest.raises(InputError, match=r"even 1 spp needs .* GiB: make the film smaller \(the film's "
                                         r"width/height in the scene\)"):
        check_log_fits(tmp_path / "b.h5", 4 * pixels, 3, where="mitsuba log", spp=1,
                       film="the film's width/height in the scene")


# ------------------------------------------------------------------ /reference of the wrong kind
def test_a_reference_group_is_refused_in_one_line(tmp_path, capsys):
    """An AttributeError traceback ('Group' object has no attribute 'shape') in compare, info and
    reconstruct."""
    path = _log(tmp_path / "r.h5")
    with h5py.File(path, "r+") as f:
        f.create_group("reference")
    img = write_exr(tmp_path / "img.exr", np.ones((H, W, 3), np.float32))
    for argv in (["info", path], ["compare", img, path], ["reconstruct", path, "-o", tmp_path / "o.exr"]):
        code, out, err = run_cli(argv, capsys)
        _one_line(code, err, str(path), "dataset /reference", "a group, expected a dataset")
        assert not out
    assert not (tmp_path / "o.exr").exists()


@pytest.mark.parametrize("kind", ["dangling", "loop", "external"])
def test_links_that_lead_nowhere_name_the_feature(tmp_path, capsys, kind):
    """'the file is damaged', without /features/NAME."""
    path = _log(tmp_path / "l.h5")
    with h5py.File(path, "r+") as f:
        f["features/bad"] = {"dangling": h5py.SoftLink("/nowhere"), "loop": h5py.SoftLink("/features/bad"),
                             "external": h5py.ExternalLink("missing.h5", "/x")}[kind]
        f["reference"] = h5py.SoftLink("/nowhere")
    for argv in (["info", path], ["reconstruct", path, "--method", "nfor", "-o", tmp_path / "o.exr"]):
        code, _, err = run_cli(argv, capsys)
        _one_line(code, err, str(path), "/features/bad", "store the data itself there, or delete it")
    with h5py.File(path, "r+") as f:
        del f["features/bad"]
    code, _, err = run_cli(["info", path], capsys)
    _one_line(code, err, "/reference: a soft link to /nowhere")


# ------------------------------------------------------------------ names and lines
def test_a_name_with_a_newline_keeps_the_error_on_one_line(tmp_path, capsys):
    path = _log(tmp_path / "nl.h5")
    with h5py.File(path, "r+") as f:
        f["features"].create_dataset("a\nb\x1b[2J", data=np.full(W * H * SPP, b"x"))
    code, _, err = run_cli(["info", path], capsys)
    _one_line(code, err, "/features/a\\nb\\x1b[2J", "expected a numeric dtype")
    exc = InputError("p\nq", "f", "x")
    assert exc.where == "p\nq" and str(exc) == "p\\nq: f: x"  # kept as given, shown on one line


def test_append_log_names_a_feature_it_cannot_store(tmp_path):
    """'writing the round failed (could not convert string to float)', without the feature."""
    path = _log(tmp_path / "a.h5")
    before = path.read_bytes()
    rng = np.random.default_rng(1)
    with pytest.raises(InputError, match=r"a\.h5: features/depth: dtype <U3, expected a numeric dtype"):
        append_log(path, rng.random((5, 2)) * [W, H], rng.random((5, 3)),
                   features={"depth": np.full(5, "abc"), "albedo": np.zeros((5, 3))})
    assert path.read_bytes() == before
    with pytest.raises(InputError, match=r"b\.h5: features/depth: dtype <U1, expected a numeric dtype"):
        write_log(tmp_path / "b.h5", np.zeros((2, 2)), np.zeros((2, 3)), width=2, height=2,
                  features={"depth": np.array(["a", "b"])})
    assert not (tmp_path / "b.h5").exists()


# ------------------------------------------------------------------ pixel-statistics EXRs
def _channels_exr(path, channels: dict):
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {k: np.ascontiguousarray(v, np.float32) for k, v in channels.items()}) as f:
        f.write(str(path))
    return path


def test_mitsuba_moment_features_without_second_moments_are_read(tmp_path):
    """Complete P.albedo.*, P.sh_normal.*, P.depth.T without m2_ channels were dropped without a word."""
    from mcrecon.io.pixel_exr import read_pixel_stats_exr

    rng = np.random.default_rng(0)
    ch = {f"P.{c}": 0.5 + rng.random((H, W)) for c in "XYZ"}
    ch.update({f"m2_P.{c}": ch[f"P.{c}"] ** 2 + 0.1 for c in "XYZ"})
    feats = {f"P.albedo.{c}": rng.random((H, W)) for c in "RGB"}
    feats.update({f"P.sh_normal.{c}": rng.random((H, W)) for c in "XYZ"})
    feats["P.depth.T"] = 1 + rng.random((H, W))
    feats["m2_P.depth.T"] = feats["P.depth.T"] ** 2 + 0.5  # the depth's moments are complete
    path = _channels_exr(tmp_path / "m.exr", {**ch, **feats})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        pix = read_pixel_stats_exr(path, spp=SPP)
    assert pix.sources["features"] == {"albedo": ("P.albedo.R", "P.albedo.G", "P.albedo.B"),
                                       "normal": ("P.sh_normal.X", "P.sh_normal.Y", "P.sh_normal.Z"),
                                       "depth": ("P.depth.T",)}
    st = pix.stats.features
    np.testing.assert_allclose(st["albedo"].mean[..., 0], np.float32(feats["P.albedo.R"]))
    assert np.all(st["albedo"].sample_variance() == 0)  # no moments: noise-free, as pbrt's features
    assert np.all(st["depth"].sample_variance() > 0)  # from its moments


def test_a_refused_multi_part_exr_says_its_parts_in_its_one_line(tmp_path, capsys):
    import OpenEXR

    path = tmp_path / "mp.exr"
    head = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File([OpenEXR.Part({**head, "name": "beauty"}, {"RGB": np.ones((4, 5, 3), np.float32)}),
                  OpenEXR.Part({**head, "name": "aux"}, {"Albedo": np.ones((4, 5, 3), np.float32)})]).write(str(path))
    code, _, err = run_cli(["reconstruct", path, "--spp", "4", "-o", tmp_path / "o.exr"], capsys)
    _one_line(code, err, "layout: not recognised", "2 parts; only the first is read", "Albedo.B")
    code, _, err = run_cli(["info", path], capsys)
    assert code == 2 and err.count("\n") == 1, err


def test_an_all_zero_count_channel_is_refused_before_any_note(tmp_path, capsys):
    rng = np.random.default_rng(0)
    ch = {c: 0.2 + rng.random((H, W)) for c in "RGB"}
    ch.update({f"Variance.{c}": 0.1 * rng.random((H, W)) for c in "RGB"})
    ch["N"] = np.zeros((H, W))
    path = _channels_exr(tmp_path / "z.exr", ch)
    for method in ("box", "awr"):  # awr: a note on its variance estimator came first
        code, _, err = run_cli(["reconstruct", path, "--count", "N", "--method", method, "-o", tmp_path / "o.exr"],
                               capsys)
        _one_line(code, err, str(path), "count channel N: no pixel has a positive count")


def test_the_pixel_exr_modules_import_each_other_in_one_direction_only():
    """pixel_exr imports pixel_exr_features; the features module never imports the reader back (not even
    inside a function: a circle the module-level check does not see)."""
    src = (ROOT / "mcrecon" / "io" / "pixel_exr_features.py").read_text()
    for node in ast.walk(ast.parse(src)):
        if isinstance(node, ast.ImportFrom):
            assert node.module != "pixel_exr" and not (node.level and node.module is None and
                                                       any(a.name == "pixel_exr" for a in node.names)), node.lineno


# ------------------------------------------------------------------ renderer replies
_SENTINEL_RENDERER = textwrap.dedent("""
    import sys
    import h5py
    import numpy as np
    req, reply = sys.argv[1:]
    with h5py.File(req, "r") as f:
        w, h, seed = (int(f.attrs[k]) for k in ("width", "height", "seed"))
        channels = list(f.attrs["channels"])
        counts = f["counts"][...] if "counts" in f else np.zeros((h, w), np.int64)
        extra = f["positions"][...] if "positions" in f else np.zeros((0, 2))
    rng = np.random.default_rng(seed)
    pix = np.repeat(np.arange(w * h), counts.ravel())
    pos = np.concatenate([np.stack([pix % w, pix // w], 1) + rng.random((pix.size, 2)), extra])
    depth = np.ones(len(pos))
    depth[::7] = np.finfo(np.float64).max  # a "no hit" sentinel every round
    with h5py.File(reply, "w") as f:
        f.attrs.update(format="mcrecon-sample-log", format_version=1, width=w, height=h, channels=channels)
        f["positions"] = pos
        f["values"] = rng.uniform(0.5, 1.5, (len(pos), len(channels)))
        f["features/depth"] = depth
        f["features/hit"] = depth < 2  # a bool mask: taken as 0/1
""")


def test_reply_feature_sentinels_are_warned_once_and_bool_features_taken_as_0_1(tmp_path):
    """DBL_MAX was warned every round (NaN and Inf once); a bool feature was refused."""
    from mcrecon.adaptive.run import adapt
    from mcrecon.renderers.command import CommandRenderer

    script = tmp_path / "sentinel_renderer.py"
    script.write_text(_SENTINEL_RENDERER)
    r = CommandRenderer([sys.executable, str(script), "{request}", "{reply}"], width=8, height=6)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        adapt(r, "box", spp=8, seed=3, log=tmp_path / "run.h5")
    said = [str(w.message) for w in rec if "feature values set to 0" in str(w.message)]
    log = read_log(tmp_path / "run.h5")
    assert log.n_rounds > 1 and len(said) == 1, said
    depth, hit = log.read_feature("depth"), log.read_feature("hit")
    assert depth.max() == 1.0 and set(np.unique(depth)) == {0.0, 1.0}
    np.testing.assert_array_equal(hit, depth)  # 1 where hit, 0 at the sentinels


def test_bool_reply_features_of_the_feature_renderer_are_taken_as_0_1(tmp_path):
    from mcrecon.adaptive.run import adapt
    from mcrecon.renderers.command import CommandRenderer

    r = CommandRenderer([sys.executable, str(ROOT / "tests" / "renderers" / "feature_renderer.py"), "bool",
                         "{request}", "{reply}"], width=12, height=8)
    adapt(r, "box", spp=4, seed=3, log=tmp_path / "run.h5")
    log = read_log(tmp_path / "run.h5")
    pos = np.asarray(log.read_all().positions, np.float64)
    np.testing.assert_array_equal(log.read_feature("depth"), (pos[:, 0] + 1000 * pos[:, 1] > 500).astype(np.uint8))


@pytest.mark.parametrize("bad", [np.nan, np.inf, np.finfo(np.float64).max])
def test_a_python_renderers_zeroed_features_are_warned_once_per_run(bad):
    """The reply check warned a callable renderer's NaN/Inf/DBL_MAX feature entries every round."""
    from mcrecon.adaptive.run import adapt
    from mcrecon.core.requests import SampleBatch

    def shade(pos, rng, req):
        depth = np.ones(len(pos))
        depth[::7] = bad
        return SampleBatch(pos, rng.random((len(pos), 3)), {"depth": depth})

    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        result = adapt(jittered_renderer(shade, width=8, height=6), "box", spp=8, seed=3)
    said = [str(w.message) for w in rec if "feature values set to 0" in str(w.message)]
    assert len(result.rounds) > 1 and len(said) == 1, said

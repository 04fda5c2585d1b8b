"""Malformed inputs to the pixel-statistics EXRs, half buffers, compare, report and renderer replies.

Each input is refused in one line (exit 2, no traceback, no partial output)
or read correctly: none ends in a traceback, a silent crash, a memory bomb,
a misread input with exit 0, or more than one line.  The inputs are built
here.
"""

import json
import sys
import warnings

import numpy as np
import pytest

from mcrecon import InputError, McreconWarning, RendererError
from mcrecon.io import read_exr, write_exr
from mcrecon.io.pixel_exr import MITSUBA_XYZ_TO_SRGB, read_pixel_stats_exr, xyz_from_rgb_matrix
from mcrecon.core.metrics import flip_available

from helpers import run_cli, run_cli_process

H, W, SPP = 8, 10, 8


def _one_line(code, err, *matches):
    assert code == 2, err
    assert err.count("\n") == 1 and err.startswith("mcrecon: error: ") and "Traceback" not in err, err
    for m in matches:
        assert m in err, err


def _channels_exr(path, channels: dict, dtype=np.float32, **attrs):
    """An EXR of the given channels; a value ``(array, xs, ys)``: a full-size array stored subsampled by (xs, ys)."""
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **attrs}
    data = {}
    for name, v in channels.items():
        if isinstance(v, tuple):
            arr, xs, ys = v
            data[name] = OpenEXR.Channel(name, np.ascontiguousarray(arr, dtype=dtype), xs, ys)
        else:
            data[name] = OpenEXR.Channel(name, np.ascontiguousarray(v, dtype=dtype))
    with OpenEXR.File(header, data) as f:
        f.write(str(path))
    return path


def _pbrt_channels(seed=0):
    rng = np.random.default_rng(seed)
    ch = {c: 0.2 + rng.random((H, W)) for c in "RGB"}
    ch.update({f"Variance.{c}": 0.1 * rng.random((H, W)) for c in "RGB"})
    return ch


def _mitsuba_channels(seed=0):
    """Moment-integrator channels of per-pixel samples (H, W, SPP, 3)."""
    rng = np.random.default_rng(seed)
    s = 0.5 + rng.gamma(4.0, 0.25, (H, W, SPP, 3))
    xyz = s @ np.linalg.inv(MITSUBA_XYZ_TO_SRGB).T
    m1, m2 = xyz.mean(axis=2), (xyz ** 2).mean(axis=2)
    ch = {}
    for i, a in enumerate("XYZ"):
        ch[f"nested.{a}"] = m1[..., i]
        ch[f"m2_nested.{a}"] = m2[..., i]
    return ch


# ------------------------------------------------------------------ 1. tracebacks
def test_subsampled_mean_channel_is_refused_naming_the_file_and_channel(tmp_path, capsys):
    """pbrt-v4 layout with B at xSampling 2: np.stack raised 'all input arrays must have the same shape'."""
    ch = _pbrt_channels()
    ch["B"] = (ch["B"], 2, 2)  # the writer keeps every second pixel
    p = _channels_exr(tmp_path / "sub.exr", ch, samplesPerPixel=SPP)
    with pytest.raises(InputError, match="subsampled"):
        read_pixel_stats_exr(p)
    code, out, err = run_cli(["denoise", p, "-o", tmp_path / "o.exr"], capsys)
    _one_line(code, err, str(p), "'B'", "subsampled", "xSampling 2")
    assert not (tmp_path / "o.exr").exists()
    code, out, err = run_cli(["compare", p, p], capsys)  # read_exr stacks every channel
    _one_line(code, err, str(p), "'B'", "subsampled")


def test_a_subsampled_channel_that_is_not_used_is_ignored(tmp_path):
    ch = _pbrt_channels()
    ch["u"] = (np.ones((H, W)), 2, 2)
    got = read_pixel_stats_exr(_channels_exr(tmp_path / "p.exr", ch, samplesPerPixel=SPP))
    assert got.stats.shape == (H, W, 3)


@pytest.mark.parametrize("chrom", [(0.0,) * 8, (0.64, 0.33) * 3 + (0.3127, 0.329),
                                   (0.64, 0.33, 0.3, 0.6, 0.15, 0.06, 0.3127, 0.0)])
def test_degenerate_chromaticities_are_refused(tmp_path, capsys, chrom):
    """All 0: ZeroDivisionError; three identical primaries: LinAlgError (singular); white y 0."""
    p = _channels_exr(tmp_path / "c.exr", _pbrt_channels(), samplesPerPixel=SPP, chromaticities=chrom)
    code, out, err = run_cli(["denoise", p, "-o", tmp_path / "o.exr"], capsys)
    _one_line(code, err, str(p), "chromaticities")
    with pytest.raises(InputError, match="chromaticities"):
        xyz_from_rgb_matrix(tuple(zip(chrom[::2], chrom[1::2])))


def _run_folder(tmp_path, rows):
    d = tmp_path / "run"
    (d / "images").mkdir(parents=True)
    write_exr(d / "images" / "reference.exr", np.ones((4, 4, 3)))
    (d / "convergence_run.json").write_text(json.dumps({"images": [], "scene": "soft_shadow", "report_spp": 8,
                                                        "eps": 0.01, "smape_eps": 0.01, "flip": False}))
    (d / "convergence.json").write_text(json.dumps(rows) if not isinstance(rows, str) else rows)
    return d


GOOD_ROW = {"scene": "soft_shadow", "method": "box", "mode": "uniform", "spp": 8, "samples": 128,
            "renderer_seconds": 0.1, "toolkit_seconds": 0.01, "wall_seconds": 0.11, "relative_mse": 0.5,
            "rmse": 0.1, "ssim": 0.9, "smape": 0.2, "one_minus_ssim": 0.1}


@pytest.mark.parametrize("row, field", [
    ({}, "method"),
    ({**GOOD_ROW, "spp": "eight"}, "spp"),
    ({**GOOD_ROW, "spp": 8.5}, "spp"),
    ({**GOOD_ROW, "spp": True}, "spp"),
    ({**GOOD_ROW, "samples": -1}, "samples"),
    ({**GOOD_ROW, "relative_mse": "0.5"}, "relative_mse"),
    ({**GOOD_ROW, "renderer_seconds": float("nan")}, "renderer_seconds"),
    ({**GOOD_ROW, "method": 3}, "method"),
])
def test_report_refuses_malformed_convergence_records(tmp_path, capsys, row, field):
    d = _run_folder(tmp_path, [GOOD_ROW, row])
    code, out, err = run_cli(["report", d, "-o", tmp_path / "r.html"], capsys)
    _one_line(code, err, str(d / "convergence.json"), "record 1", field)
    assert not (tmp_path / "r.html").exists() and out == ""


def test_report_of_well_formed_records_still_writes(tmp_path, capsys):
    d = _run_folder(tmp_path, [GOOD_ROW, {**GOOD_ROW, "spp": 4, "flip": 0.3}])
    code, out, err = run_cli(["report", d, "-o", tmp_path / "r.html"], capsys)
    assert code == 0 and (tmp_path / "r.html").exists(), err


def test_renderer_cmd_with_an_unclosed_quote_names_the_flag(tmp_path, capsys):
    code, out, err = run_cli(["adapt", "--renderer-cmd", "render 'oops {request} {reply}", "--spp", "4",
                              "--size", "4x4", "-o", tmp_path / "o.exr", "--quiet"], capsys)
    _one_line(code, err, "--renderer-cmd", "quotation")


# ------------------------------------------------------------------ 2. crash, memory
@pytest.mark.skipif(not flip_available(), reason="flip-evaluator not installed (pip install flip-evaluator)")
def test_compare_against_an_all_black_reference_computes_the_rest(tmp_path):
    """HDR-FLIP's exposure range is empty for a black reference: flip-evaluator printed on stdout and
    ended the process with status 255."""
    a = write_exr(tmp_path / "a.exr", np.random.default_rng(0).random((8, 8, 3)))
    z = write_exr(tmp_path / "zero.exr", np.zeros((8, 8, 3)))
    p = run_cli_process(["compare", a, z, "--json"], timeout=120)
    assert p.returncode == 0, p
    res = json.loads(p.stdout)
    assert "flip" not in res and res["mse"] > 0 and any("FLIP" in n and "black" in n for n in res["notes"])
    from mcrecon.core.metrics import flip

    with pytest.raises(InputError, match="FLIP"):
        flip(read_exr(a)[0], read_exr(z)[0])


def _big_reply_renderer(tmp_path, rows):
    """A renderer whose reply declares ``rows`` samples (chunked datasets, no data written)."""
    script = tmp_path / "big_reply.py"
    script.write_text(f"""
import sys, h5py, numpy as np
with h5py.File(sys.argv[1], "r") as q:
    w, h = int(q.attrs["width"]), int(q.attrs["height"])
with h5py.File(sys.argv[2], "w") as f:
    f.attrs["format_version"] = 1
    f.attrs["width"], f.attrs["height"] = w, h
    f.attrs["channels"] = np.array(["R", "G", "B"], dtype=h5py.string_dtype())
    f.create_dataset("positions", shape=({rows}, 2), dtype=np.float32, chunks=(65536, 2))
    f.create_dataset("values", shape=({rows}, 3), dtype=np.float32, chunks=(65536, 3))
""")
    return script


def test_a_reply_declaring_more_rows_than_requested_is_refused_before_reading(tmp_path, monkeypatch):
    """A reply of 200 M declared rows was read whole (killed at 8 GiB) before its length was checked."""
    from mcrecon.io import reader as samplelog
    from mcrecon.renderers.command import CommandRenderer
    from mcrecon.core.requests import SampleRequest

    def no_read(*a, **k):
        raise AssertionError("the reply's samples were read before its declared length was checked")

    monkeypatch.setattr(samplelog.SampleLog, "read_all", no_read)
    monkeypatch.setattr(samplelog, "read_log", no_read)
    r = CommandRenderer([sys.executable, str(_big_reply_renderer(tmp_path, 200_000_000)), "{request}", "{reply}"],
                        width=4, height=4, workdir=tmp_path / "x")
    with pytest.raises(RendererError, match="reply length") as e:
        r.render(SampleRequest(4, 4, counts=np.ones((4, 4), np.int64)))
    assert "200000000" in str(e.value) and "16" in str(e.value)


# ------------------------------------------------------------------ 3. exit 0 with a misread input
def test_second_moment_below_the_squared_mean_warns_with_the_count(tmp_path):
    ch = _mitsuba_channels()
    ch["m2_nested.Y"][1, 2] = 0.5 * ch["nested.Y"][1, 2] ** 2      # damaged: far below
    ch["m2_nested.X"][3, 4] = 0.9 * ch["nested.X"][3, 4] ** 2
    ch["m2_nested.Z"][3, 4] = 0.9 * ch["nested.Z"][3, 4] ** 2      # the same pixel, another channel
    p = _channels_exr(tmp_path / "m.exr", ch)
    with pytest.warns(McreconWarning, match=r"2 sampled pixel\(s\).*second moment below the squared mean"):
        got = read_pixel_stats_exr(p, spp=SPP)
    assert got.stats.m2[1, 2, 1] == 0 and got.stats.m2[3, 4, 0] == 0


def test_second_moment_equal_to_the_squared_mean_up_to_rounding_is_silent(tmp_path):
    """A constant pixel: m2 = m1^2 in exact arithmetic, a few float32 ulps below it once stored."""
    ch = _mitsuba_channels()
    for a in "XYZ":
        m1 = ch[f"nested.{a}"].astype(np.float32)
        ch[f"m2_nested.{a}"] = np.nextafter(np.nextafter(m1 * m1, 0), 0)  # two ulps below
    p = _channels_exr(tmp_path / "m.exr", ch)
    with warnings.catch_warnings():
        warnings.simplefilter("error", McreconWarning)
        got = read_pixel_stats_exr(p, spp=SPP)
    assert (got.stats.m2 == 0).all()


def test_spp_whose_total_overflows_int64_is_refused_at_the_flag(tmp_path, capsys):
    """--spp 9223372036854775807 on 80 pixels printed '-80 samples' (int64 overflow of the count sum)."""
    p = _channels_exr(tmp_path / "m.exr", _mitsuba_channels())
    code, out, err = run_cli(["denoise", p, "-o", tmp_path / "o.exr", "--spp", "9223372036854775807"], capsys)
    _one_line(code, err, "--spp", str((2 ** 63 - 1) // (H * W)))
    assert not (tmp_path / "o.exr").exists()
    bound = (2 ** 63 - 1) // (H * W)
    code, out, err = run_cli(["denoise", p, "-o", tmp_path / "o.exr", "--spp", str(bound)], capsys)
    assert code == 0, err
    assert f"{bound * H * W} samples" in out


# ------------------------------------------------------------------ 4. one clean line
def _corrupt_exrs(tmp_path):
    good = write_exr(tmp_path / "good.exr", np.random.default_rng(0).random((32, 32, 3)))
    data = good.read_bytes()
    trunc = tmp_path / "trunc.exr"
    trunc.write_bytes(data[: len(data) // 2])
    junk = tmp_path / "junk.exr"
    junk.write_bytes(b"not an exr at all\n" * 8)
    return good, trunc, junk


def test_corrupt_exrs_give_one_line_and_nothing_else(tmp_path):
    """OpenEXR printed its own lines (stdout and stderr) and the reason given was 'Invalid part index'."""
    good, trunc, junk = _corrupt_exrs(tmp_path)
    for argv, bad, why in [
        (("denoise", trunc, "-o", tmp_path / "o.exr", "--spp", "4"), trunc, "truncated or corrupt"),
        (("compare", good, trunc), trunc, "truncated or corrupt"),
        (("compare", junk, good), junk, "not an OpenEXR file"),
        (("denoise", good, "--half-buffer", trunc, "--mean", "R,G,B", "--variance-channels", "R,G,B",
          "--spp", "4", "--method", "auto", "-o", tmp_path / "o.exr"), trunc, "truncated or corrupt"),
    ]:
        p = run_cli_process(argv, timeout=120)
        code, out, err = p.returncode, p.stdout, p.stderr
        assert code == 2 and out == "" and err.count("\n") == 1, (argv, code, out, err)
        assert err.startswith(f"mcrecon: error: {bad}: ") and why in err and "part index" not in err, err
    assert not (tmp_path / "o.exr").exists()


def test_awr_note_comes_after_the_input_is_validated(tmp_path, capsys):
    ch = _pbrt_channels()
    ch["Variance.G"][2, 3] = np.nan
    p = _channels_exr(tmp_path / "v.exr", ch, samplesPerPixel=SPP)
    code, out, err = run_cli(["denoise", p, "-o", tmp_path / "o.exr", "--method", "awr"], capsys)
    _one_line(code, err, str(p), "Variance.G")


def test_compare_errors_name_the_files(tmp_path, capsys):
    a = write_exr(tmp_path / "a.exr", np.ones((4, 4, 3)))
    b = write_exr(tmp_path / "b.exr", np.ones((4, 5, 3)))
    code, out, err = run_cli(["compare", a, b], capsys)
    _one_line(code, err, str(a), str(b), "shape")
    ref = np.ones((4, 4, 3))
    ref[1, 1, 0] = np.nan
    r = write_exr(tmp_path / "r.exr", ref)
    code, out, err = run_cli(["compare", a, r], capsys)
    _one_line(code, err, f"{r}: ", "1 non-finite")


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_compare_refuses_nonfinite_image_values_like_the_reference(tmp_path, capsys, bad):
    img = np.ones((8, 8, 3))
    img[2, 2, 1] = bad
    img[5, 1, :] = bad
    a = write_exr(tmp_path / "a.exr", img)
    r = write_exr(tmp_path / "r.exr", np.ones((8, 8, 3)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's RuntimeWarnings on Inf
        code, out, err = run_cli(["compare", a, r, "--no-flip"], capsys)
    _one_line(code, err, f"{a}: ", "4 non-finite")
    assert out == ""


def test_a_log_the_disk_cannot_hold_is_refused_before_rendering(tmp_path):
    """`mcrecon mitsuba log --spp 9223372036854775807` used to render pass after pass into the log until
    the disk was full; the size is now checked before the first sample (the check the command uses)."""
    from mcrecon.io.writer import check_log_fits

    with pytest.raises(InputError, match=r"mitsuba log: spp: .* GiB, more than the .* GiB free .*lower --spp"):
        check_log_fits(tmp_path / "big.h5", 2 ** 62, 3, where="mitsuba log")
    check_log_fits(tmp_path / "small.h5", 1000, 3, where="mitsuba log")  # fits: no error
    assert not (tmp_path / "big.h5").exists()

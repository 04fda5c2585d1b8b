"""One input path: what a method takes is declared on its Requirements and refused in one place.

Pixel-statistics EXRs and half-buffer pairs of them are sources of the
offline layer: ``mcrecon.reconstruct("frame.exr")``,
``mcrecon.reconstruct(("a.exr", "b.exr"))`` and ``mcrecon batch 'frames/*.exr'``
take them; the command line only composes those public calls.
"""

from __future__ import annotations

import ast
import warnings
from pathlib import Path

import numpy as np
import pytest

import mcrecon
from mcrecon import InputError, McreconWarning, PixelStats, SampleSet
from mcrecon.cli import main
from mcrecon.core.halves import split_halves
from mcrecon.io import read_exr, read_pixel_stats_exr
from mcrecon.io.pixel_exr import read_half_buffer_exrs
from mcrecon.io.pixel_exr import xyz_from_rgb_matrix
from mcrecon.methods import get_method

PACKAGE = Path(mcrecon.__file__).parent
H, W, SPP = 16, 20, 8
BUILTIN = ("box", "gem", "awr", "splat", "ci", "auto", "nfor")


def write_channels(path, channels: dict, **attrs):
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **attrs}
    data = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in channels.items()}
    with OpenEXR.File(header, data) as f:
        f.write(str(path))
    return path


def sample_set(seed=0, spp=SPP):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:H, 0:W]
    base = np.stack([0.5 + 0.4 * np.sin(xx / 3.0), 0.3 + 0.2 * yy / H, 0.2 + 0.6 * (xx > W // 2)], axis=-1)
    vals = base[:, :, None, :] * rng.gamma(3.0, 1 / 3.0, (H, W, spp, 3))
    pos = np.stack([xx[:, :, None] + rng.random((H, W, spp)), yy[:, :, None] + rng.random((H, W, spp))], -1)
    return SampleSet(pos.reshape(-1, 2), vals.reshape(-1, 3), width=W, height=H, channels=("X", "Y", "Z"))


def pbrt_file(path, st: PixelStats):
    """A pbrt-v4 GBufferFilm-like EXR of statistics in XYZ: sRGB mean, XYZ variances, samplesPerPixel."""
    rgb = st.mean @ np.linalg.inv(xyz_from_rgb_matrix()).T
    var = st.sample_variance(ddof=1, undefined=0.0)
    ch = {c: rgb[..., i] for i, c in enumerate("RGB")}
    ch.update({f"Variance.{c}": var[..., i] for i, c in enumerate("RGB")})
    return write_channels(path, ch, samplesPerPixel=int(st.count.flat[0]))


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("exr")
    ss = sample_set()
    h = split_halves(ss)
    return {"all": pbrt_file(d / "all.exr", PixelStats.from_source(ss)), "a": pbrt_file(d / "a.exr", h.a),
            "b": pbrt_file(d / "b.exr", h.b), "dir": d}


def quiet(fn, *a, **k):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fn(*a, **k)


# ------------------------------------------------------------------ EXR inputs from Python
@pytest.mark.parametrize("method", ["box", "gem", "awr"])
def test_reconstruct_takes_an_exr_path(files, method):
    rec = mcrecon.reconstruct(files["all"], method=method, full=True)
    pix = read_pixel_stats_exr(files["all"])
    np.testing.assert_array_equal(rec.image, pix.output_image(mcrecon.reconstruct(pix.stats, method=method)))
    assert rec.channels == ("R", "G", "B") and rec.inputs.channels == ("X", "Y", "Z") and len(rec.files) == 1
    # a file read already is taken too, and read options go with a path
    np.testing.assert_array_equal(mcrecon.reconstruct(pix, method=method), rec.image)
    np.testing.assert_array_equal(mcrecon.reconstruct(files["all"], method=method,
                                                      exr_options={"layout": "pbrt-v4"}), rec.image)


def test_reconstruct_takes_a_pair_of_exr_paths(files):
    rec = mcrecon.reconstruct((files["a"], files["b"]), method="auto", full=True)
    pa, pb = read_half_buffer_exrs(files["a"], files["b"])
    expect = pa.output_image(mcrecon.reconstruct((pa.stats, pb.stats), method="auto"))
    np.testing.assert_array_equal(rec.image, expect)
    assert len(rec.files) == 2 and rec.inputs.halves is not None and rec.inputs.halves.source is None


def test_the_command_line_writes_what_python_returns(files, capsys):
    out = files["dir"] / "cli_pair.exr"
    assert main(["denoise", str(files["a"]), "--half-buffer", str(files["b"]), "-o", str(out), "--method",
                 "auto"]) == 0
    expect = mcrecon.reconstruct((files["a"], files["b"]), method="auto")
    np.testing.assert_array_equal(read_exr(out)[0], expect.astype(np.float32))
    assert "half-buffer pair" in capsys.readouterr().err


def test_a_method_adapts_to_one_exr_by_its_declared_options(files):
    """auto's default candidates need two halves: on one EXR it takes the options its Requirements declare."""
    assert dict(get_method("auto").requires.statistics_options) == {"candidates": "box,gauss"}
    with pytest.warns(McreconWarning, match=r"candidates='box,gauss'.*a pair of two EXR paths"):
        img = mcrecon.reconstruct(files["all"], method="auto")
    pix = read_pixel_stats_exr(files["all"])
    np.testing.assert_array_equal(img, pix.output_image(mcrecon.reconstruct(pix.stats, method="auto",
                                                                            candidates="box,gauss")))
    # options the caller chose are never changed: refused in one line, naming the fix
    with pytest.raises(InputError, match="candidates='box,gauss'"):
        mcrecon.reconstruct(files["all"], method="auto", candidates="box,nlm")
    # awr: the paper's 'range' estimator needs sample ranges, which statistics from moments lack
    with pytest.warns(McreconWarning, match="variance='sample'"):
        mcrecon.reconstruct(files["all"], method="awr", variant="paper")
    with pytest.raises(InputError, match="minimum and maximum.*variance='sample'"):
        mcrecon.reconstruct(files["all"], method="awr", variance="range")
    # in-memory statistics: the caller chooses (no silent change), the message suggests the option
    with pytest.raises(InputError, match="variance='sample'"):
        mcrecon.reconstruct(pix.stats, method="awr", variant="paper")
    # the default estimator takes them as they are
    with warnings.catch_warnings():
        warnings.simplefilter("error", McreconWarning)
        mcrecon.reconstruct(files["all"], method="awr")


def test_exr_refusals_come_before_reading(files, tmp_path):
    missing = tmp_path / "missing.exr"
    with pytest.raises(InputError, match="individual samples.*sample log"):
        mcrecon.reconstruct(missing, method="splat")  # refused for the method, not for the missing file
    with pytest.raises(InputError, match="does not use half buffers"):
        mcrecon.reconstruct((missing, files["b"]), method="gem")
    with pytest.raises(InputError, match="fireflies"):
        mcrecon.reconstruct(files["all"], method="box", fireflies="cascade")
    with pytest.raises(InputError, match="exr_options"):
        mcrecon.reconstruct(sample_set(), method="box", exr_options={"spp": 4})


# ------------------------------------------------------------------ batch over EXR frames
@pytest.fixture(scope="module")
def client():
    pytest.importorskip("distributed", reason="needs the dask extra: pip install 'mcrecon[dask]'")
    from mcrecon.distributed import cluster

    with cluster.local_client(1, threads=1) as c:
        yield c


def test_batch_reconstructs_exr_frames(files, client, tmp_path, capsys):
    from mcrecon.distributed.batch import reconstruct_many

    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(2):
        pbrt_file(frames / f"f{i}.exr", PixelStats.from_source(sample_set(seed=i)))
    out = tmp_path / "out"
    res = reconstruct_many(str(frames / "*.exr"), method="gem", out_dir=out, client=client, progress=False)
    assert res.ok and [r["status"] for r in res.records] == ["done", "done"]
    for i in range(2):
        img, names = read_exr(out / f"f{i}.exr")
        assert names == ("R", "G", "B")
        np.testing.assert_array_equal(img, mcrecon.reconstruct(frames / f"f{i}.exr", method="gem").astype(np.float32))
    assert res.records[0]["samples"] == H * W * SPP
    # the command line: the same, and up to date on a rerun
    assert main(["batch", str(frames / "*.exr"), "--out-dir", str(out), "--method", "gem", "--scheduler",
                 client.scheduler.address, "--quiet"]) == 0
    assert "2 up to date" in capsys.readouterr().out
    # an output directory holding the frames would replace them: refused before any work
    with pytest.raises(InputError, match="replace the frame"):
        reconstruct_many(str(frames / "*.exr"), method="gem", out_dir=frames, client=client)


# ------------------------------------------------------------------ one place, no names
def _string_constants(rel: str) -> set:
    tree = ast.parse((PACKAGE / rel).read_text())
    return {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)}


def test_the_dispatcher_and_the_refusals_name_no_method():
    for rel in ("offline/inputs.py", "offline/pixel_files.py", "methods/supply.py"):
        named = _string_constants(rel) & set(BUILTIN)
        assert not named, f"{rel} names methods {named}"


def test_input_refusals_live_in_one_place():
    phrases = ("does not use half buffers", "needs the individual samples or two", "minimum and maximum, which")
    for path in PACKAGE.rglob("*.py"):
        text = path.read_text()
        for p in phrases:
            if p in text:
                assert path == PACKAGE / "methods" / "supply.py", f"{path}: {p!r}"


def test_the_cli_composes_public_calls_and_the_registry_circle_is_gone():
    tree = ast.parse((PACKAGE / "cli" / "commands.py").read_text())
    used = {a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) for a in n.names} | \
        {n.name for n in ast.walk(tree) if isinstance(n, (ast.ClassDef, ast.FunctionDef))}
    for name in ("read_pixel_stats_exr", "read_half_buffer_exrs", "check_method", "pixel_stats_options",
                 "_PixelStatsInput", "_read_pixel_stats_input"):
        assert name not in used, name
    tree = ast.parse((PACKAGE / "methods" / "base.py").read_text())
    targets = {(n.level, n.module) for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    assert (1, None) not in targets  # `from . import ...`: the registry


# ------------------------------------------------------------------ options given are kept; errors in the caller's terms
def test_an_option_given_equal_to_its_default_is_not_replaced(files, cli, tmp_path):
    """Given, not "different from the default": auto's default candidates given explicitly are refused on
    one EXR (naming the option), never silently swapped for the statistics options."""
    default = get_method("auto").params["candidates"]
    assert get_method("auto", candidates=default).given_options == {"candidates"}
    with pytest.raises(InputError, match=r"candidates.*given.*pair of two EXR paths") as exc:
        mcrecon.reconstruct(files["all"], method="auto", candidates=default)
    assert exc.value.field == "candidates"
    code, out, err = cli(["reconstruct", files["all"], "-o", tmp_path / "o.exr", "--method", "auto",
                          "--candidates", default])
    assert code == 2 and len(err.strip().splitlines()) == 1 and not (tmp_path / "o.exr").exists()
    assert "--candidates" in err and "--half-buffer B.exr" in err and "candidates=" not in err


def test_python_errors_on_exr_inputs_name_keywords_and_the_cli_names_flags(files, cli, tmp_path):
    with pytest.warns(McreconWarning) as rec:
        mcrecon.reconstruct(files["all"], method="auto")
    text = str(rec[0].message)
    assert "--" not in text and "candidates='box,gauss'" in text
    with pytest.raises(InputError) as exc:
        mcrecon.reconstruct((files["a"], files["b"]), method="gem")
    assert exc.value.field == "source" and "--" not in str(exc.value)
    with pytest.raises(InputError, match=r"fireflies='cascade'") as exc:
        mcrecon.reconstruct(files["all"], method="box", fireflies="cascade")
    assert exc.value.where == str(files["all"])
    code, _, err = cli(["reconstruct", files["all"], "-o", tmp_path / "o.exr", "--fireflies", "cascade"])
    assert code == 2 and str(files["all"]) in err and "--fireflies cascade" in err and "fireflies=" not in err
    code, _, err = cli(["reconstruct", files["a"], "--half-buffer", files["b"], "-o", tmp_path / "o.exr",
                        "--method", "gem"])
    assert code == 2 and "--half-buffer" in err


@pytest.mark.parametrize("n", [1])  # three or more are a seed set (tests/test_seed_sets.py)
def test_a_tuple_of_exr_paths_that_is_no_pair_says_what_a_pair_is(files, n):
    with pytest.raises(InputError, match=rf"got {n} item\(s\); a half-buffer pair is two EXR paths"):
        mcrecon.reconstruct(tuple([files["a"], files["b"], files["all"]][:n]), method="auto")


def test_a_pair_with_one_non_exr_item_blames_that_item(files):
    with pytest.raises(InputError, match=r"x\.h5 is not an EXR") as exc:
        mcrecon.reconstruct((files["a"], "x.h5"), method="auto")
    assert exc.value.field == "source[1]"


@pytest.mark.parametrize("bad, said", [({"bogus": 1}, "unknown key 'bogus'"), ("x", "got str")])
def test_bad_exr_options_are_one_line_naming_the_valid_keys(files, bad, said):
    with pytest.raises(InputError, match=said) as exc:
        mcrecon.reconstruct(files["all"], method="box", exr_options=bad)
    assert exc.value.field == "exr_options" and "layout" in str(exc.value) and "spp" in str(exc.value)


def test_one_helper_says_what_an_exr_input_is():
    """The "is this an EXR" test is offline.pixel_files.is_pixel_file_source alone."""
    for rel in ("cli/commands.py", "cli/batch.py", "distributed/batch.py"):
        assert '.endswith(".exr")' not in (PACKAGE / rel).read_text(), rel


def test_batch_reads_mitsuba_moment_frames_with_the_read_flags(client, tmp_path, cli):
    """A Mitsuba moment EXR carries no sample count: batch takes --spp like reconstruct does."""
    from test_pixel_exr import mitsuba_exr, samples

    from mcrecon.distributed.batch import reconstruct_many

    frames = tmp_path / "mframes"
    frames.mkdir()
    for i in range(2):
        mitsuba_exr(frames / f"m{i}.exr", samples(seed=i))
    out = tmp_path / "o"
    code, stdout, err = cli(["batch", frames / "*.exr", "--out-dir", out, "--method", "gem", "--spp", 8,
                             "--scheduler", client.scheduler.address, "--quiet"])
    assert code == 0, err
    assert "2 reconstructed" in stdout
    for i in range(2):
        expect = mcrecon.reconstruct(frames / f"m{i}.exr", method="gem", exr_options={"spp": 8})
        np.testing.assert_array_equal(read_exr(out / f"m{i}.exr")[0], expect.astype(np.float32))
    # auto's fallback on one EXR is kept in a batch (the options given travel, not every option's value)
    res = reconstruct_many(str(frames / "*.exr"), method="auto", out_dir=tmp_path / "oa", client=client,
                           progress=False, exr_options={"spp": 8})
    assert res.ok, res.failed
    # read options with a sample log among the frames: refused before any work
    from mcrecon.io import write_log

    rng = np.random.default_rng(1)
    log = write_log(tmp_path / "l.h5", rng.random((64, 2)) * [W, H], rng.random((64, 3)), width=W, height=H)
    with pytest.raises(InputError, match="exr_options"):
        reconstruct_many([str(frames / "m0.exr"), str(log)], method="gem", out_dir=tmp_path / "ob",
                         client=client, exr_options={"spp": 8})


def test_batch_help_says_exr_frames_are_taken(cli):
    code, out, _ = cli(["batch", "--help"])
    assert code == 0 and ".exr" in out and "--spp" in out and "--layout" in out

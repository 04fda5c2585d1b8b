"""Boundary inputs found in review that the other boundary tests do not cover.

Each test failed before its fix: attributes of the wrong type read as
integers, memory bombs (a film or a sample budget this machine cannot hold)
ending in a traceback or an OOM kill, a log's non-finite reference refused
after the work with a message naming neither the file nor the dataset, a
negative /rounds/end read as rows, a non-finite preview exposure, a
half-buffer pair made of one file twice.
"""

import h5py
import numpy as np
import pytest

import mcrecon.core.samples
from mcrecon import InputError
from mcrecon.cli import main
from mcrecon.io import read_log, write_exr, write_log

from helpers import run_cli


def _one_line(code, err, match):
    assert code == 2, err
    assert err.count("\n") == 1 and err.startswith("mcrecon: error: ") and "Traceback" not in err, err
    assert match in err, err


def _log(tmp_path, name="b.h5", w=8, h=6, n=200, **kw):
    rng = np.random.default_rng(0)
    return write_log(tmp_path / name, rng.random((n, 2)) * [w, h], rng.random((n, 3)).astype(np.float32),
                     width=w, height=h, **kw)


# ------------------------------------------------------------------ integer attributes
@pytest.mark.parametrize("key, value, match", [
    ("width", 8.5, "attribute width/height"),
    ("width", 8.0, "attribute width/height"),
    ("height", "6", "attribute width/height"),
    ("width", True, "attribute width/height"),
    ("n_committed", 100.5, "attribute n_committed"),
    ("format_minor", 2.5, "attribute format_minor"),
    ("format_version", 1.0, "attribute format_version"),
])
def test_integer_attributes_of_another_type_are_refused(tmp_path, capsys, key, value, match):
    """int(8.5) == 8 and int("6") == 6 read a wrong header as a valid one; the format says integers."""
    path = _log(tmp_path)
    with h5py.File(path, "r+") as f:
        f.attrs[key] = value
    with pytest.raises(InputError, match=match):
        read_log(path)
    code, _, err = run_cli(["info", path], capsys)
    _one_line(code, err, match)


def test_integer_attributes_of_any_integer_type_still_read(tmp_path):
    path = _log(tmp_path)
    with h5py.File(path, "r+") as f:
        f.attrs["width"], f.attrs["height"] = np.uint8(8), np.array([6], np.int16)
        f.attrs["n_committed"] = np.uint64(150)
    log = read_log(path)
    assert (log.width, log.height, log.n_samples) == (8, 6, 150)


# ------------------------------------------------------------------ memory bombs
def _small_memory(monkeypatch, nbytes):
    monkeypatch.setattr(mcrecon.core.samples, "available_memory", lambda: nbytes)


def test_a_film_larger_than_memory_is_refused_by_info_and_denoise(tmp_path, capsys, monkeypatch):
    """200 samples on a 4096x4096 film: the per-pixel arrays need more than the machine has (here: 64 MiB)."""
    path = _log(tmp_path)
    with h5py.File(path, "r+") as f:
        f.attrs["width"], f.attrs["height"] = 4096, 4096
    _small_memory(monkeypatch, 64 << 20)
    for argv in (["info", path], ["denoise", path, "-o", tmp_path / "o.exr"]):
        code, _, err = run_cli(argv, capsys)
        _one_line(code, err, "4096x4096")
        assert "memory" in err
    assert not (tmp_path / "o.exr").exists()


def test_a_film_within_the_pixel_limit_but_not_in_memory_is_refused(tmp_path, capsys):
    """2^31 pixels is the format's limit; its per-pixel statistics (over 200 GB) fit no machine we run on:
    one line, not numpy's MemoryError traceback."""
    path = _log(tmp_path)
    with h5py.File(path, "r+") as f:
        f.attrs["width"], f.attrs["height"] = 65536, 32768
    code, _, err = run_cli(["denoise", path, "-o", tmp_path / "o.exr"], capsys)
    _one_line(code, err, "65536x32768")


@pytest.mark.parametrize("argv, match", [
    (["render-log", "--scene", "flat", "--spp", "2", "--size", "100000x100000", "-o", "{tmp}/r.h5"],
     "100000x100000"),
    (["adapt", "--scene", "flat", "--spp", "2", "--size", "100000x100000", "-o", "{tmp}/a.exr"], "100000x100000"),
])
def test_a_size_beyond_the_pixel_limit_is_refused_at_the_flag(tmp_path, capsys, argv, match):
    code, _, err = run_cli([a.replace("{tmp}", str(tmp_path)) for a in argv], capsys)
    _one_line(code, err, match)
    assert "--size" in err


def test_a_log_larger_than_the_disk_is_refused_before_rendering(tmp_path, capsys):
    # render-log streams its samples (memory bounded by a block), so 8e12 samples are bounded by the disk
    code, _, err = run_cli(["render-log", "--scene", "flat", "--spp", "2000000000", "--size", "64x64",
                            "-o", str(tmp_path / "r.h5")], capsys)
    _one_line(code, err, "on disk")
    assert "samples" in err and "r.h5" in err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv", [
    # the whole budget is box's first round: this one was killed by the kernel's OOM killer at 24 GB
    ["adapt", "--scene", "flat", "--spp", "1e12", "--size", "8x8", "-o", "{tmp}/a.exr", "--log", "{tmp}/a.h5",
     "--quiet"],
])
def test_a_round_larger_than_memory_is_refused_before_rendering(tmp_path, capsys, monkeypatch, argv):
    _small_memory(monkeypatch, 1 << 30)
    code, _, err = run_cli([a.replace("{tmp}", str(tmp_path)) for a in argv], capsys)
    _one_line(code, err, "memory")
    assert "samples" in err


# ------------------------------------------------------------------ the log's reference
def test_a_non_finite_reference_in_a_log_is_refused_naming_the_dataset_before_any_output(tmp_path, capsys):
    ref = np.ones((6, 8, 3))
    ref[1, 2, 0] = np.nan
    path = _log(tmp_path, reference=np.ones((6, 8, 3)))
    with h5py.File(path, "r+") as f:
        f["reference"][...] = ref
    code, _, err = run_cli(["denoise", path, "-o", tmp_path / "o.exr"], capsys)
    _one_line(code, err, "dataset /reference")
    assert str(path) in err
    assert not (tmp_path / "o.exr").exists()


# ------------------------------------------------------------------ /rounds/end
def test_a_negative_round_end_is_named_not_read_as_rows(tmp_path, capsys):
    path = _log(tmp_path, rounds=np.repeat([0, 1], 100))
    with h5py.File(path, "r+") as f:
        f["rounds/end"][0] = -5
    code, _, err = run_cli(["info", path], capsys)
    _one_line(code, err, "dataset /rounds/end")
    assert "rows -5" not in err and "-5" in err


# ------------------------------------------------------------------ CLI flags
@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "1e400"])
def test_a_non_finite_exposure_is_refused(tmp_path, capsys, value):
    path = _log(tmp_path)
    with pytest.raises(SystemExit) as exc:  # refused by the parser, before any work
        main([str(a) for a in ["denoise", path, "-o", tmp_path / "o.exr", "--exposure", value]])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "--exposure" in err and err.count("\n") == 1 and "Traceback" not in err, err
    assert not (tmp_path / "o.exr").exists()


# ------------------------------------------------------------------ half-buffer pairs
def test_a_half_buffer_pair_of_one_file_twice_is_refused(tmp_path, capsys):
    """The same file as both halves has no noise between its halves: a dual-buffer estimate is silently 0."""
    rng = np.random.default_rng(1)
    img = rng.random((6, 8, 6)).astype(np.float32)
    path = write_exr(tmp_path / "h.exr", img, channels=("R", "G", "B", "Variance.R", "Variance.G", "Variance.B"))
    link = tmp_path / "h2.exr"
    link.symlink_to(path)
    for other in (path, link):
        code, _, err = run_cli(["denoise", path, "-o", tmp_path / "o.exr", "--method", "auto", "--mean", "R,G,B",
                                "--variance-channels", "Variance.R,Variance.G,Variance.B", "--spp", "4",
                                "--half-buffer", other], capsys)
        errors = [ln for ln in err.splitlines() if "error" in ln]
        assert code == 2 and len(errors) == 1 and "same file" in errors[0], err


def test_values_beyond_float32_are_said_once_when_written_to_an_exr(tmp_path):
    """A float64 image with finite values beyond float32's range: the EXR (float32) holds +-Inf there,
    and one McreconWarning says so with the count (before: numpy's overflow RuntimeWarning only)."""
    import warnings

    from mcrecon import McreconWarning
    from mcrecon.io import read_exr

    img = np.ones((4, 5, 3))
    img[1, 2, 0] = 1e308
    img[3, 4, 2] = -1e300
    img[0, 0, 1] = np.inf  # already infinite: not counted
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        write_exr(tmp_path / "big.exr", img)
    msgs = [str(w.message) for w in rec]
    assert len(rec) == 1 and issubclass(rec[0].category, McreconWarning), msgs
    assert "2 finite value(s)" in msgs[0] and "big.exr" in msgs[0]
    back, _ = read_exr(tmp_path / "big.exr")
    assert back[1, 2, 0] == np.inf and back[3, 4, 2] == -np.inf and back[2, 2, 2] == 1.0


def test_a_channel_named_twice_in_a_mapping_is_refused_at_the_flag(tmp_path, capsys):
    """``--mean R,R,B`` was read, reconstructed, and refused only when the output EXR got two channels
    named R (the error named the output); now the flag is refused before any work."""
    rng = np.random.default_rng(1)
    img = rng.random((6, 8, 6)).astype(np.float32)
    path = write_exr(tmp_path / "p.exr", img, channels=("R", "G", "B", "Variance.R", "Variance.G", "Variance.B"))
    code, _, err = run_cli(["denoise", path, "-o", tmp_path / "o.exr", "--mean", "R,R,B",
                            "--variance-channels", "Variance.R,Variance.G,Variance.B", "--spp", "4"], capsys)
    _one_line(code, err, "--mean")
    assert "'R' twice" in err
    assert not (tmp_path / "o.exr").exists()


def test_a_sample_count_beyond_int64_is_refused_as_a_count(tmp_path, capsys):
    """``--spp 99999999999999999999999`` on a statistics EXR was refused as "count: dtype object"."""
    rng = np.random.default_rng(1)
    img = rng.random((6, 8, 6)).astype(np.float32)
    path = write_exr(tmp_path / "p.exr", img, channels=("R", "G", "B", "Variance.R", "Variance.G", "Variance.B"))
    code, _, err = run_cli(["denoise", path, "-o", tmp_path / "o.exr", "--mean", "R,G,B",
                            "--variance-channels", "Variance.R,Variance.G,Variance.B",
                            "--spp", "99999999999999999999999"], capsys)
    _one_line(code, err, "--spp")
    assert "positive whole number" in err


@pytest.mark.parametrize("method, extra", [("gem", []), ("awr", ["--round-spp", "1e10"])])
def test_a_planned_round_larger_than_memory_is_refused_before_its_positions_are_drawn(tmp_path, capsys,
                                                                                     monkeypatch, method, extra):
    """gem's and awr's plans draw every sample's position: ``--spp 1e12`` on 8x8 made gem allocate
    43.7 TiB (a MemoryError traceback) before the driver's round check could run (awr's rounds are
    ``round_spp`` per pixel: its bomb needs that option too)."""
    _small_memory(monkeypatch, 1 << 30)
    # a scene with structure: on flat the round is uniform (the structure test) and draws no positions
    code, _, err = run_cli(["adapt", "--scene", "soft_shadow", "--spp", "1e12", "--size", "8x8", "--method", method,
                            *extra,
                            "-o", tmp_path / "a.exr", "--log", tmp_path / "a.h5", "--quiet"], capsys)
    _one_line(code, err, "memory")
    assert f"method {method}" in err and "sample positions" in err


@pytest.mark.parametrize("flag, value", [("--final-scales", "1000"), ("--adaptive-scales", "11")])
def test_gem_scale_counts_are_bounded(tmp_path, capsys, flag, value):
    """``--final-scales 1000`` ran for minutes (Gaussians of 2^500 px); 16 final scales reach 256 px,
    10 adaptive (dyadic) scales 512 px."""
    path = _log(tmp_path)
    code, _, err = run_cli(["denoise", path, "-o", tmp_path / "o.exr", "--method", "gem", flag, value], capsys)
    _one_line(code, err, flag.lstrip("-").replace("-", "_"))


def test_boundary_errors_name_where_field_and_problem_and_pickle_as_built():
    import pickle

    from mcrecon.errors import InputError, RendererError

    for cls, base in ((InputError, ValueError), (RendererError, RuntimeError)):
        e = cls("run.h5", "values", "NaN in row 3; fix the renderer")
        assert isinstance(e, base) and str(e) == "run.h5: values: NaN in row 3; fix the renderer"
        back = pickle.loads(pickle.dumps(e))
        assert type(back) is cls and (back.where, back.field, back.problem) == (e.where, e.field, e.problem)

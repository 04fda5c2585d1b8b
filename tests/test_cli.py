"""The mcrecon command line, end to end, as a user would run it."""

import json
import subprocess
import sys

import h5py
import numpy as np
import pytest

from mcrecon.cli import main
from mcrecon.io import read_exr, read_log, write_exr, write_log


def run(args, capsys):
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture
def scene_log(tmp_path, capsys):
    path = tmp_path / "flat.h5"
    code, out, err = run(["render-log", "--scene", "soft_shadow", "--spp", "4", "--size", "24x16", "-o", path], capsys)
    assert code == 0, err
    return path


def test_scenes_and_methods(capsys):
    code, out, _ = run(["scenes"], capsys)
    assert code == 0 and "soft_shadow" in out and "caustic" in out
    code, out, _ = run(["methods"], capsys)
    assert code == 0 and out.startswith("box")


def test_info(scene_log, capsys):
    code, out, _ = run(["info", scene_log, "--json"], capsys)
    info = json.loads(out)
    assert code == 0 and info["width"] == 24 and info["samples"] == 24 * 16 * 4
    assert info["spp_min"] == info["spp_max"] == 4 and info["reference"] is True
    code, out, _ = run(["info", scene_log], capsys)
    assert "spp_mean" in out and "4.000" in out


def test_info_counts_nonfinite_and_negative(tmp_path, capsys):
    val = np.array([[1.0], [np.nan], [-2.0], [np.inf]])
    write_log(tmp_path / "x.h5", np.array([[0.5, 0.5]] * 4), val, width=2, height=1, channels=["Y"])
    code, out, err = run(["info", tmp_path / "x.h5", "--json"], capsys)
    info = json.loads(out)
    assert info["nonfinite_samples"] == 2 and info["negative_samples"] == 1 and info["empty_pixels"] == 1


def test_denoise_writes_exr_png_and_diagnostics(scene_log, tmp_path, capsys):
    out_exr = tmp_path / "o.exr"
    code, out, err = run(["denoise", scene_log, "-o", out_exr, "--method", "box", "--diagnostics", tmp_path / "d"],
                         capsys)
    assert code == 0, err
    assert "relative MSE" in out
    img, ch = read_exr(out_exr)
    assert img.shape == (16, 24, 3) and ch == ("R", "G", "B")
    assert (tmp_path / "o.png").exists() and (tmp_path / "d" / "sample_density.png").exists()
    # box equals the per-pixel mean of the log's samples (float32 in the EXR)
    data = read_log(scene_log).read_all()
    pix = np.floor(data.positions[:, 1]).astype(int) * 24 + np.floor(data.positions[:, 0]).astype(int)
    mean = np.stack([np.bincount(pix, data.values[:, c], 24 * 16) / 4 for c in range(3)], 1).reshape(16, 24, 3)
    np.testing.assert_allclose(img, mean, rtol=1e-6)


def test_adapt_on_a_scene_and_compare(tmp_path, capsys):
    code, out, err = run(["adapt", "--scene", "flat", "--size", "16x16", "--spp", "4", "--method", "box",
                          "-o", tmp_path / "a.exr", "--log", tmp_path / "a.h5", "--quiet"], capsys)
    assert code == 0, err
    assert "stopped: budget" in out and "renderer" in out and "toolkit" in out and "relative MSE" in out
    assert read_log(tmp_path / "a.h5").n_samples == 16 * 16 * 4
    code, out, err = run(["adapt", "--scene", "flat", "--size", "16x16", "--spp", "8", "--method", "box",
                          "-o", tmp_path / "b.exr", "--rounds-json", tmp_path / "r.json", "--quiet"], capsys)
    rounds = json.loads((tmp_path / "r.json").read_text())
    assert code == 0 and [r["samples_total"] for r in rounds] == [256, 512, 1024, 2048]
    assert rounds[-1]["error"] < rounds[0]["error"] and all(r["toolkit_seconds"] >= 0 for r in rounds)
    code, out, err = run(["adapt", "--scene", "flat", "--size", "8x8", "--spp", "2", "--method", "box",
                          "-o", tmp_path / "c.exr", "--log", tmp_path / "c.h5", "--storage-dtype", "float64",
                          "--quiet"], capsys)
    assert code == 0 and read_log(tmp_path / "c.h5").value_dtype == np.float64
    img, _ = read_exr(tmp_path / "a.exr")
    write_exr(tmp_path / "ref.exr", np.full_like(img, 0.5))
    code, out, err = run(["compare", tmp_path / "a.exr", tmp_path / "ref.exr", "--json"], capsys)
    m = json.loads(out)
    assert code == 0 and 0 < m["relative_mse"] < 1 and np.isfinite(m["ssim"])


@pytest.mark.parametrize("args, match", [
    (["denoise", "{tmp}/missing.h5", "-o", "{tmp}/o.exr"], "missing.h5: file: does not exist"),
    (["denoise", "{tmp}/text.h5", "-o", "{tmp}/o.exr"], "text.h5: file: not a readable HDF5"),
    (["denoise", "{log}", "-o", "{tmp}/o.exr", "--method", "nope"], "unknown method 'nope'; valid: box"),
    (["denoise", "{log}", "-o", "{tmp}/o.png"], "expected a path ending in .exr"),
    (["denoise", "{log}", "-o", "{tmp}/o.exr", "--method", "box", "--gamma", "0.2"], "--gamma: does not apply"),
    (["adapt", "--scene", "nope", "--spp", "4", "-o", "{tmp}/o.exr"], "nope"),
    (["adapt", "--scene", "flat", "-o", "{tmp}/o.exr"], "--spp: missing"),
    (["adapt", "--scene", "flat", "--spp", "4", "--size", "ax3", "-o", "{tmp}/o.exr"], "WIDTHxHEIGHT"),
    (["adapt", "--spp", "4", "-o", "{tmp}/o.exr"], "give exactly one of"),
    (["adapt", "--scene", "flat", "--spp", "-1", "-o", "{tmp}/o.exr"], "spp"),
    (["compare", "{tmp}/missing.exr", "{tmp}/missing.exr"], "missing.exr: file: does not exist"),
    (["info"], "required"),
    (["denoise", "{log}", "-o", "{tmp}/o.exr", "--nonfinite", "keep"], "invalid choice"),
])
def test_bad_input_exits_2_with_one_line(tmp_path, scene_log, capsys, args, match):
    (tmp_path / "text.h5").write_text("not hdf5")
    args = [a.replace("{tmp}", str(tmp_path)).replace("{log}", str(scene_log)) for a in args]
    with pytest.raises(SystemExit) if args == ["info"] or "keep" in args else _nullcontext():
        code, out, err = run(args, capsys)
        assert code == 2
        lines = err.strip().splitlines()
        assert len(lines) == 1 and match in lines[0], err
        assert "Traceback" not in err
    if args == ["info"] or "keep" in args:
        err = capsys.readouterr().err
        assert match in err and len(err.strip().splitlines()) == 1


class _nullcontext:
    def __enter__(self):
        return self

    def __exit__(self, *a):
        return False


def test_positions_off_film_in_a_log(tmp_path, capsys):
    write_log(tmp_path / "x.h5", np.array([[0.5, 0.5]]), np.ones((1, 3)), width=2, height=2)
    with h5py.File(tmp_path / "x.h5", "r+") as f:
        f["positions"][0] = [5.0, 0.5]
    code, out, err = run(["denoise", tmp_path / "x.h5", "-o", tmp_path / "o.exr"], capsys)
    assert code == 2 and "x.h5: positions: 1 sample(s) off the film" in err


def test_empty_pixels_are_filled_with_a_warning(tmp_path, capsys):
    write_log(tmp_path / "x.h5", np.array([[0.5, 0.5]]), np.array([[2.0, 1.0, 0.5]]), width=3, height=1)
    code, out, err = run(["denoise", tmp_path / "x.h5", "-o", tmp_path / "o.exr"], capsys)
    assert code == 0 and "mcrecon: warning: " in err and "2 pixel(s) without samples" in err
    img, _ = read_exr(tmp_path / "o.exr")
    np.testing.assert_array_equal(img[0], [[2.0, 1.0, 0.5]] * 3)


def test_module_entry_point_runs_in_a_subprocess(tmp_path):
    r = subprocess.run([sys.executable, "-m", "mcrecon", "info", str(tmp_path / "none.h5")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "does not exist" in r.stderr

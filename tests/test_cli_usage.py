"""What the command line says when it is used wrongly or for the first time: one clean line, the close
option, the accepted inputs, the default output folders, the demo's compile notice and times."""

import json
import re

import numpy as np
import pytest

from mcrecon.io import write_exr, write_png_preview
from mcrecon.methods import available_methods

from helpers import run_cli


@pytest.fixture
def small_log(tmp_path, capsys):
    path = tmp_path / "s.h5"
    code, _, err = run_cli(["render-log", "--scene", "soft_shadow", "--spp", "2", "--size", "8x8", "-o", path], capsys)
    assert code == 0, err
    return path


@pytest.mark.parametrize("argv, typo, meant", [
    (["denoise", "{log}", "-o", "{tmp}/o.exr", "--methd", "gem"], "--methd", "--method"),
    (["denoise", "{log}", "-o", "{tmp}/o.exr", "--gama=0.2"], "--gama", "--gamma"),
    (["info", "{log}", "--jsn"], "--jsn", "--json"),
    (["experiment", "convergence", "--sise", "8x8"], "--sise", "--size"),
    (["mitsuba", "log", "--seeed", "1", "-o", "{tmp}/x.h5"], "--seeed", "--seed"),
])
def test_unknown_long_option_names_the_close_one(argv, typo, meant, small_log, tmp_path, capsys):
    argv = [a.format(log=small_log, tmp=tmp_path) for a in argv]
    code, out, err = run_cli(argv, capsys)
    assert code == 2 and out == "" and err.count("\n") == 1
    assert "unrecognized arguments: " in err and f"{typo}: did you mean {meant}?" in err
    assert not (tmp_path / "o.exr").exists()


def test_unknown_option_far_from_every_option_gets_no_guess(small_log, capsys):
    code, _, err = run_cli(["info", small_log, "--zzzzzz"], capsys)
    assert code == 2 and err == "mcrecon: error: unrecognized arguments: --zzzzzz\n"


@pytest.mark.parametrize("command", ["denoise", "adapt"])
def test_missing_output_is_one_prefix_and_names_the_command(command, small_log, capsys):
    argv = ["denoise", small_log] if command == "denoise" else ["adapt", "--scene", "flat", "--spp", "2"]
    code, out, err = run_cli(argv, capsys)
    assert code == 2 and out == ""
    assert err == f"mcrecon: error: {command}: -o/--output: missing: give the output EXR path\n"


def _exr(path):
    write_exr(path, np.ones((4, 4, 3), np.float32))


def _png(path):
    write_png_preview(path, np.ones((4, 4, 3), np.float32))


_OTHER_FORMATS = [
    (_exr, "x.exr", "it is an OpenEXR image"),
    (_png, "x.png", "it is a PNG image"),
    (lambda p: p.write_text("positions,values\n0.5,0.5,1\n"), "x.h5", "it is a text file"),
    (lambda p: p.write_bytes(b""), "x.h5", "it is an empty file (0 bytes)"),
]


# denoise reads an EXR as pixel statistics (tests/test_pixel_exr.py): not another format for it
@pytest.mark.parametrize("make, name, kind, command", [
    (*f, command) for command in ("info", "denoise", "resume") for f in _OTHER_FORMATS
    if not (command == "denoise" and f[1].endswith(".exr"))])
def test_a_file_of_another_format_says_what_it_is_and_what_is_accepted(make, name, kind, command, tmp_path,
                                                                       capsys):
    path = tmp_path / name
    make(path)
    argv = {"info": ["info", path], "denoise": ["denoise", path, "-o", tmp_path / "o.exr"],
            "resume": ["adapt", "--resume", path, "-o", tmp_path / "o.exr"]}[command]
    code, out, err = run_cli(argv, capsys)
    assert code == 2 and out == "" and err.count("\n") == 1
    assert err.startswith(f"mcrecon: error: {path}: file: not a readable HDF5 file: {kind}; ")
    assert "HDF5 sample log (.h5" in err and "pixel-statistics EXR" in err and "regenerate" not in err
    assert not (tmp_path / "o.exr").exists()


def test_a_truncated_log_is_named_as_such(small_log, tmp_path, capsys):
    cut = tmp_path / "cut.h5"
    cut.write_bytes(small_log.read_bytes()[:2000])
    code, _, err = run_cli(["info", cut], capsys)
    assert code == 2 and "not a readable HDF5 file (truncated or damaged: " in err and "regenerate it" in err


def test_methods_list_is_only_the_list_and_json(capsys):
    code, out, err = run_cli(["methods"], capsys)
    assert code == 0
    assert [line.split()[0] for line in out.splitlines()] == available_methods()  # nothing else on stdout
    assert "mcrecon methods NAME" in err and "--json" in err
    code, out, err = run_cli(["methods", "--json"], capsys)
    listed = json.loads(out)
    assert code == 0 and err == "" and [m["name"] for m in listed] == available_methods()
    code, out, _ = run_cli(["methods", "gem", "--json"], capsys)
    gem = json.loads(out)
    flags = {o["name"]: o["flag"] for o in gem["options"]}
    assert code == 0 and gem["name"] == "gem" and gem["adaptive"] is True
    assert flags["gamma"] == "--gamma" and gem["inputs"]["statistics"] is True
    assert gem == next(m for m in listed if m["name"] == "gem")
    code, out, err = run_cli(["methods", "nope", "--json"], capsys)
    assert code == 2 and out == "" and "unknown method 'nope'" in err


def test_convergence_writes_a_default_folder(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    code, out, err = run_cli(["experiment", "convergence", "--scene", "flat", "--size", "8x8", "--spp", "2",
                              "--modes", "uniform", "--methods", "box", "--oidn", "no", "--flip", "no"], capsys)
    assert code == 0, err
    assert (tmp_path / "convergence_flat" / "report.md").exists() and "wrote convergence_flat" in out


def test_bias_and_the_experiments_write_a_default_folder(tmp_path, monkeypatch, capsys):
    """`mcrecon bias --scene flat` stopped at `the following arguments are required: --out`, as convergence did."""
    monkeypatch.chdir(tmp_path)
    code, out, err = run_cli(["bias", "--scene", "flat", "--size", "8x8", "--spp", "8", "--B", "20"], capsys)
    assert code == 0, err
    assert (tmp_path / "bias_flat" / "bias.json").exists() and "wrote bias_flat" in out
    from mcrecon.cli import build_parser

    for cmd in (["experiment", "stability"], ["experiment", "gallery"], ["experiment", "error-rate"],
                ["experiment", "normality", "--scene", "flat"]):
        assert build_parser(cmd[0]).parse_args(cmd).out is None  # not required; the command names it


def test_demo_says_it_compiles_and_times_without_compiling(tmp_path, monkeypatch, capsys):
    from mcrecon.cli import builtins as commands_builtins

    calls = []
    from mcrecon.offline import reconstruction as rec_reconstruction

    real = rec_reconstruction.reconstruct

    def counting(source, method, **kw):
        calls.append((method.name, source.width))
        return real(source, method=method, **kw)

    monkeypatch.setattr(rec_reconstruction, "reconstruct", counting)
    monkeypatch.setattr(commands_builtins, "_COMPILING_AFTER", 0.0)  # as if the warm-up were compiling
    code, out, err = run_cli(["demo", "--size", "24x20", "--spp", "2", "--methods", "box,ci", "--out", tmp_path / "d"],
                             capsys)
    assert code == 0, err
    assert re.fullmatch(r"mcrecon: compiling kernels \(first run only, ~\d+ s\)\n", err)
    # a warm-up on a tiny log first, then each method twice on the demo's log: the second is timed
    assert calls == [("box", 16), ("ci", 16), ("box", 24), ("box", 24), ("ci", 24), ("ci", 24)]
    assert "time: the method's second reconstruction" in out and "ci is box here by design" in out
    monkeypatch.setattr(commands_builtins, "_COMPILING_AFTER", 1e6)  # a warm cache: no notice
    code, out, err = run_cli(["demo", "--size", "24x20", "--spp", "2", "--methods", "box", "--out", tmp_path / "d"],
                             capsys)
    assert code == 0 and err == "" and "ci and splat" not in out

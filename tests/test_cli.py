"""The mcrecon command line, end to end, as a user would run it."""

import ast
import json
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np

import mcrecon
import pytest

from mcrecon import InputError
from mcrecon.cli import main
from mcrecon.adaptive.run import adapt, resume
from mcrecon.io import read_exr, read_log, set_run_settings, summarize_log, write_exr, write_log
from mcrecon.methods import available_methods, method_class
from mcrecon.renderers import command_spec, renderer_from_spec, scene_spec

from helpers import MCRECON, run_cli, run_cli_process

ROOT = Path(__file__).parents[1]
EXAMPLE = str(ROOT / "data_tools" / "example_renderer.py")


@pytest.fixture
def scene_log(tmp_path, capsys):
    path = tmp_path / "flat.h5"
    code, out, err = run_cli(["render-log", "--scene", "soft_shadow", "--spp", "4", "--size", "24x16", "-o", path],
                             capsys)
    assert code == 0, err
    return path


def test_scenes_and_methods(capsys):
    code, out, _ = run_cli(["scenes"], capsys)
    assert code == 0 and "soft_shadow" in out and "caustic" in out
    code, out, _ = run_cli(["methods"], capsys)
    assert code == 0 and out.startswith("box")


def test_info(scene_log, capsys):
    code, out, _ = run_cli(["info", scene_log, "--json"], capsys)
    info = json.loads(out)
    assert code == 0 and info["width"] == 24 and info["samples"] == 24 * 16 * 4
    assert info["spp_min"] == info["spp_max"] == 4 and info["reference"] is True
    code, out, _ = run_cli(["info", scene_log], capsys)
    assert "spp_mean" in out and "4.000" in out


def test_info_counts_nonfinite_and_negative(tmp_path, capsys):
    val = np.array([[1.0], [np.nan], [-2.0], [np.inf]])
    write_log(tmp_path / "x.h5", np.array([[0.5, 0.5]] * 4), val, width=2, height=1, channels=["Y"])
    code, out, err = run_cli(["info", tmp_path / "x.h5", "--json"], capsys)
    info = json.loads(out)
    assert info["nonfinite_samples"] == 2 and info["negative_samples"] == 1 and info["empty_pixels"] == 1


def test_reconstruct_is_the_verb_and_denoise_its_alias(scene_log, tmp_path, capsys):
    """One verb (issue 23): `mcrecon reconstruct`, as mcrecon.reconstruct; `denoise` stays an alias."""
    a, b = tmp_path / "a.exr", tmp_path / "b.exr"
    assert run_cli(["reconstruct", scene_log, "-o", a, "--method", "gem"], capsys)[0] == 0
    assert run_cli(["denoise", scene_log, "-o", b, "--method", "gem"], capsys)[0] == 0
    np.testing.assert_array_equal(read_exr(a)[0], read_exr(b)[0])
    np.testing.assert_array_equal(read_exr(a)[0], mcrecon.reconstruct(scene_log, method="gem").astype(np.float32))
    from mcrecon.cli import build_parser

    assert "alias: denoise" in build_parser().format_help()


def test_denoise_writes_exr_png_and_diagnostics(scene_log, tmp_path, capsys):
    out_exr = tmp_path / "o.exr"
    code, out, err = run_cli(["denoise", scene_log, "-o", out_exr, "--method", "box", "--diagnostics", tmp_path / "d"],
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
    code, out, err = run_cli(["adapt", "--scene", "flat", "--size", "16x16", "--spp", "4", "--method", "box",
                              "-o", tmp_path / "a.exr", "--log", tmp_path / "a.h5", "--quiet"], capsys)
    assert code == 0, err
    assert "stopped: budget" in out and "renderer" in out and "toolkit" in out and "relative MSE" in out
    assert read_log(tmp_path / "a.h5").n_samples == 16 * 16 * 4
    code, out, err = run_cli(["adapt", "--scene", "flat", "--size", "16x16", "--spp", "8", "--method", "box",
                              "-o", tmp_path / "b.exr", "--rounds-json", tmp_path / "r.json", "--quiet"], capsys)
    rounds = json.loads((tmp_path / "r.json").read_text())
    assert code == 0 and [r["samples_total"] for r in rounds] == [256, 512, 1024, 2048]
    assert rounds[-1]["error"] < rounds[0]["error"] and all(r["toolkit_seconds"] >= 0 for r in rounds)
    code, out, err = run_cli(["adapt", "--scene", "flat", "--size", "8x8", "--spp", "2", "--method", "box",
                              "-o", tmp_path / "c.exr", "--log", tmp_path / "c.h5", "--storage-dtype", "float64",
                              "--quiet"], capsys)
    assert code == 0 and read_log(tmp_path / "c.h5").value_dtype == np.float64
    img, _ = read_exr(tmp_path / "a.exr")
    write_exr(tmp_path / "ref.exr", np.full_like(img, 0.5))
    code, out, err = run_cli(["compare", tmp_path / "a.exr", tmp_path / "ref.exr", "--json"], capsys)
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
    code, out, err = run_cli(args, capsys)   # the parser's refusals included (its SystemExit)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and match in lines[0], err
    assert "Traceback" not in err


def test_positions_off_film_in_a_log(tmp_path, capsys):
    write_log(tmp_path / "x.h5", np.array([[0.5, 0.5]]), np.ones((1, 3)), width=2, height=2)
    with h5py.File(tmp_path / "x.h5", "r+") as f:
        f["positions"][0] = [5.0, 0.5]
    code, out, err = run_cli(["denoise", tmp_path / "x.h5", "-o", tmp_path / "o.exr"], capsys)
    assert code == 2 and "x.h5: positions: 1 sample(s) off the film" in err


def test_empty_pixels_are_filled_with_a_warning(tmp_path, capsys):
    write_log(tmp_path / "x.h5", np.array([[0.5, 0.5]]), np.array([[2.0, 1.0, 0.5]]), width=3, height=1)
    code, out, err = run_cli(["denoise", tmp_path / "x.h5", "-o", tmp_path / "o.exr"], capsys)
    assert code == 0 and "mcrecon: warning: " in err and "2 pixel(s) without samples" in err
    img, _ = read_exr(tmp_path / "o.exr")
    np.testing.assert_array_equal(img[0], [[2.0, 1.0, 0.5]] * 3)


def test_module_entry_point_runs_in_a_subprocess(tmp_path):
    r = run_cli_process(["info", tmp_path / "none.h5"])
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "does not exist" in r.stderr


# ------------------------------------------------------------------ info
def test_info_prints_summarize_log(scene_log, capsys):
    code, out, _ = run_cli(["info", scene_log, "--json"], capsys)
    got = json.loads(out)
    assert code == 0 and got.pop("feature_details") == [] and got == json.loads(json.dumps(summarize_log(scene_log)))


@pytest.mark.parametrize("breakage, match", [
    (lambda f: f.attrs.__setitem__("format_version", "one"), "expected the integer 1"),
    (lambda f: f.require_group("run").attrs.__setitem__("settings_json", "{bad"), "not valid JSON"),
])
def test_info_on_a_malformed_log_is_one_line(tmp_path, capsys, breakage, match):
    path = write_log(tmp_path / "m.h5", np.full((4, 2), 0.5), np.ones((4, 3)), width=2, height=2)
    with h5py.File(path, "r+") as f:
        breakage(f)
    code, out, err = run_cli(["info", path], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and match in err


def test_info_into_a_closed_pipe_exits_0(scene_log):
    # `mcrecon info LOG | head -1`: the reader is gone before mcrecon writes.
    proc = subprocess.Popen([*MCRECON, "info", str(scene_log)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()
    err = proc.stderr.read().decode()
    proc.stderr.close()
    assert proc.wait() == 0 and err == ""
    r = subprocess.run(["bash", "-c", f"set -o pipefail; {sys.executable} -m mcrecon info {scene_log} | head -1"],
                       capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.startswith("file") and r.stderr == ""


def test_log_outputs_are_logs_and_are_not_replaced_silently(tmp_path, capsys):
    # render-log replaced a 5-round adaptive log without a word, and wrote HDF5 into "x.exr" (which
    # every later command then refused as "not an OpenEXR file")
    log = tmp_path / "keep.h5"
    args = ["render-log", "--scene", "flat", "--spp", "1", "--size", "4x4", "-o"]
    code, _, err = run_cli(args + [str(log)], capsys)
    assert code == 0 and log.is_file()
    before = log.read_bytes()
    code, _, err = run_cli(args + [str(log)], capsys)
    assert code == 2 and "exists" in err and "--overwrite" in err and len(err.strip().splitlines()) == 1
    assert log.read_bytes() == before
    code, _, err = run_cli(["render-log", "--scene", "flat", "--spp", "2", "--size", "4x4", "-o", str(log),
                            "--overwrite"], capsys)
    assert code == 0 and log.read_bytes() != before
    for bad in (["render-log", "--scene", "flat", "--spp", "1", "--size", "4x4", "-o", str(tmp_path / "x.exr")],
                ["adapt", "--scene", "flat", "--spp", "2", "--size", "4x4", "--log", str(tmp_path / "x.exr"),
                 "-o", str(tmp_path / "y.exr")],
                ["mitsuba", "reference", "--spp", "1", "-o", str(tmp_path / "r.h5")]):
        code, _, err = run_cli(bad, capsys)
        assert code == 2 and "expected a path ending in" in err and len(err.strip().splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.h5"]


def test_a_closed_pipe_does_not_stop_the_command(tmp_path):
    # `mcrecon render-log ... | head -1`: the reader leaves after the first line, and the files printed
    # after it (here the reference EXR) must still be written
    log, exr = tmp_path / "r.h5", tmp_path / "ref.exr"
    proc = subprocess.Popen([*MCRECON, "render-log", "--scene", "soft_shadow", "--size", "8x8", "--spp", "2", "-o",
                             str(log), "--reference-exr", str(exr)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    proc.stdout.close()
    assert proc.wait() == 0
    assert log.is_file() and exr.is_file()


def test_render_log_writes_the_stored_reference_as_exr(tmp_path, capsys):
    log, ref = tmp_path / "c.h5", tmp_path / "ref.exr"
    assert main(["render-log", "--scene", "caustic", "--spp", "2", "--size", "12x8", "-o", str(log),
                 "--reference-exr", str(ref)]) == 0
    assert f"wrote {ref}" in capsys.readouterr().out
    img, channels = read_exr(ref)
    stored = read_log(log)
    assert channels == stored.channels
    assert np.array_equal(img, stored.reference().astype(np.float32))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.h5", "ref.exr", "ref.png"]   # and its preview; no temporary left

    other = tmp_path / "d.h5"
    for bad, text in ((str(other), "is the -o sample log"), (str(tmp_path / "r.png"), ".exr")):
        code, _, err = run_cli(["render-log", "--scene", "caustic", "--spp", "2", "--size", "12x8", "-o", other,
                                "--reference-exr", bad], capsys)
        assert code == 2 and err.count("\n") == 1 and text in err, err
    assert not other.exists()                            # refused before any work


def test_closed_descriptors_do_not_stop_the_command(tmp_path):
    # `>&- 2>&-`: Python leaves sys.stdout/sys.stderr None; wrapping None was a traceback (exit 120)
    log, exr = tmp_path / "c.h5", tmp_path / "c.exr"
    cmd = (f"{sys.executable} -m mcrecon render-log --scene flat --spp 1 --size 4x4 -o {log} "
           f"--reference-exr {exr} >&- 2>&-")
    assert subprocess.run(["bash", "-c", cmd]).returncode == 0
    assert log.is_file() and exr.is_file()
    assert subprocess.run(["bash", "-c", cmd]).returncode == 2  # the log exists: refused, even unheard


# ------------------------------------------------------------------ method options
@pytest.mark.parametrize("command", ["denoise", "adapt"])
def test_help_groups_the_options_per_method(command, capsys):
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    sections, title = {}, None
    for line in text.splitlines():
        if line and not line[0].isspace() and line.endswith(":"):  # a group's title
            title = line[:-1]
            sections[title] = ""
        elif title is not None:
            sections[title] += line + "\n"
    flags = {o.name: ("--method-" if o.name == "exposure" else "--") + o.name.replace("_", "-")
             for name in available_methods() for o in method_class(name).options}
    for name in available_methods():
        cls = method_class(name)
        titles = [t for t in sections if t.startswith(f"{name} options (")]
        if not cls.options:
            assert not titles
            continue
        assert len(titles) == 1, (name, list(sections))
        body = sections[titles[0]]
        for o in cls.options:
            assert flags[o.name] in body, (name, o.name)
            # the flag's help comes from the Option: its default and valid values
            assert f"default: {o.default}" in " ".join(body.split()), (name, o.name)
    # an option of several methods is registered once and named in the other groups
    gem = sections[next(t for t in sections if t.startswith("gem options"))]
    awr = sections[next(t for t in sections if t.startswith("awr options"))]
    assert "--initial-spp N " in gem and "--initial-spp N: the flag listed under gem options; for awr:" in awr


def test_methods_describes_one_method(capsys):
    code, out, err = run_cli(["methods", "gem"], capsys)
    assert code == 0, err
    for o in method_class("gem").options:
        line = next(ln for ln in out.splitlines() if ln.split()[:1] == [o.flag])
        assert f"{o.type.__name__}, default {o.default}" in line
        assert o.expectation().split("(")[0].strip() in " ".join(out.split())
    assert "inputs (method.requires" in out and "pixel statistics" in out and "reference image" in out
    assert "per-sample features      not read" in out
    code, out, err = run_cli(["methods", "nfor"], capsys)
    assert code == 0 and "per-sample features      required" in out
    code, out, err = run_cli(["methods", "ci"], capsys)
    assert code == 0 and "--method-exposure" in out  # ci's exposure on denoise/adapt (which have --exposure)
    code, out, err = run_cli(["methods", "nope"], capsys)
    assert code == 2 and "unknown method 'nope'" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("args, match", [
    (["--method", "gem", "--tolerance", "0.1"], "method gem: --tolerance: does not apply to this method "
                                                 "(an option of ci)"),
    (["--method", "splat", "--wavelet", "haar"], "--wavelet: does not apply"),
    (["--method", "gem", "--gamma", "0.5"], "method gem: --gamma: '0.5', expected a finite number with 0 < gamma"),
    (["--method", "gem", "--iterations", "2.5"], "method gem: --iterations: '2.5', expected an integer"),
    (["--method", "awr", "--wavelet", "db4"], "method awr: --wavelet: 'db4' is not valid; valid: cdf97"),
    (["--method", "ci", "--method-exposure", "x"], "method ci: --method-exposure: 'x', expected a finite number"),
])
def test_method_flags_are_checked_against_the_chosen_method(scene_log, tmp_path, capsys, args, match):
    code, out, err = run_cli(["denoise", scene_log, "-o", tmp_path / "o.exr", *args], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and match in err, err
    assert not (tmp_path / "o.exr").exists()


def test_shared_flag_goes_to_the_chosen_method(scene_log, tmp_path, capsys):
    code, out, err = run_cli(["denoise", scene_log, "-o", tmp_path / "o.exr", "--method", "ci", "--gamma", "1.8",
                              "--alpha", "0.1"], capsys)
    assert code == 0, err


def test_bias_takes_the_stopping_rule_of_method_ci(tmp_path, capsys):
    code, out, err = run_cli(["bias", "--scene", "flat", "--size", "4x4", "--spp", "8", "--B", "5", "--tolerance",
                              "wide", "--out", tmp_path], capsys)
    assert code == 2 and "method ci: --tolerance: 'wide'" in err and len(err.strip().splitlines()) == 1


# ------------------------------------------------------------------ resume
def test_python_resume_rebuilds_a_scene_renderer_from_the_log(tmp_path):
    spec = scene_spec("soft_shadow", width=16, height=12, seed=3)
    kw = dict(spp=8, seed=5, renderer_spec=spec, progress=False)
    full = adapt(renderer_from_spec(spec), "gem", log=tmp_path / "full.h5", **kw)
    part = adapt(renderer_from_spec(spec), "gem", log=tmp_path / "part.h5", max_rounds=2, **kw)
    assert part.stopped == "max_rounds" and len(full.rounds) > 2
    res = resume(tmp_path / "part.h5", progress=False)
    np.testing.assert_array_equal(res.image, full.image)
    assert res.stats.n_samples == full.stats.n_samples == read_log(tmp_path / "part.h5").n_samples


def test_python_resume_rebuilds_a_command_renderer_from_the_log(tmp_path):
    spec = command_spec([sys.executable, EXAMPLE, "{request}", "{reply}"], width=12, height=8)
    kw = dict(spp=8, seed=2, renderer_spec=spec, progress=False)
    full = adapt(renderer_from_spec(spec), "box", log=tmp_path / "full.h5", **kw)
    part = adapt(renderer_from_spec(spec), "box", log=tmp_path / "part.h5", max_rounds=1, **kw)
    assert part.stopped == "max_rounds" and len(full.rounds) > 1
    res = resume(tmp_path / "part.h5", progress=False)
    np.testing.assert_array_equal(res.image, full.image)
    np.testing.assert_array_equal(read_log(tmp_path / "part.h5").read_all().values,
                                  read_log(tmp_path / "full.h5").read_all().values)


@pytest.mark.parametrize("change, field", [
    ({"scene": "nope"}, "run settings renderer_spec.scene"),
    ({"width": "16"}, "run settings renderer_spec.width"),
    ({"kind": "povray"}, "run settings renderer_spec.kind"),
    ({"colour": 1}, "run settings renderer_spec.colour"),
    (None, "run settings renderer_spec"),
])
def test_a_bad_recorded_renderer_spec_names_the_field(tmp_path, capsys, change, field):
    log = tmp_path / "r.h5"
    spec = scene_spec("flat", width=16, height=12)
    adapt(renderer_from_spec(spec), "box", spp=4, log=log, renderer_spec=spec, max_rounds=1, progress=False)
    settings = read_log(log).run_settings
    settings["renderer_spec"] = None if change is None else {**spec, **change}
    set_run_settings(log, settings)
    with pytest.raises(InputError) as exc:
        resume(log)
    assert (exc.value.where, exc.value.field) == (str(log), field)
    code, out, err = run_cli(["adapt", "--resume", log, "-o", tmp_path / "o.exr", "--quiet"], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and f"r.h5: {field}" in err


# ------------------------------------------------------------------ moved from test_review_fixes.py
def test_cli_output_problems_are_one_line_errors_before_any_work(tmp_path, capsys):
    log = write_log(tmp_path / "a.h5", np.full((4, 2), 0.5), np.ones((4, 3)), width=2, height=2)
    (tmp_path / "afile").write_text("x")
    cases = [
        ["denoise", str(log)],
        ["denoise", str(log), "-o", str(tmp_path / "afile" / "x.exr")],
        ["adapt", "--scene", "flat", "--size", "8x8", "--spp", "1e308", "-o", str(tmp_path / "o.exr")],
        ["adapt", "--scene", "flat", "--size", "8x8", "--spp", "4", "--log", str(tmp_path / "l.h5")],
        ["adapt", "--scene", "flat", "--size", "8x8", "--spp", "4", "-o", str(tmp_path / "o.png")],
        ["info", str(tmp_path)],
    ]
    for args in cases:
        assert main(args) == 2, args
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, (args, err)
    assert not (tmp_path / "l.h5").exists()  # refused before rendering anything


def test_resume_honours_time_limit_and_refuses_run_flags(tmp_path, capsys):
    log = tmp_path / "r.h5"
    args = ["adapt", "--scene", "flat", "--size", "8x8", "--spp", "64", "--quiet"]
    assert main(args + ["--log", str(log), "--time-limit", "1e-9", "-o", str(tmp_path / "a.exr")]) == 0
    assert "stopped: time_limit" in capsys.readouterr().out
    assert main(["adapt", "--resume", str(log), "--spp", "8", "-o", str(tmp_path / "b.exr")]) == 2
    assert "--spp" in capsys.readouterr().err
    assert main(["adapt", "--resume", str(log), "--time-limit", "600", "-o", str(tmp_path / "b.exr"), "--quiet"]) == 0
    assert "stopped: budget" in capsys.readouterr().out
    assert read_log(log).n_samples == 8 * 8 * 64


# ------------------------------------------------------------------ structure
def test_cli_modules_import_only_downward():
    """__init__ -> commands, experiments, batch -> _common; never back up (no import cycles)."""
    cli = ROOT / "mcrecon" / "cli"
    allowed = {"__init__": {"commands", "experiments", "batch", "blender", "_common"},
               "commands": {"_common", "builtins"}, "builtins": {"_common"},
               "experiments": {"_common"}, "batch": {"_common"}, "blender": {"_common"}, "_common": set()}
    for path in sorted(cli.glob("*.py")):
        seen = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level == 1:
                seen.update([node.module] if node.module else [a.name for a in node.names])
            elif isinstance(node, ast.ImportFrom) and node.level >= 2 and (node.module or "").startswith("cli"):
                seen.add(node.module)
        assert seen <= allowed[path.stem], (path.name, seen - allowed[path.stem])


def test_storage_dtype_flag_offers_what_the_driver_accepts():
    from mcrecon.cli import build_parser
    from mcrecon.adaptive.schedule import STORAGE_DTYPES
    p = build_parser()
    adapt = p._subparsers._group_actions[0].choices["adapt"]
    action = next(a for a in adapt._actions if "--storage-dtype" in a.option_strings)
    assert tuple(action.choices) == STORAGE_DTYPES and action.default == "auto"


def test_demo_writes_every_method_and_reports_its_error(tmp_path, capsys):
    """The README's first command, small: a log, one EXR + PNG per method, each method's relative MSE."""
    import re
    import mcrecon
    out = tmp_path / "demo"
    code, text, err = run_cli(["demo", "--size", "24x20", "--spp", "4", "--out", str(out)], capsys)
    assert code == 0, err
    # the default list leaves out the methods that need per-sample features (the scene's log has none)
    methods = [n for n in mcrecon.available_methods() if mcrecon.get_method(n).requires.features != "required"]
    errors = dict(re.findall(r"^(\w+)\s+relative MSE ([0-9.eE+-]+)", text, re.M))
    assert set(errors) == set(methods)
    ref, _ = mcrecon.read_exr(out / "soft_shadow_reference.exr")
    for name in methods:
        img, _ = mcrecon.read_exr(out / f"soft_shadow_{name}.exr")
        assert img.shape == (20, 24, 3) and (out / f"soft_shadow_{name}.png").exists()
        from mcrecon.core.metrics import relative_mse
        assert float(errors[name]) == pytest.approx(relative_mse(img.astype(np.float64), ref), rel=1e-4)
    assert mcrecon.read_log(out / "soft_shadow.h5").n_samples == 24 * 20 * 4


def test_adapt_names_where_its_time_went(tmp_path, capsys):
    # with --rounds-json the error after each round took 1.45 s of a 1.82 s run and the line named only
    # the renderer's 0.02 s and the toolkit's 0.08 s
    code, out, err = run_cli(["adapt", "--scene", "flat", "--size", "8x8", "--spp", "8", "--method", "gem", "-o",
                              str(tmp_path / "a.exr"), "--rounds-json", str(tmp_path / "r.json")], capsys)
    assert code == 0
    line = out.splitlines()[0]
    assert "final image" in line and "error after each round" in line
    code, out, err = run_cli(["adapt", "--scene", "flat", "--size", "8x8", "--spp", "8", "--method", "gem", "-o",
                              str(tmp_path / "b.exr")], capsys)
    assert code == 0 and "final image" in out and "error after each round" not in out


def test_adapt_scene_features_opt_in(tmp_path, capsys):
    # `mcrecon scenes` calls soft_shadow's features opt-in, but adapt refused --features without --mitsuba
    from mcrecon.io import read_log

    log = tmp_path / "f.h5"
    code, out, err = run_cli(["adapt", "--scene", "soft_shadow", "--features", "all", "--size", "8x8", "--spp", "4",
                              "--method", "nfor", "--log", str(log), "-o", str(tmp_path / "f.exr")], capsys)
    assert code == 0, err
    assert set(read_log(log).feature_names) == {"albedo", "normal", "depth"}
    assert read_log(log).run_settings["renderer_spec"]["features"] is True   # a resume sends them again
    code, _, err = run_cli(["adapt", "--scene", "checker_wall", "--features", "albedo", "--size", "8x8", "--spp", "2",
                            "-o", str(tmp_path / "g.exr")], capsys)
    assert code == 2 and "with --scene, all" in err and len(err.strip().splitlines()) == 1

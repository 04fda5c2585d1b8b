"""A new user's first hour: the commands and outputs README.md and docs/index.md advertise, run as a user
runs them -- from a scratch folder outside the repository, as written -- and the files they leave behind.

What tests/test_docs_commands.py runs block by block is checked here for what it does not see: the
experiment the README's prose names, a terminal's Ctrl-C, what a person sees in the PNGs, and which
skips the README's install leaves.
"""

from __future__ import annotations

import ast
import re
import tempfile
import warnings

import numpy as np
import pytest

from helpers import MCRECON, ROOT, cli_env, run_cli, run_cli_process


@pytest.fixture
def scratch(tmp_path, monkeypatch):
    """A scratch folder outside the repository as the working directory, and a temporary folder of its own
    (to see what a command leaves there)."""
    work, tmp = tmp_path / "work", tmp_path / "tmp"
    work.mkdir()
    tmp.mkdir()
    monkeypatch.chdir(work)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp))
    return work, tmp


# ---- experiment convergence ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("scene", ["soft_shadow", "checker_wall"])
def test_convergence_as_advertised_runs_every_method_and_leaves_nothing_in_tmp(scene, scratch, capsys):
    """`mcrecon experiment convergence --scene S --html` (README, docs/index.md): its default methods
    include nfor, which needs the features the experiment renders when the scene has them."""
    work, tmp = scratch
    code, out, err = run_cli(["experiment", "convergence", "--scene", scene, "--html", "--size", "12x8", "--spp", "2",
                          "--oidn", "no", "--flip", "no"], capsys)
    assert code == 0, err
    assert re.search(r"^nfor +uniform", out, re.M) and re.search(r"^auto +adaptive", out, re.M)
    assert (work / f"convergence_{scene}" / "report.html").stat().st_size > 0
    assert list(tmp.iterdir()) == []


def test_convergence_auto_and_nfor_see_what_reconstruct_sees_on_a_log_of_the_scene(tmp_path):
    """The textured scenes' features reach the methods: each image is the one `reconstruct` makes of a
    `render-log` log of the same scene, spp and seed."""
    import mcrecon
    from mcrecon.experiments.convergence import run_convergence
    from mcrecon.renderers.scenes import write_scene_log

    size, spp = (24, 16), 4
    res = run_convergence("checker_wall", methods=["box", "auto", "nfor"], spp=[spp], size=size,
                          modes=["uniform"], oidn=False, flip=False)
    log = write_scene_log("checker_wall", tmp_path / "cw.h5", width=size[0], height=size[1], spp=spp)
    for name in ("box", "auto", "nfor"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            expected = mcrecon.reconstruct(log, method=name)
        np.testing.assert_array_equal(res.images[(name, "uniform")], expected, err_msg=name)


def test_convergence_without_features_refuses_nfor_in_one_line_before_rendering(scratch, capsys):
    work, tmp = scratch
    code, out, err = run_cli(["experiment", "convergence", "--scene", "checker_wall", "--no-features", "--methods",
                          "box,nfor", "--size", "12x8", "--spp", "2"], capsys)
    assert code == 2 and out == "" and err.count("\n") == 1
    assert err.startswith("mcrecon: error: convergence: methods: nfor needs per-sample features")
    assert "--no-features" in err and "leave nfor out of --methods" in err and "mcrecon-convergence" not in err
    assert list(tmp.iterdir()) == [] and list(work.iterdir()) == []


def test_convergence_without_features_leaves_nfor_out_of_the_default_methods(scratch, capsys):
    code, out, err = run_cli(["experiment", "convergence", "--scene", "flat", "--no-features", "--size", "8x8",
                          "--spp", "2", "--modes", "uniform", "--oidn", "no", "--flip", "no"], capsys)
    assert code == 0, err
    assert not re.search(r"^nfor ", out, re.M) and re.search(r"^auto +uniform", out, re.M)
    assert "note: nfor left out: this run renders no per-sample features" in out


def test_convergence_failing_mid_run_leaves_nothing_in_tmp_and_names_no_temporary_file(scratch, monkeypatch):
    from mcrecon.errors import InputError
    from mcrecon.experiments import convergence

    _, tmp = scratch
    real = convergence.reconstruct

    def failing(source, **kw):
        if str(source).endswith("u4.h5"):
            raise InputError(str(source), "dataset /values", f"{source} is broken")
        return real(source, **kw)

    monkeypatch.setattr(convergence, "reconstruct", failing)
    with pytest.raises(InputError) as exc:
        convergence.run_convergence("flat", methods=["box"], spp=[2, 4], size=(8, 8), modes=["uniform"],
                                    oidn=False, flip=False)
    assert "mcrecon-convergence" not in str(exc.value) and str(tmp) not in str(exc.value)
    assert exc.value.where == "convergence flat uniform 4 spp"
    assert list(tmp.iterdir()) == []


def test_time_plot_runs_forward_in_time_in_budget_order(tmp_path, monkeypatch):
    """Per-run times jitter on a shared machine (a later budget can take less time than an earlier one);
    each method's line still goes forward in time, through its budgets in order."""
    import matplotlib.axes

    from mcrecon.experiments.convergence import ConvergenceResult, _write_convergence

    base = {"scene": "flat", "mode": "uniform", "samples": 64, "renderer_seconds": 0.0, "smape": 0.1,
            "one_minus_ssim": 0.1, "rmse": 0.1, "ssim": 0.9}
    times = {2: 0.30, 4: 0.05, 8: 0.20, 16: 0.08}  # jittered: not in budget order
    rows = [dict(base, method="box", spp=s, toolkit_seconds=t, wall_seconds=t, relative_mse=1.0 / s)
            for s, t in times.items()]
    lines = []
    real = matplotlib.axes.Axes.loglog
    monkeypatch.setattr(matplotlib.axes.Axes, "loglog",
                        lambda self, x, y, *a, **k: (lines.append((list(x), list(y))), real(self, x, y, *a, **k))[1])
    res = ConvergenceResult(rows, {}, {}, np.ones((4, 4, 3)), 16, [], flip=False)
    _write_convergence(res, tmp_path, scene="flat")
    by_spp, by_time = lines
    assert by_spp == ([2, 4, 8, 16], [0.5, 0.25, 0.125, 0.0625])
    xs, ys = by_time
    assert ys == [0.5, 0.25, 0.125, 0.0625]                         # budgets in order: the error falls
    assert all(b > a for a, b in zip(xs, xs[1:]))                    # and time only goes forward
    assert xs[-1] == pytest.approx(sum(times.values()))


# ---- the README's command-line block ------------------------------------------------------------------------------

def _readme_block(heading: str) -> str:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text[text.index(f"\n## {heading}\n"):]
    m = re.search(r"^```(sh|python)\n(.*?)^```", section, re.M | re.S)
    return m.group(2)


def _shell_commands(block: str) -> list[list[str]]:
    import shlex

    return [shlex.split(line, comments=True) for line in block.replace("\\\n", " ").splitlines()
            if shlex.split(line, comments=True)]


def test_readme_command_block_writes_each_output_once():
    """The gem image the diagnostics describe is not replaced by a later command's: one command, one name
    (but the resume, which continues the run that wrote it)."""
    written = {}
    for argv in _shell_commands(_readme_block("Command line")):
        for flag in ("-o", "--reference-exr", "--log"):
            if flag in argv:
                path = argv[argv.index(flag) + 1]
                assert path not in written or "--resume" in argv, f"{path}: {written.get(path)} and {argv}"
                written[path] = argv
        if argv[:2] == ["mcrecon", "reconstruct"]:
            gem_out = argv[argv.index("-o") + 1]
    assert any(a[:2] == ["mcrecon", "compare"] and a[2] == gem_out for a in _shell_commands(
        _readme_block("Command line")))


def test_readme_command_block_runs_as_written_outside_the_repository(scratch, monkeypatch, capsys):
    """Copied into a terminal in any folder (the venv active: `python` and `mcrecon` are its own), every
    line works: nothing relative to the clone.  tests/test_docs_commands.py leaves this block to this test,
    so the checks of its own runner are here too (exit 0, no `mcrecon: error` on stderr)."""
    import os
    import subprocess
    import sys

    work, _ = scratch
    monkeypatch.setenv("PATH", os.path.dirname(sys.executable) + os.pathsep + os.environ.get("PATH", ""))
    # an installed mcrecon: importable by the renderer command from any folder
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(ROOT)] + [p for p in os.environ.get("PYTHONPATH", "")
                                                                     .split(os.pathsep) if p]))
    for argv in _shell_commands(_readme_block("Command line")):
        assert argv[0] == "mcrecon", argv
        code, out, err = run_cli(argv[1:], capsys)
        assert code == 0 and "mcrecon: error" not in err, f"{' '.join(argv)} exited {code}: {err.strip()}"
    for name in ("caustic_reference.exr", "caustic_reference.png", "caustic_gem.exr", "diag/sample_density.png",
                 "adapt_gem.exr", "ext.exr"):
        assert (work / name).stat().st_size > 0, name
    assert not (work / "data_tools").exists()
    proc = subprocess.run([sys.executable, "-m", "mcrecon.renderers.example"], capture_output=True, text=True,
                          cwd=work)
    assert proc.returncode == 2 and proc.stderr.startswith("usage: python -m mcrecon.renderers.example")


def test_packaged_example_renderer_answers_as_the_script_in_the_clone(tmp_path):
    """`python -m mcrecon.renderers.example` (the README's) and data_tools/example_renderer.py (h5py alone,
    the protocol spelled out) are one renderer: the same reply to the same request."""
    import importlib.util

    from mcrecon.core.requests import SampleRequest
    from mcrecon.io import read_log
    from mcrecon.renderers import example
    from mcrecon.renderers.command import write_request

    counts = np.arange(12, dtype=np.int64).reshape(3, 4) % 3
    req = SampleRequest(4, 3, counts=counts, positions=np.array([[0.5, 0.5], [3.25, 2.75]]), round_index=2, seed=7)
    write_request(tmp_path / "req.h5", req, channels=("R", "G", "B"))
    spec = importlib.util.spec_from_file_location("example_script", ROOT / "data_tools" / "example_renderer.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    script.main(tmp_path / "req.h5", tmp_path / "a.h5")
    example.main(tmp_path / "req.h5", tmp_path / "b.h5")
    a, b = read_log(tmp_path / "a.h5"), read_log(tmp_path / "b.h5")
    assert a.channels == b.channels == ("R", "G", "B") and a.n_samples == b.n_samples == counts.sum() + 2
    np.testing.assert_array_equal(a.read_all().positions, b.read_all().positions)
    np.testing.assert_array_equal(a.read_all().values, b.read_all().values)


# ---- Ctrl-C ---------------------------------------------------------------------------------------------------------

def test_ctrl_c_in_adapt_with_a_log_says_how_to_continue_and_that_command_does(scratch, capsys):
    import signal
    import subprocess
    import time

    work, _ = scratch
    env = cli_env({"MCRECON_SCENE_RATE": "2000"})  # a renderer slow enough to be interrupted half-way
    argv = [*MCRECON, "adapt", "--scene", "soft_shadow", "--size", "16x16", "--spp", "64",
            "--method", "box", "--log", "my run.h5", "-o", "o.exr", "--quiet"]
    # the child starts with Ctrl-C at its default disposition, as a shell starts a command: a test process
    # (an xdist worker after other tests ran in it) may have SIGINT ignored, which exec would pass on
    proc = subprocess.Popen(argv, cwd=work, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    t0 = time.monotonic()
    while not (work / "my run.h5").exists() and time.monotonic() - t0 < 60:
        time.sleep(0.05)
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)  # what Ctrl-C sends
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert err == "mcrecon: interrupted; `mcrecon adapt --resume 'my run.h5' -o o.exr` continues the run from " \
                  "its last committed round\n"
    resume = re.search(r"`mcrecon (.*?)`", err).group(1)
    import shlex

    code, out, err = run_cli(shlex.split(resume), capsys)  # that command, here (the working folder is work)
    assert code == 0 and "stopped: budget" in out, err
    assert "before this resume" in out


@pytest.mark.parametrize("argv", [
    ["adapt", "--scene", "flat", "--size", "8x8", "--spp", "4", "-o", "o.exr"],                       # no log
    ["adapt", "--scene", "flat", "--size", "8x8", "--spp", "4", "-o", "o.exr", "--log", "never.h5"],  # none yet
    ["reconstruct", "s.h5", "-o", "o.exr"],
])
def test_ctrl_c_without_a_log_on_disk_says_only_interrupted(argv, scratch, monkeypatch, capsys):
    from mcrecon.cli import commands

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(commands, "_cmd_adapt", interrupted)
    monkeypatch.setattr(commands, "_cmd_reconstruct", interrupted)
    code, out, err = run_cli(argv, capsys)
    assert code == 130 and err == "mcrecon: interrupted\n"


# ---- outputs a person reads ---------------------------------------------------------------------------------------

def test_render_log_reference_exr_gets_its_png_preview_beside_it(scratch, capsys):
    from PIL import Image

    work, _ = scratch
    code, out, err = run_cli(["render-log", "--scene", "soft_shadow", "--spp", "2", "--size", "24x16", "-o", "s.h5",
                          "--reference-exr", "ref.exr"], capsys)
    assert code == 0, err
    assert "wrote ref.exr" in out and "wrote ref.png" in out
    with Image.open(work / "ref.png") as im:
        assert im.size == (24, 16) and len(np.unique(np.asarray(im.convert("L")))) > 4  # the scene, not a blank


# ---- the README's Python section and help() -------------------------------------------------------------------------

def test_readme_python_block_runs_as_written(scratch):
    """Extracted and run in a fresh interpreter in a scratch folder: the renderer it passes to adapt is a
    mcrecon.CallableRenderer, and every name it uses is defined in it."""
    import subprocess
    import sys

    work, _ = scratch
    block = _readme_block("Python")
    assert "mcrecon.CallableRenderer(" in block and "mcrecon.adapt(renderer" in block
    (work / "example.py").write_text(block)
    proc = subprocess.run([sys.executable, "-W", "error", "example.py"], cwd=work, env=cli_env(), capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (work / "log.h5").exists() and (work / "run.h5").exists()


def test_adapt_refuses_a_plain_function_naming_callable_renderer():
    import mcrecon
    from mcrecon.errors import InputError

    def shade(request):
        return None

    with pytest.raises(InputError) as exc:
        mcrecon.adapt(shade, "gem", spp=4)
    assert exc.value.where == "adapt" and exc.value.field == "renderer"
    assert "shade is a plain function" in str(exc.value) and "mcrecon.CallableRenderer(fn, width=W, height=H)" \
        in str(exc.value)


def test_help_of_adapt_documents_every_parameter_and_its_example_runs():
    import doctest
    import inspect

    import mcrecon
    from mcrecon.adaptive import run as driver

    doc = mcrecon.adapt.__doc__
    for section in ("Parameters", "Returns", "Raises", "Examples"):
        assert f"\n    {section}\n    {'-' * len(section)}\n" in doc, section
    for name in inspect.signature(driver.adapt).parameters:
        assert re.search(rf"\n    {name} : ", doc), name
    assert "CallableRenderer" in doc and "resume" in doc
    test = doctest.DocTestParser().get_doctest(doc, {}, "mcrecon.adapt", None, 0)
    runner = doctest.DocTestRunner(verbose=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        runner.run(test)
    assert runner.tries > 0 and runner.failures == 0


def test_help_of_reconstruct_names_every_method_that_takes_half_buffers():
    import mcrecon
    from mcrecon.methods import half_buffer_methods

    doc = " ".join(mcrecon.reconstruct.__doc__.split())
    assert half_buffer_methods() == ["auto", "nfor"]
    for name in half_buffer_methods():
        assert f"``{name}``" in doc[doc.index("half-buffer pair"):doc.index("The pair must")], name


def test_diagnostics_pngs_have_a_title_with_the_values_and_a_colour_bar(scratch, monkeypatch, capsys):
    """A uniform log's sample_density is one value everywhere: the PNG says which, drawn mid-scale on a
    colour bar around it."""
    from matplotlib.figure import Figure
    from PIL import Image

    work, _ = scratch
    seen = {}
    real = Figure.savefig

    def recording(self, fname, *a, **k):
        cbar = [ax for ax in self.axes if ax.get_label() == "<colorbar>"]
        seen[len(seen)] = (self.axes[0].get_title(), cbar[0].get_ylim() if cbar else None)
        return real(self, fname, *a, **k)

    monkeypatch.setattr(Figure, "savefig", recording)
    code, _, err = run_cli(["render-log", "--scene", "flat", "--spp", "4", "--size", "24x16", "-o", "u.h5"], capsys)
    assert code == 0, err
    code, out, err = run_cli(["reconstruct", "u.h5", "-o", "u.exr", "--method", "gem", "--diagnostics", "diag"],
                             capsys)
    assert code == 0, err
    titles = {t.split(":")[0]: (t, lim) for t, lim in seen.values()}
    assert {"sample_density", "selected_scale"} <= set(titles)
    title, (lo, hi) = titles["sample_density"]
    assert title == "sample_density: every pixel 4" and lo < 4 < hi
    title, (lo, hi) = titles["selected_scale"]
    assert re.fullmatch(r"selected_scale: \S+ to \S+|selected_scale: every pixel \S+", title)
    with Image.open(work / "diag" / "sample_density.png") as im:
        assert im.size[0] > 24 * 4  # a figure, not the 24x16 map alone
        colours = np.unique(np.asarray(im.convert("RGB")).reshape(-1, 3), axis=0)
    assert len(colours) > 50  # text, axes and a colour bar beside the one colour of the map


# ---- what the README's install leaves skipped ---------------------------------------------------------------------

def test_readme_install_brings_oidn_and_says_how_to_get_the_mitsuba_tests():
    import tomllib

    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    assert any(re.match(r"pyoidn\b", d) for d in deps), deps  # `pip install -e ".[test]"` brings OIDN
    setup = (ROOT / "README.md").read_text(encoding="utf-8")
    setup = " ".join(setup[setup.index("## Set-up"):setup.index("## Methods")].split())
    assert "`PYTHON=.venv/bin/python bash data_tools/install_mitsuba.sh`" in setup
    assert "Mitsuba 3 bridge's tests need" in setup and "libLLVM 19" in setup
    assert (ROOT / "data_tools" / "install_mitsuba.sh").exists()


#: Words that say how to get what a skipped test lacks.
#: What a skip reason names to say how to get the missing thing (a package to install, a variable to set,
#: root; for a CPU the pins cannot be checked on, the machine to run them on).
_HOW = ("install", "pip ", "apt", "root", "MCRECON_", "on an x86-64 machine")
#: Variables whose text says it already: mitsuba_available()'s reason (checked below), the C tools' and the
#: docs test's HDF5 checks (install hints, collected in ``skipped``) and the docs' skip marks (why a block
#: is not run here, tests/test_docs_commands.py).
_SAYS_HOW = {"_REASON", "reason", "why", "skipped"}


def _skip_reasons():
    """(file:line, reason node or None) of every skip in tests/*.py: pytest.skip(...), importorskip's
    reason=, skipif's reason=."""
    for path in sorted((ROOT / "tests").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not isinstance(node, ast.Call):
                continue
            name = ast.unparse(node.func)
            if name not in ("pytest.skip", "pytest.importorskip", "pytest.mark.skipif"):
                continue
            reason = next((k.value for k in node.keywords if k.arg == "reason"), None)
            if name == "pytest.skip" and reason is None and node.args:
                reason = node.args[0]
            yield f"{path.name}:{node.lineno}", reason


def test_every_skip_reason_says_what_is_missing_and_how_to_get_it():
    """`pytest -rs` after the README's install: each skip names what it lacks and how to get it (a skip
    that is a statement about the code, not a missing thing, is no skip: such a case leaves the grid)."""
    bad = []
    for where, reason in _skip_reasons():
        if reason is None:
            bad.append(f"{where}: no reason (importorskip's own names the module, not how to get it)")
            continue
        text = " ".join(n.value for n in ast.walk(reason) if isinstance(n, ast.Constant) and isinstance(n.value, str))
        names = {n.id for n in ast.walk(reason) if isinstance(n, ast.Name)}
        if not (any(w in text for w in _HOW) or names & _SAYS_HOW):
            bad.append(f"{where}: {ast.unparse(reason)}")
    assert not bad, "\n".join(bad)


def test_mitsuba_skip_reason_says_how_to_install_it(monkeypatch):
    import importlib.util

    from mcrecon.renderers import mitsuba as mb

    monkeypatch.setattr(mb, "_PROBE_CACHE", {})
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None)
    ok, reason = mb.mitsuba_available()
    assert not ok and "not installed" in reason and "bash data_tools/install_mitsuba.sh" in reason

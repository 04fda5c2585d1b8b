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
from pathlib import Path

import numpy as np
import pytest

from mcrecon.cli import main

ROOT = Path(__file__).resolve().parents[1]


def run(args, capsys):
    try:
        code = main([str(a) for a in args])
    except SystemExit as exc:  # argparse's errors
        code = exc.code
    out = capsys.readouterr()
    return code, out.out, out.err


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
    code, out, err = run(["experiment", "convergence", "--scene", scene, "--html", "--size", "12x8", "--spp", "2",
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
    code, out, err = run(["experiment", "convergence", "--scene", "checker_wall", "--no-features", "--methods",
                          "box,nfor", "--size", "12x8", "--spp", "2"], capsys)
    assert code == 2 and out == "" and err.count("\n") == 1
    assert err.startswith("mcrecon: error: convergence: methods: nfor needs per-sample features")
    assert "--no-features" in err and "leave nfor out of --methods" in err and "mcrecon-convergence" not in err
    assert list(tmp.iterdir()) == [] and list(work.iterdir()) == []


def test_convergence_without_features_leaves_nfor_out_of_the_default_methods(scratch, capsys):
    code, out, err = run(["experiment", "convergence", "--scene", "flat", "--no-features", "--size", "8x8",
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

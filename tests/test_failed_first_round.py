"""A run refused or failed before its first committed round leaves no log behind, so the retry is not refused.

A log the run created itself is removed when the run raises before a round
is committed (a renderer that fails in round 0, a method that refuses the
first reply); a log with a committed round stays resumable, and a log the
user gave (``resume``, or an existing file the run refused) is never removed.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from mcrecon import InputError, RendererError
from mcrecon.adaptive.run import adapt, resume
from mcrecon.core.requests import SampleBatch
from mcrecon.io import read_log

from helpers import ROOT, jittered_renderer, run_cli, run_cli_process

W, H = 12, 8


def _renderer(*, features=True, fail_round=None, error=RendererError):
    """Noisy samples with albedo, normal and depth (``features``); raises ``error`` in ``fail_round``."""

    def shade(pos, rng, req):
        if req.round_index == fail_round:
            raise RendererError("test renderer", "render", "fails on purpose") if error is RendererError else error
        val = np.repeat(0.2 + 0.6 * (pos[:, :1] > W / 2), 3, axis=1) * rng.uniform(0.5, 1.5, (len(pos), 1))
        feats = {}
        if features:
            feats = {"albedo": np.repeat(0.5 + 0.1 * (pos[:, :1] > W / 2), 3, axis=1),
                     "normal": np.tile([0.0, 0.0, 1.0], (len(pos), 1)), "depth": 1.0 + 0 * pos[:, 0]}
        return SampleBatch(pos, val, feats)

    return jittered_renderer(shade, width=W, height=H, name="test renderer")


def _left_behind(log: Path) -> list[str]:
    return sorted(p.name for p in log.parent.iterdir() if p.name.startswith(log.name))


@pytest.mark.parametrize("pipeline", [False, True])
def test_a_method_refusing_the_first_reply_leaves_no_log_and_the_retry_runs(tmp_path, pipeline):
    log = tmp_path / "run.h5"
    with pytest.raises(InputError, match="nfor needs per-sample features"):
        adapt(_renderer(features=False), "nfor", spp=8, seed=1, log=log, pipeline=pipeline, progress=False)
    assert _left_behind(log) == []  # nor its lock file
    res = adapt(_renderer(), "nfor", spp=8, seed=1, log=log, pipeline=pipeline, progress=False)
    assert res.samples == read_log(log).n_samples == W * H * 8


@pytest.mark.parametrize("pipeline", [False, True])
def test_a_renderer_failing_in_round_0_leaves_no_log(tmp_path, pipeline):
    log = tmp_path / "run.h5"
    with pytest.raises(RendererError, match="fails on purpose"):
        adapt(_renderer(fail_round=0), "gem", spp=8, seed=1, log=log, pipeline=pipeline, progress=False)
    assert _left_behind(log) == []

    class Raw:  # a renderer of the protocol's own, raising what it raises
        width, height, channels = W, H, ("R", "G", "B")

        def render(self, req):
            raise ValueError("bad")

    with pytest.raises(ValueError, match="bad"):  # any error of the run, not only the toolkit's own
        adapt(Raw(), "box", spp=8, log=log, pipeline=pipeline, progress=False)
    assert _left_behind(log) == []
    # overwrite=True: the file the run would replace stays as it was
    log.write_bytes(b"an older file")
    with pytest.raises(RendererError):
        adapt(_renderer(fail_round=0), "box", spp=8, log=log, overwrite=True, progress=False)
    assert _left_behind(log) == ["run.h5"] and log.read_bytes() == b"an older file"


@pytest.mark.parametrize("pipeline", [False, True])
def test_a_failure_after_the_first_committed_round_keeps_the_log_resumable(tmp_path, pipeline):
    log = tmp_path / "run.h5"
    with pytest.raises(RendererError):
        adapt(_renderer(fail_round=2), "gem", spp=8, seed=1, log=log, pipeline=pipeline, progress=False)
    assert read_log(log).n_rounds >= 1
    res = resume(log, _renderer(), progress=False)
    full = adapt(_renderer(), "gem", spp=8, seed=1, pipeline=pipeline, progress=False)
    np.testing.assert_array_equal(res.image, full.image)


def test_a_log_given_to_resume_or_refused_is_never_removed(tmp_path):
    log = tmp_path / "run.h5"
    with pytest.warns(Warning, match="no samples"):
        adapt(_renderer(), "gem", spp=8, seed=1, log=log, max_rounds=0, progress=False)  # no round committed
    assert read_log(log).n_rounds == 0
    with pytest.raises(RendererError):
        resume(log, _renderer(fail_round=0), progress=False)
    assert read_log(log).run_settings["method"] == "gem"
    with pytest.raises(InputError, match="exists; resume it"):
        adapt(_renderer(fail_round=0), "gem", spp=8, seed=1, log=log, progress=False)
    assert read_log(log).run_settings["method"] == "gem"
    res = resume(log, _renderer(), progress=False)
    assert res.samples == W * H * 8


def test_an_interrupted_first_round_keeps_its_log_for_resume(tmp_path):
    """Ctrl-C is not a refusal: the run stops resumable, as at any later round."""
    log = tmp_path / "run.h5"
    with pytest.raises(KeyboardInterrupt):
        adapt(_renderer(fail_round=0, error=KeyboardInterrupt), "box", spp=8, seed=1, log=log, progress=False)
    assert read_log(log).n_rounds == 0
    assert resume(log, _renderer(), progress=False).samples == W * H * 8


# ------------------------------------------------------------------ through the command line
def _one_line(code, err, *matches):
    assert code == 2, err
    assert err.count("\n") == 1 and err.startswith("mcrecon: error: ") and "Traceback" not in err, err
    for m in matches:
        assert m in err, err


def test_cli_nfor_without_features_leaves_nothing_and_the_retry_with_features_runs(tmp_path, capsys, monkeypatch):
    """As a user types it: refused in a separate process (its exit status and its one line), nothing left;
    the corrected command, run here in the same folder, runs."""
    base = ["adapt", "--scene", "checker_wall", "--size", "16x12", "--spp", "8",
            "--method", "nfor", "--log", "run.h5", "-o", "out.exr", "--quiet"]
    bad = run_cli_process(base + ["--features", "none"], cwd=tmp_path, timeout=300)
    _one_line(bad.returncode, bad.stderr, "nfor needs per-sample features")
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    monkeypatch.chdir(tmp_path)
    code, _, err = run_cli(base, capsys)
    assert code == 0, err
    assert read_log(tmp_path / "run.h5").n_samples == 16 * 12 * 8 and (tmp_path / "out.exr").exists()


def test_cli_scene_without_its_features_then_with_them(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    base = ["adapt", "--scene", "soft_shadow", "--size", "16x12", "--spp", "8", "--method", "nfor",
            "--log", "run.h5", "-o", "out.exr", "--quiet"]
    _one_line(*run_cli(base, capsys)[::2], "nfor needs per-sample features")
    assert not (tmp_path / "run.h5").exists() and not (tmp_path / "out.exr").exists()
    code, _, err = run_cli(base + ["--features", "all"], capsys)
    assert code == 0, err


def test_cli_external_renderer_failing_in_round_0_then_corrected(tmp_path, capsys, monkeypatch):
    """The README's external-renderer command from another directory: its relative path fails in round 0;
    nothing is left, and the command with the right path runs at once."""
    monkeypatch.chdir(tmp_path)
    cmd = "{} data_tools/example_renderer.py {{request}} {{reply}}"
    base = ["adapt", "--size", "16x12", "--spp", "4", "--method", "box", "--log", "ext.h5", "-o", "out.exr",
            "--quiet"]
    code, _, err = run_cli(base + ["--renderer-cmd", cmd.format(sys.executable)], capsys)
    _one_line(code, err, "round 0")
    assert not (tmp_path / "ext.h5").exists() and not (tmp_path / "out.exr").exists()
    fixed = f"{sys.executable} {ROOT / 'data_tools' / 'example_renderer.py'} {{request}} {{reply}}"
    code, _, err = run_cli(base + ["--renderer-cmd", fixed], capsys)
    assert code == 0, err
    assert read_log(tmp_path / "ext.h5").n_samples == 16 * 12 * 4


@pytest.mark.skipif(not __import__("importlib").util.find_spec("mitsuba"), reason="needs Mitsuba 3: PYTHON=.venv/bin/python bash data_tools/install_mitsuba.sh")
def test_cli_mitsuba_without_features_leaves_no_log(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, _, err = run_cli(["adapt", "--mitsuba", "cornell-box", "--features", "none", "--size", "8x8", "--spp", "4",
                            "--method", "nfor", "--log", "m.h5", "-o", "out.exr", "--quiet"], capsys)
    _one_line(code, err, "nfor needs per-sample features")
    assert not (tmp_path / "m.h5").exists()


def test_cli_reference_of_another_size_names_the_file(tmp_path, capsys, monkeypatch):
    from mcrecon.io import write_exr

    monkeypatch.chdir(tmp_path)
    write_exr(tmp_path / "ref.exr", np.ones((8, 8, 3), np.float32))
    code, _, err = run_cli(["adapt", "--scene", "flat", "--size", "16x12", "--spp", "2", "--method", "box",
                            "--reference", "ref.exr", "--log", "l.h5", "-o", "out.exr"], capsys)
    _one_line(code, err, "ref.exr: shape: (8, 8, 3)", "(12, 16, 3)")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ref.exr"]


# ------------------------------------------------------------------ what reached the disk decides, and nothing is lost
def _shared_renderer(*, fail_round=None, error=None):
    """``helpers.jittered_renderer`` of a two-tone film; raises ``error`` (default: a RendererError) in ``fail_round``."""
    from helpers import jittered_renderer

    def shade(pos, rng, req):
        if req.round_index == fail_round:
            raise error if error is not None else RendererError("test renderer", "render", "fails on purpose")
        return np.repeat(0.2 + 0.6 * (pos[:, :1] > W / 2), 3, axis=1) * rng.uniform(0.5, 1.5, (len(pos), 1))

    return jittered_renderer(shade, width=W, height=H, name="test renderer")


def _files(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


@pytest.mark.parametrize("pipeline", [False, True])
def test_a_round_on_disk_is_kept_when_the_error_comes_after_its_append(tmp_path, pipeline):
    """The per-round error (``finish`` with a reference) raises after round 0 was appended: its samples stay."""
    from mcrecon.methods.box import BoxMethod

    class FinishFails(BoxMethod):
        def reconstruct_run(self, run, inputs):
            raise RuntimeError("finish fails on purpose")

    log = tmp_path / "run.h5"
    ref = np.full((H, W, 3), 0.5)
    with pytest.raises(RuntimeError, match="finish fails on purpose"):
        adapt(_shared_renderer(), FinishFails(), spp=8, seed=1, log=log, reference=ref, pipeline=pipeline,
              progress=False)
    assert read_log(log).n_rounds >= 1
    res = resume(log, _shared_renderer(), progress=False)
    assert res.samples == W * H * 8


@pytest.mark.parametrize("pipeline", [False, True])
def test_overwrite_keeps_the_old_log_bit_identical_until_the_new_run_commits_a_round(tmp_path, pipeline):
    log = tmp_path / "run.h5"
    adapt(_shared_renderer(), "gem", spp=4, seed=3, log=log, progress=False)
    old = log.read_bytes()
    for error, raised in ((None, RendererError), (ValueError("bad"), RendererError),
                          (KeyboardInterrupt(), KeyboardInterrupt)):  # the renderer's refusal, any error, Ctrl-C
        with pytest.raises(raised):
            adapt(_shared_renderer(fail_round=0, error=error), "box", spp=8, log=log, overwrite=True,
                  pipeline=pipeline, progress=False)
        assert log.read_bytes() == old
        assert _files(tmp_path) == ["run.h5"]  # no temporary log, no lock
    # a failure after round 0: the new run's log has replaced the old one and resumes
    with pytest.raises(RendererError):
        adapt(_shared_renderer(fail_round=2), "box", spp=8, seed=1, log=log, overwrite=True, pipeline=pipeline,
              progress=False)
    assert _files(tmp_path) == ["run.h5"]
    sl = read_log(log)
    assert sl.run_settings["method"] == "box" and sl.n_rounds == 2
    assert resume(log, _shared_renderer(), progress=False).samples == W * H * 8
    # a run that succeeds replaces it, and its result names the log
    res = adapt(_shared_renderer(), "box", spp=4, seed=2, log=log, overwrite=True, pipeline=pipeline,
                progress=False)
    assert res.log == log and _files(tmp_path) == ["run.h5"]
    assert read_log(log).n_samples == res.samples == W * H * 4 and read_log(log).run_settings["seed"] == 2


def test_a_refused_first_round_removes_the_directories_it_created(tmp_path):
    (tmp_path / "kept").mkdir()
    for log in (tmp_path / "nd" / "sub" / "run.h5", tmp_path / "kept" / "new" / "run.h5"):
        with pytest.raises(RendererError):
            adapt(_shared_renderer(fail_round=0), "box", spp=4, log=log, progress=False)
    assert _files(tmp_path) == ["kept"]  # a directory that was there before stays


def test_ctrl_c_says_what_the_log_on_disk_lets_the_user_do(tmp_path, cli, monkeypatch):
    from mcrecon.cli import commands

    monkeypatch.chdir(tmp_path)

    def interrupted_after(rounds):
        def cmd(args):
            adapt(_shared_renderer(), "box", spp=4, log=args.log, max_rounds=rounds, progress=False)
            raise KeyboardInterrupt

        return cmd

    argv = ["adapt", "--scene", "flat", "--size", "8x8", "--spp", "4", "-o", "o.exr", "--log"]
    monkeypatch.setattr(commands, "_cmd_adapt", interrupted_after(1))
    code, _, err = cli(argv + ["one.h5"])
    assert code == 130 and err == "mcrecon: interrupted; `mcrecon adapt --resume one.h5 -o o.exr` continues the " \
                                  "run from its last committed round\n"
    monkeypatch.setattr(commands, "_cmd_adapt", interrupted_after(0))
    code, _, err = cli(argv + ["none.h5"])
    assert code == 130 and err.splitlines(keepends=True)[-1] == "mcrecon: interrupted before any round was committed; `mcrecon adapt --resume " \
                                  "none.h5 -o o.exr` starts the run from its first round\n"


def test_mcrecon_adapt_is_the_driver_itself_refusing_a_plain_function_before_anything(tmp_path):
    import inspect

    import mcrecon
    from mcrecon.adaptive import run as driver

    assert mcrecon.adapt is driver.adapt
    assert {"seed", "log", "overwrite", "pipeline", "on_round"} <= set(inspect.signature(mcrecon.adapt).parameters)

    def shade(request):
        return None

    with pytest.raises(InputError, match=r"shade is a plain function.*mcrecon.CallableRenderer\(fn, width=W, "
                                         r"height=H\)"):
        driver.adapt(shade, "gem", spp=4, log=tmp_path / "run.h5")
    assert _files(tmp_path) == []

"""The adapt command around the run: a resume from another directory, the run summary's times, and the
progress of --renderer-cmd runs."""

from __future__ import annotations

from pathlib import Path

import pytest

from mcrecon.cli import main

from helpers import run_cli

ROOT = Path(__file__).parents[1]


# ----------------------------------------------------------------- resume from another directory
def test_resume_of_a_relative_renderer_command_from_another_directory(tmp_path, capsys, monkeypatch):
    import sys

    from mcrecon.io import read_log
    from mcrecon.io.writer import set_run_settings

    log = tmp_path / "run.h5"
    monkeypatch.chdir(ROOT)          # as the README has it: a path relative to the clone
    cmd = f"{sys.executable} data_tools/example_renderer.py {{request}} {{reply}}"
    assert main(["adapt", "--renderer-cmd", cmd, "--size", "8x8", "--spp", "8", "--method", "box",
                 "--log", str(log), "--time-limit", "1e-9", "-o", str(tmp_path / "a.exr"), "--quiet"]) == 0
    assert "stopped: time_limit" in capsys.readouterr().out
    spec = read_log(log).run_settings["renderer_spec"]
    assert spec["argv"][1] == "data_tools/example_renderer.py" and spec["cwd"] == str(ROOT)

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert main(["adapt", "--resume", str(log), "--time-limit", "600", "-o", str(tmp_path / "b.exr"),
                 "--quiet"]) == 0
    assert "stopped: budget" in capsys.readouterr().out
    assert read_log(log).n_samples == 8 * 8 * 8

    settings = read_log(log).run_settings            # a recorded directory that is gone: one line
    settings["renderer_spec"]["cwd"] = str(tmp_path / "gone")
    set_run_settings(log, settings)
    code, _, err = run_cli(["adapt", "--resume", log, "-o", tmp_path / "c.exr", "--quiet"], capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert "renderer_spec.cwd" in err and "gone" in err and "not a directory" in err


# ----------------------------------------------------------------- the run summary's times
_TIMES = r"time (?P<t>[\d.]+) s \(renderer (?P<r>[\d.]+) s, (?:toolkit (?P<k>[\d.]+) s|waiting for the " \
         r"toolkit (?P<w>[\d.]+) s; toolkit (?P<kp>[\d.]+) s, overlapping the renderer), final image " \
         r"(?P<f>[\d.]+) s(?:, error after each round (?P<e>[\d.]+) s)?\)"
_ROUNDING = 0.005   # each printed figure is rounded to 2 decimals


def _times(out: str) -> dict:
    import re

    m = re.search(_TIMES, out)
    assert m, out
    return {k: float(v) for k, v in m.groupdict().items() if v is not None}


@pytest.mark.parametrize("pipe", ["--no-pipeline", "--pipeline"])
def test_run_summary_parts_never_exceed_the_whole(tmp_path, capsys, pipe):
    assert main(["adapt", "--scene", "soft_shadow", "--size", "16x16", "--spp", "32", "--method", "box", pipe,
                 "-o", str(tmp_path / "a.exr"), "--quiet"]) == 0
    t = _times(capsys.readouterr().out)
    if pipe == "--pipeline":   # the renderer's time and its waits are the loop; the toolkit overlaps them
        assert t["r"] + t["w"] + t["f"] <= t["t"] + 4 * _ROUNDING and t["kp"] <= t["t"] + 2 * _ROUNDING
    else:
        assert "k" in t and t["r"] + t["k"] + t["f"] <= t["t"] + 4 * _ROUNDING


def test_resumed_run_summary_gives_this_sessions_times(tmp_path, capsys):
    from mcrecon.adaptive.run import adapt
    from mcrecon.io import read_log
    from mcrecon.io.writer import update_round_record
    from mcrecon.renderers import renderer_from_spec, scene_spec

    log = tmp_path / "r.h5"
    spec = scene_spec("soft_shadow", width=16, height=16)
    adapt(renderer_from_spec(spec), "box", spp=32, log=log, renderer_spec=spec, max_rounds=2, progress=False,
          pipeline=False)
    # the earlier session rendered for 100 s (a slow renderer): its rounds are not this session's time
    last = read_log(log).round_records[-1]
    update_round_record(log, {**last, "renderer_seconds": 100.0})
    assert main(["adapt", "--resume", str(log), "-o", str(tmp_path / "b.exr"), "--quiet"]) == 0
    out = capsys.readouterr().out
    t = _times(out)
    assert t["r"] + t["k"] + t["f"] <= t["t"] + 4 * _ROUNDING
    assert "before this resume: 2 round(s), renderer 10" in out   # named apart: 100 s and the round before


# ----------------------------------------------------------------- progress of --renderer-cmd runs
def test_renderer_cmd_run_shows_per_round_progress_when_asked(tmp_path, capsys):
    import sys

    example = ROOT / "data_tools" / "example_renderer.py"
    cmd = f"{sys.executable} {example} {{request}} {{reply}}"
    # awr renders its 16 spp in one round: the progress must say so while it renders, not only after
    argv = ["adapt", "--renderer-cmd", cmd, "--size", "8x8", "--spp", "16", "--method", "awr",
            "-o", str(tmp_path / "a.exr")]
    assert main(argv + ["--progress"]) == 0
    err = capsys.readouterr().err.splitlines()
    starts = [i for i, line in enumerate(err) if "round 0: rendering 1024 samples" in line]
    ends = [i for i, line in enumerate(err) if "round 0  1024 samples" in line]
    assert starts and ends and starts[0] < ends[0], err
    assert all("\r" not in line for line in err)          # not a terminal: plain lines
    for quiet in ("--no-progress", "--quiet"):
        assert main(argv + [quiet]) == 0
        assert "round 0" not in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(argv + ["--progress", "--quiet"])


def test_progress_is_on_by_default_on_a_terminal(tmp_path, monkeypatch):
    import io
    import sys

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    term = Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    cmd = f"{sys.executable} {ROOT / 'data_tools' / 'example_renderer.py'} {{request}} {{reply}}"
    assert main(["adapt", "--renderer-cmd", cmd, "--size", "8x8", "--spp", "16", "--method", "awr",
                 "-o", str(tmp_path / "a.exr")]) == 0
    text = term.getvalue()
    assert "round 0: rendering 1024 samples" in text and "\r[" in text   # said while round 0 renders

"""Issue 27: batch (workers, literal names, damaged outputs), render-log --reference-exr,
resuming from another directory, the run summary's times, progress on --renderer-cmd runs."""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path

import numpy as np
import pytest

from mcrecon.cli import main
from mcrecon.errors import InputError
from mcrecon.io import read_exr, write_exr
from mcrecon.renderers.scenes import get_scene, write_scene_log


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


# ----------------------------------------------------------------- 1. batch
@pytest.fixture(scope="module")
def client():
    pytest.importorskip("distributed", reason="needs the dask extra: pip install 'mcrecon[dask]'")
    from mcrecon import distributed as D
    from mcrecon.distributed import batch as D_batch
    from mcrecon.distributed import cluster as D_cluster

    with D_cluster.local_client(1, threads=1) as c:
        yield c


@pytest.fixture(scope="module")
def shots(tmp_path_factory):
    d = tmp_path_factory.mktemp("shots")
    write_scene_log(get_scene("soft_shadow"), d / "shot[1].h5", width=12, height=8, spp=4, seed=1)
    write_scene_log(get_scene("caustic"), d / "shot1.h5", width=16, height=8, spp=4, seed=2)
    write_scene_log(get_scene("soft_shadow"), d / "take[2].h5", width=12, height=8, spp=4, seed=3)
    return d


def test_batch_workers_capped_at_frames_and_cores(shots, tmp_path, capsys, monkeypatch):
    pytest.importorskip("distributed", reason="needs the dask extra: pip install 'mcrecon[dask]'")
    from mcrecon import distributed as D
    from mcrecon.distributed import batch as D_batch
    from mcrecon.distributed import cluster as D_cluster

    asked = []

    @contextlib.contextmanager
    def no_cluster(workers=None, **kw):
        asked.append(workers)
        raise InputError("test", "cluster", "not started")
        yield  # pragma: no cover

    monkeypatch.setattr(D_cluster, "local_client", no_cluster)
    assert main(["batch", str(shots / "shot1.h5"), "--out-dir", str(tmp_path), "--workers", "1000000",
                 "--quiet"]) == 2
    assert asked == [1]                                  # one frame: one worker, not a million
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "warning" in err[0] and "1000000 workers capped at 1" in err[0]
    assert "not started" in err[1]
    for bad in ("0", "-3", "two"):                       # refused by the flag, before any work
        with pytest.raises(SystemExit) as exc:
            main(["batch", str(shots / "shot1.h5"), "--out-dir", str(tmp_path), "--workers", bad])
        assert exc.value.code == 2
        assert "--workers" in _one_line_error(capsys)
    assert len(asked) == 1


def test_batch_existing_name_is_literal_not_a_pattern(shots):
    pytest.importorskip("distributed", reason="needs the dask extra: pip install 'mcrecon[dask]'")
    from mcrecon import distributed as D
    from mcrecon.distributed import batch as D_batch
    from mcrecon.distributed import cluster as D_cluster

    assert D_batch._expand([str(shots / "shot[1].h5")]) == [shots / "shot[1].h5"]   # not shot1.h5
    assert D_batch._expand([str(shots / "take[2].h5")]) == [shots / "take[2].h5"]   # exists: no "matches no file"
    assert D_batch._expand([str(shots / "shot?.h5")]) == [shots / "shot1.h5"]       # a pattern still globs
    with pytest.raises(InputError, match="matches no file"):
        D_batch._expand([str(shots / "take[3].h5")])


def test_batch_literal_name_and_damaged_output_redone(client, shots, tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["batch", str(shots / "shot[1].h5"), "--out-dir", str(out), "--scheduler", client.scheduler.address,
            "--quiet"]
    assert main(argv) == 0
    exr = out / "shot[1].exr"
    assert read_exr(exr)[0].shape == (8, 12, 3)          # shot[1].h5 (12x8), not shot1.h5 (16x8)
    doc = json.loads((out / "batch_summary.json").read_text())
    assert [f["log"] for f in doc["frames"]] == [str(shots / "shot[1].h5")]
    capsys.readouterr()
    good = exr.read_bytes()
    assert main(argv) == 0
    assert "1 up to date" in capsys.readouterr().out     # intact: skipped

    exr.write_bytes(good[:40])                           # truncated, still newer than the log
    assert main(argv) == 0
    cap = capsys.readouterr()
    assert "1 reconstructed" in cap.out
    assert "damaged" in cap.err and "not a readable EXR" in cap.err and str(exr) in cap.err
    assert exr.read_bytes() == good

    exr.write_bytes(good[:len(good) // 2])               # cut after its header: the pixels are missing
    assert main(argv) == 0
    cap = capsys.readouterr()
    assert "1 reconstructed" in cap.out and "not a readable EXR" in cap.err
    assert exr.read_bytes() == good

    write_exr(exr, np.zeros((4, 4, 3)))                  # readable, but not this log's size
    assert main(argv) == 0
    cap = capsys.readouterr()
    assert "1 reconstructed" in cap.out and "4x4" in cap.err
    assert exr.read_bytes() == good


# ----------------------------------------------------------------- 2. render-log --reference-exr
def test_render_log_writes_the_stored_reference_as_exr(tmp_path, capsys):
    from mcrecon.io import read_log

    log, ref = tmp_path / "c.h5", tmp_path / "ref.exr"
    assert main(["render-log", "--scene", "caustic", "--spp", "2", "--size", "12x8", "-o", str(log),
                 "--reference-exr", str(ref)]) == 0
    assert f"wrote {ref}" in capsys.readouterr().out
    img, channels = read_exr(ref)
    stored = read_log(log)
    assert channels == stored.channels
    assert np.array_equal(img, stored.reference().astype(np.float32))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.h5", "ref.exr", "ref.png"]   # no temporary left

    other = tmp_path / "d.h5"
    for bad, text in ((str(other), "is the -o sample log"), (str(tmp_path / "r.png"), ".exr")):
        assert main(["render-log", "--scene", "caustic", "--spp", "2", "--size", "12x8", "-o", str(other),
                     "--reference-exr", bad]) == 2
        assert text in _one_line_error(capsys)
    assert not other.exists()                            # refused before any work


# ----------------------------------------------------------------- 3. resume from another directory
ROOT = Path(__file__).parents[1]


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
    assert main(["adapt", "--resume", str(log), "-o", str(tmp_path / "c.exr"), "--quiet"]) == 2
    err = _one_line_error(capsys)
    assert "renderer_spec.cwd" in err and "gone" in err and "not a directory" in err


# ----------------------------------------------------------------- 4. the run summary's times
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


# ----------------------------------------------------------------- 5. progress of --renderer-cmd runs
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

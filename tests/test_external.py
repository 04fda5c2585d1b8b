"""Out-of-process renderer protocol: faults, time-outs, SIGKILL and resume."""

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mcrecon import InputError, RendererError
from mcrecon.driver import adapt, resume
from mcrecon.io import read_exr, read_log
from mcrecon.renderers.command import CommandRenderer, read_request, write_request
from mcrecon.renderers.protocol import SampleRequest

FAULT = str(Path(__file__).parent / "renderers" / "fault_renderer.py")
FEATURES = str(Path(__file__).parent / "renderers" / "feature_renderer.py")
EXAMPLE = str(Path(__file__).parents[1] / "data_tools" / "example_renderer.py")


def _cmd(mode="ok", fault_round=-1, timeout=30.0, w=12, h=8):
    return CommandRenderer([sys.executable, FAULT, mode, str(fault_round), "{request}", "{reply}"],
                           width=w, height=h, timeout=timeout)


def test_request_file_round_trip(tmp_path):
    req = SampleRequest(5, 3, counts=np.arange(15).reshape(3, 5), positions=np.array([[0.25, 2.5]]),
                        round_index=4, seed=2**63 + 5)
    write_request(tmp_path / "r.h5", req, channels=("R", "G", "B"))
    back = read_request(tmp_path / "r.h5")
    assert (back.round_index, back.seed, back.total) == (4, 2**63 + 5, req.total)
    np.testing.assert_array_equal(back.counts, req.counts)
    np.testing.assert_array_equal(back.positions, req.positions)


def test_example_renderer_runs_a_whole_adaptive_run(tmp_path):
    r = CommandRenderer([sys.executable, EXAMPLE, "{request}", "{reply}"], width=16, height=16)
    res = adapt(r, "box", spp=4, seed=1, log=tmp_path / "run.h5")
    assert res.stats.n_samples == 16 * 16 * 4 and np.isfinite(res.image).all()
    assert all(rec["renderer_seconds"] > 0 for rec in res.rounds)


def test_reply_features_reach_the_log_of_an_adaptive_run(tmp_path):
    r = CommandRenderer([sys.executable, FEATURES, "ok", "{request}", "{reply}"], width=12, height=8)
    log = tmp_path / "run.h5"
    res = adapt(r, "box", spp=8, seed=3, log=log)
    got = read_log(log)
    assert got.n_samples == res.stats.n_samples == 12 * 8 * 8 and got.n_rounds > 1
    assert got.feature_names == ("depth", "normal")
    pos = np.asarray(got.read_all().positions, np.float64)
    depth, normal = got.read_feature("depth"), got.read_feature("normal")
    assert depth.dtype == np.float32 and depth.shape == (got.n_samples,)
    assert normal.dtype == np.float64 and normal.shape == (got.n_samples, 3)
    # every row belongs to its own sample, across all rounds
    np.testing.assert_allclose(depth, pos[:, 0] + 1000 * pos[:, 1], rtol=1e-6)
    np.testing.assert_allclose(normal[:, 1:], pos, rtol=1e-6)


@pytest.mark.parametrize("mode, match", [
    ("short", r"shape \(95,\), expected \(96, \.\.\.\)"),
    ("long", r"shape \(97,\), expected \(96, \.\.\.\)"),
    ("text", "dtype object, expected a numeric dtype"),
])
def test_bad_reply_features_name_the_reply_file_and_dataset(tmp_path, mode, match):
    r = CommandRenderer([sys.executable, FEATURES, mode, "{request}", "{reply}"], width=12, height=8,
                        workdir=tmp_path / "exchange")
    with pytest.raises(RendererError) as exc:
        adapt(r, "box", spp=8, seed=3, log=tmp_path / "run.h5")
    msg = str(exc.value)
    assert "\n" not in msg
    assert f"reply {tmp_path / 'exchange' / 'round-00000.reply.h5'} dataset /features/depth" in msg
    assert re.search(match, msg), msg


@pytest.mark.parametrize("mode, match", [
    ("exit", "exit status: 3 .*out of memory"),
    ("short", "reply length"),
    ("channels", "reply channels"),
    ("offpixel", "inside the requested pixels"),
    ("noreply", "was not written"),
    ("garbage", "malformed"),
])
def test_faulty_renderer_gives_clear_error_and_resumable_log(tmp_path, mode, match):
    log = tmp_path / "run.h5"
    with pytest.raises(RendererError, match=match):
        adapt(_cmd(mode, fault_round=1), "box", spp=4, seed=2, log=log)
    assert read_log(log).n_rounds == 1
    res = resume(log, _cmd())
    assert res.stats.n_samples == 12 * 8 * 4


def test_hanging_renderer_times_out(tmp_path):
    log = tmp_path / "run.h5"
    t0 = time.perf_counter()
    with pytest.raises(RendererError, match="time-out.*longer than 1.5 s"):
        adapt(_cmd("hang", fault_round=1, timeout=1.5), "box", spp=4, log=log)
    assert time.perf_counter() - t0 < 30
    assert read_log(log).n_rounds == 1


def test_nan_reply_under_each_policy(tmp_path):
    with pytest.raises(RendererError, match="NaN or Inf"):
        adapt(_cmd("nan", fault_round=0), "box", spp=2, nonfinite="raise", log=tmp_path / "a.h5")
    with pytest.warns(Warning, match="2 sample"):
        res = adapt(_cmd("nan", fault_round=0), "box", spp=2, nonfinite="drop")
    assert res.stats.n_dropped == 2 and np.isfinite(res.image).all()


def test_command_validation():
    with pytest.raises(InputError, match="placeholders"):
        CommandRenderer(["renderer", "in.h5"], width=2, height=2)
    with pytest.raises(RendererError, match="not found"):
        adapt(CommandRenderer(["/no/such/renderer", "{request}", "{reply}"], width=2, height=2), "box", spp=1)


def _run_cli(args, **kw):
    return subprocess.run([sys.executable, "-m", "mcrecon", *args], capture_output=True, text=True, **kw)


def _wait_for_round(marker: Path, k: int, proc, timeout: float = 120.0) -> list[int]:
    """Wait until the fault renderer reports a call for round >= k; return the renderer PIDs seen.

    A safety deadline only: the marker is written by the renderer process itself,
    so this waits on an event, not on the state of a file another process is writing.
    """
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if marker.exists():
            lines = [ln.split() for ln in marker.read_text().splitlines(keepends=True) if ln.endswith("\n")]
            if any(int(r) >= k for r, _ in lines):
                return [int(pid) for _, pid in lines]
        if proc.poll() is not None:
            pytest.fail(f"the run ended (status {proc.returncode}) before round {k}: {proc.stderr.read()!r}")
        time.sleep(0.02)
    pytest.fail(f"the renderer was not asked for round {k} within {timeout} s")


def _kill(pid: int) -> None:
    try:
        os.kill(pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def test_sigkill_mid_run_then_resume_matches_uninterrupted(tmp_path):
    cmd = f"{sys.executable} {FAULT} slow -1 {{request}} {{reply}}"
    common = ["adapt", "--renderer-cmd", cmd, "--size", "12x8", "--spp", "32", "--method", "box", "--seed", "9",
              "--quiet"]
    log = tmp_path / "killed.h5"
    marker = tmp_path / "rounds.txt"
    # The renderer reports every call and holds round 3 until killed: the driver commits
    # round k before it requests round k + 1, so rounds 0-2 are in the log by then and the
    # driver is blocked in the renderer call (6 rounds in all for this run).
    env = {**os.environ, "FAULT_RENDERER_MARKER": str(marker), "FAULT_RENDERER_HOLD": "3"}
    proc = subprocess.Popen([sys.executable, "-m", "mcrecon", *common, "--log", str(log), "-o",
                             str(tmp_path / "killed.exr")], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            env=env)
    pids = []
    try:
        pids = _wait_for_round(marker, 3, proc)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        proc.stderr.close()
        for pid in pids:  # the held renderer (the others have exited)
            _kill(pid)
    killed = read_log(log)  # only now: the writer is dead
    assert killed.n_rounds == 3 and len(killed.round_records) == 3
    assert 0 < killed.n_samples < 12 * 8 * 32
    out = _run_cli(["adapt", "--resume", str(log), "-o", str(tmp_path / "resumed.exr"), "--quiet"])
    assert out.returncode == 0, out.stderr
    ref = _run_cli([*common, "--log", str(tmp_path / "full.h5"), "-o", str(tmp_path / "full.exr")])
    assert ref.returncode == 0, ref.stderr
    assert read_log(log).n_samples == read_log(tmp_path / "full.h5").n_samples == 12 * 8 * 32
    a, _ = read_exr(tmp_path / "resumed.exr")
    b, _ = read_exr(tmp_path / "full.exr")
    np.testing.assert_array_equal(a, b)

"""A sequential run writes its log behind (issue 25): round j goes to disk while round j+1 is planned and
rendered.  The plans, the image and the log are those of a run that wrote in line; nothing handed over is
lost when the run stops, fails or is killed.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
import types
from pathlib import Path

import numpy as np
import pytest

import mcrecon.adaptive.rounds as rounds_mod
from mcrecon import InputError, RendererError, get_method
from mcrecon.adaptive.run import adapt, resume
from mcrecon.core.requests import SampleBatch
from mcrecon.io import read_log
from mcrecon.renderers import CallableRenderer

from helpers import request_positions

FAULT = str(Path(__file__).parent / "renderers" / "fault_renderer.py")
W, H = 16, 12


def _fn(req, bad_round=None):
    if req.round_index == bad_round:
        raise RuntimeError("the renderer's own failure")
    rng = np.random.default_rng(req.seed)
    pos = request_positions(req, rng)
    return SampleBatch(pos, rng.random((len(pos), 3)) * (1 + (pos[:, :1] > W / 2)))


def _gem():
    return get_method("gem", initial_spp=4, iterations=5)


def test_written_behind_on_the_writer_thread_and_identical_to_no_log(tmp_path):
    log = tmp_path / "run.h5"
    res = adapt(CallableRenderer(_fn, width=W, height=H), _gem(), spp=12, seed=3, log=log, track_error=False,
                progress=False)
    plain = adapt(CallableRenderer(_fn, width=W, height=H), _gem(), spp=12, seed=3, track_error=False,
                  progress=False)
    np.testing.assert_array_equal(res.image, plain.image)
    sl = read_log(log)
    assert sl.n_rounds == len(res.rounds) == len(plain.rounds) > 3
    assert sl.round_records == res.rounds
    appends = [e for e in res.timeline if e["phase"] == "append"]
    assert len(appends) == sl.n_rounds and all(e["thread"] == "toolkit" for e in appends)
    assert sl.n_samples == res.samples == plain.samples


def test_a_failed_write_stops_the_run_with_the_rounds_before_committed(tmp_path, monkeypatch):
    """The append of round 2 fails on the writer thread: the run raises that error (not later than the
    next round's hand-over), the log holds rounds 0-1, and the resume ends as a run never stopped."""
    real = rounds_mod.append_log

    def failing(path, *a, round_index, **kw):
        if round_index == 2:
            raise InputError(str(path), "log", "no space left on device (a test's fault)")
        return real(path, *a, round_index=round_index, **kw)

    monkeypatch.setattr(rounds_mod, "append_log", failing)
    log = tmp_path / "run.h5"
    with pytest.raises(InputError, match="no space left"):
        adapt(CallableRenderer(_fn, width=W, height=H), _gem(), spp=12, seed=4, log=log, track_error=False,
              progress=False)
    monkeypatch.setattr(rounds_mod, "append_log", real)
    sl = read_log(log)
    assert sl.n_rounds == 2 and len(sl.round_records) == 2
    res = resume(log, CallableRenderer(_fn, width=W, height=H), track_error=False, progress=False)
    full = adapt(CallableRenderer(_fn, width=W, height=H), _gem(), spp=12, seed=4, track_error=False,
                 progress=False)
    np.testing.assert_array_equal(res.image, full.image)


def test_a_renderer_error_waits_for_the_round_being_written(tmp_path):
    log = tmp_path / "run.h5"
    with pytest.raises(RendererError, match="own failure"):
        adapt(CallableRenderer(lambda r: _fn(r, bad_round=3), width=W, height=H), _gem(), spp=12, seed=5,
              log=log, track_error=False, progress=False)
    sl = read_log(log)
    assert sl.n_rounds == 3 and len(sl.round_records) == 3  # round 2, written behind, is on disk


DRIVER = textwrap.dedent("""
    import sys
    from mcrecon.adaptive import adapt
    from mcrecon.methods.gem import GEMMethod
    from mcrecon.renderers.command import CommandRenderer

    log, w, h, FAULT = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
    r = CommandRenderer([sys.executable, FAULT, "ok", "-1", "{request}", "{reply}"], width=w, height=h)
    adapt(r, GEMMethod(initial_spp=4, iterations=6), spp=16, seed=7, log=log, progress=False, track_error=False)
""")


def test_sigkill_while_written_behind_then_resume_matches_uninterrupted(tmp_path):
    """Killed while the renderer holds round 3: round 2 was handed to the writer (on disk or not, as the
    kill found it); the resume plans and renders what is missing and ends bit-identical."""
    hold, w, h = 3, 12, 8
    script = tmp_path / "driver.py"
    script.write_text(DRIVER)
    log, marker = tmp_path / "killed.h5", tmp_path / "rounds.txt"
    env = {**os.environ, "FAULT_RENDERER_MARKER": str(marker), "FAULT_RENDERER_HOLD": str(hold)}
    proc = subprocess.Popen([sys.executable, str(script), str(log), str(w), str(h), FAULT],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    pids = []
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not pids:
            if marker.exists():
                lines = [ln.split() for ln in marker.read_text().splitlines(keepends=True) if ln.endswith("\n")]
                pids = [int(p) for r, p in lines if int(r) >= hold]
            if proc.poll() is not None:
                pytest.fail(f"the run ended (status {proc.returncode}): {proc.stderr.read()!r}")
            time.sleep(0.02)
        assert pids, f"round {hold} was not requested"
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        proc.stderr.close()
        for pid in pids:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
    killed = read_log(log)
    assert killed.n_rounds in (hold - 1, hold) and len(killed.round_records) == killed.n_rounds

    def renderer():
        from mcrecon.renderers.command import CommandRenderer

        return CommandRenderer([sys.executable, FAULT, "ok", "-1", "{request}", "{reply}"], width=w, height=h)

    res = resume(log, renderer(), track_error=False, progress=False)
    full = adapt(renderer(), get_method("gem", initial_spp=4, iterations=6), spp=16, seed=7,
                 log=tmp_path / "full.h5", track_error=False, progress=False)
    np.testing.assert_array_equal(res.image, full.image)
    np.testing.assert_array_equal(read_log(log).read_all().positions, read_log(tmp_path / "full.h5").read_all().positions)


def test_a_renderer_that_refills_its_buffers_still_gets_its_own_rounds_in_the_log(tmp_path, monkeypatch):
    """A callable that fills one values array again every round (allowed: it is not ``fresh_replies``):
    the writer gets a copy, so the log holds each round's own values even when the write lags behind the
    next render (the append is slowed here so that it always does)."""
    real = rounds_mod.append_log

    def slow(*a, **kw):
        time.sleep(0.15)  # the next round renders into the same buffer meanwhile
        return real(*a, **kw)

    buf = {}

    def refilling(req):
        b = _fn(req)
        out = buf.setdefault("v", np.empty((0, 3)))
        if out.shape != b.values.shape:
            out = buf["v"] = np.empty(b.values.shape)
        out[...] = b.values
        return SampleBatch(b.positions, out)

    monkeypatch.setattr(rounds_mod, "append_log", slow)
    res = adapt(CallableRenderer(refilling, width=W, height=H), _gem(), spp=12, seed=6, log=tmp_path / "r.h5",
                track_error=False, progress=False)
    fresh = adapt(CallableRenderer(_fn, width=W, height=H), _gem(), spp=12, seed=6, log=tmp_path / "f.h5",
                  track_error=False, progress=False)
    np.testing.assert_array_equal(res.image, fresh.image)
    np.testing.assert_array_equal(read_log(tmp_path / "r.h5").read_all().values,
                                  read_log(tmp_path / "f.h5").read_all().values)


class _InterruptedOnce:
    """A future whose first ``result()`` is interrupted by Ctrl-C (the write itself goes on)."""

    def __init__(self):
        self.calls = 0

    def done(self):
        return True

    def result(self):
        self.calls += 1
        if self.calls == 1:
            raise KeyboardInterrupt
        return None


def test_ctrl_c_while_waiting_for_a_write_waits_it_out_then_stops():
    """Ctrl-C during the wait does not abandon the write (the run holds the log's lock until it is done):
    the round is finished (on_round sees it), then the interrupt is raised."""
    fut, seen = _InterruptedOnce(), []

    class Bar:
        def update(self, *a):
            pass

    from mcrecon.adaptive.context import RunClock

    stats = type("S", (), {"n_samples": 0, "n_dropped": 0})()
    ctx = types.SimpleNamespace(log_path=None, rounds=[], on_round=seen.append, bar=Bar(), stats=stats,
                                clock=RunClock())
    writes = rounds_mod._LogWrites(ctx)
    writes.behind.append((fut, {"round": 4, "wall_seconds": 0.0}))
    with pytest.raises(KeyboardInterrupt):
        writes.written(wait=True)
    assert fut.calls == 2 and [r["round"] for r in seen] == [4] and not writes.behind
    fut2 = _InterruptedOnce()
    with pytest.raises(KeyboardInterrupt):
        rounds_mod._wait_out(fut2)
    assert fut2.calls == 2

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
from mcrecon.adaptive.run import adapt, resume
from mcrecon.io import read_exr, read_log
from mcrecon.renderers.command import CommandRenderer, read_request, write_request
from mcrecon.core.requests import SampleRequest

from helpers import MCRECON, cli_env, request_positions, run_cli_process

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
    ("matrix", r"shape \(96, 2, 2\), expected \(96,\) or \(96, k\)"),
])
def test_bad_reply_features_name_the_reply_file_and_dataset(tmp_path, mode, match):
    # (a bool feature is a mask: taken as 0/1, as everywhere features enter; not a bad reply)
    r = CommandRenderer([sys.executable, FEATURES, mode, "{request}", "{reply}"], width=12, height=8,
                        workdir=tmp_path / "exchange")
    with pytest.raises(RendererError) as exc:
        adapt(r, "box", spp=8, seed=3, log=tmp_path / "run.h5")
    msg = str(exc.value)
    assert "\n" not in msg
    assert f"reply {tmp_path / 'exchange' / 'round-00000.reply.h5'} dataset /features/depth" in msg
    assert re.search(match, msg), msg


@pytest.mark.parametrize("mode, match", [
    ("rename", r"round 1 sends dist \(\d+,\), normal \(\d+, 3\); the first reply sent depth \(96,\), "
               r"normal \(96, 3\): every round must send the same features"),
    ("widen", r"round 1 sends depth \(\d+,\), normal \(\d+, 4\); the first reply sent depth \(96,\), "
              r"normal \(96, 3\)"),
])
def test_reply_features_must_stay_the_same_every_round(tmp_path, mode, match):
    r = CommandRenderer([sys.executable, FEATURES, mode, "{request}", "{reply}"], width=12, height=8)
    with pytest.raises(RendererError, match=match) as exc:
        adapt(r, "box", spp=8, seed=3, log=tmp_path / "run.h5")
    assert "/features" in str(exc.value)
    # round 0 was committed before the bad round: the run is resumable
    assert read_log(tmp_path / "run.h5").n_rounds >= 1


def test_nonfinite_reply_features_are_zeroed_and_warned(tmp_path):
    from mcrecon.errors import McreconWarning

    r = CommandRenderer([sys.executable, FEATURES, "nan", "{request}", "{reply}"], width=12, height=8)
    with pytest.warns(McreconWarning, match=r"round 0 \(later rounds are not warned again\): features: 2 "
                                            r"sample\(s\) with NaN, Inf or beyond \+-1e\+30 feature values set to 0") as rec:
        adapt(r, "box", spp=8, seed=3, log=tmp_path / "run.h5")
    got = read_log(tmp_path / "run.h5")
    depth = got.read_feature("depth")
    assert np.isfinite(depth).all()
    pos = np.asarray(got.read_all().positions, np.float64)
    ends = np.concatenate([[0], np.cumsum([rec["samples"] for rec in got.round_records])])
    bad = np.zeros(len(depth), bool)
    bad[ends[:-1]] = bad[ends[1:] - 1] = True  # each round's first and last rows
    np.testing.assert_array_equal(depth[bad], 0.0)
    np.testing.assert_allclose(depth[~bad], (pos[:, 0] + 1000 * pos[:, 1])[~bad], rtol=1e-6)
    # the colour of those samples is kept; one warning for the run, not one per round
    assert got.n_samples == 12 * 8 * 8 and got.n_rounds > 1
    assert sum("feature values set to 0" in str(w.message) for w in rec) == 1


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


def test_sigkill_mid_run_then_resume_matches_uninterrupted(tmp_path, cli):
    # (no "slow" renderer: the hold below is the synchronisation, a sleep per round only cost time)
    cmd = f"{sys.executable} {FAULT} ok -1 {{request}} {{reply}}"
    common = ["adapt", "--renderer-cmd", cmd, "--size", "12x8", "--spp", "32", "--method", "box", "--seed", "9",
              "--quiet"]
    log = tmp_path / "killed.h5"
    marker = tmp_path / "rounds.txt"
    # The renderer reports every call and holds round 3 until killed: the driver commits
    # round k before it requests round k + 1, so rounds 0-2 are in the log by then and the
    # driver is blocked in the renderer call (6 rounds in all for this run).
    env = cli_env({"FAULT_RENDERER_MARKER": str(marker), "FAULT_RENDERER_HOLD": "3"})
    proc = subprocess.Popen([*MCRECON, *common, "--log", str(log), "-o", str(tmp_path / "killed.exr")],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
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
    out = run_cli_process(["adapt", "--resume", str(log), "-o", str(tmp_path / "resumed.exr"), "--quiet"])
    assert out.returncode == 0, out.stderr
    code, _, err = cli([*common, "--log", tmp_path / "full.h5", "-o", tmp_path / "full.exr"])  # the reference: here
    assert code == 0, err
    assert read_log(log).n_samples == read_log(tmp_path / "full.h5").n_samples == 12 * 8 * 32
    a, _ = read_exr(tmp_path / "resumed.exr")
    b, _ = read_exr(tmp_path / "full.exr")
    np.testing.assert_array_equal(a, b)


# ---------------------------------------------------------------- what the protocol doc promises (issue 13, item 2)
class _Recorder:
    """An in-process renderer that records which parts each request carried."""

    def __init__(self, w=12, h=8):
        self.width, self.height, self.channels = w, h, ("R", "G", "B")
        self.kinds = []

    def render(self, req):
        from mcrecon.core.requests import SampleBatch

        self.kinds.append(("counts" if req.counts is not None else "") + ("positions" if req.positions is not None
                                                                            else ""))
        rng = np.random.default_rng(req.seed)
        pos = request_positions(req, rng)
        return SampleBatch(pos, 0.5 + pos[:, :1] / self.width + 0.2 * rng.random((len(pos), 3)))


@pytest.mark.parametrize("method, later", [("box", "counts"), ("ci", "counts"), ("splat", "counts"),
                                           ("gem", "counts"), ("awr", "counts"), ("auto", "counts")])
def test_which_methods_send_counts_and_which_positions(method, later):
    """docs/renderer-protocol.md's table: round 0 is counts for every method; then counts or positions."""
    r = _Recorder()
    from mcrecon import get_method

    opts = {"gem": {"initial_spp": 2}, "awr": {"initial_spp": 2}, "ci": {"min_spp": 2},
            "auto": {"initial_spp": 2}}.get(method, {})
    adapt(r, get_method(method, **opts), spp=8, seed=1)
    assert r.kinds[0] == "counts" and len(r.kinds) > 1, r.kinds
    assert set(r.kinds[1:]) == {later}, r.kinds


def test_reply_parts_other_than_samples_and_features_are_ignored(tmp_path):
    """A reply may be a whole log: its /round, /rounds/end, /reference, metadata and records are not
    copied to the run's log; its samples and features are."""
    script = tmp_path / "rich_renderer.py"
    script.write_text(f"""
import sys, h5py, numpy as np
sys.path.insert(0, {str(Path(EXAMPLE).parent)!r})
from example_renderer import main
main(sys.argv[1], sys.argv[2])
with h5py.File(sys.argv[2], "r+") as f:
    n, (w, h) = f["positions"].shape[0], (int(f.attrs["width"]), int(f.attrs["height"]))
    f["round"] = np.full(n, 7, np.int32)
    f["rounds/end"] = np.array([n], np.int64)
    f["reference"] = np.ones((h, w, 3))
    f["features/t"] = np.arange(n, dtype=np.int16)
    f.attrs["metadata_json"] = '{{"renderer": "rich"}}'
    f.attrs["format_minor"] = 2
    f.create_group("run").attrs["settings_json"] = "{{}}"
""")
    log = tmp_path / "run.h5"
    adapt(CommandRenderer([sys.executable, str(script), "{request}", "{reply}"], width=8, height=6), "box", spp=4,
          seed=2, log=log)
    got = read_log(log)
    assert got.n_samples == 8 * 6 * 4 and got.feature_names == ("t",) and not got.has_reference
    assert got.read_all().round.tolist() == sorted(got.read_all().round.tolist())
    assert got.read_all().round[0] == 0 and got.metadata.get("renderer") != "rich"
    assert got.read_feature("t").shape == (got.n_samples,)


def test_renderer_cmd_is_split_by_shlex_never_by_a_shell(tmp_path, cli):
    """--renderer-cmd with quoted words (a script in a directory with a space) and a placeholder inside
    a word; no shell: '$HOME' and ';' reach the command as they are."""
    d = tmp_path / "my renderers"
    d.mkdir()
    script = d / "render it.py"
    script.write_text(f"""
import sys
sys.path.insert(0, {str(Path(EXAMPLE).parent)!r})
from example_renderer import main
assert sys.argv[3:] == ["$HOME", ";", "two words"], sys.argv
main(sys.argv[1], sys.argv[2].split("=", 1)[1])
""")
    cmd = f"{sys.executable} '{script}' {{request}} --out={{reply}} '$HOME' ';' \"two words\""
    code, _, err = cli(["adapt", "--renderer-cmd", cmd, "--size", "8x6", "--spp", "2", "--method", "box", "--quiet",
                        "--log", tmp_path / "run.h5", "-o", tmp_path / "o.exr"])
    assert code == 0, err
    assert read_log(tmp_path / "run.h5").run_settings["renderer_spec"]["argv"][1:3] == [str(script), "{request}"]


@pytest.mark.parametrize("channels", ["R, G, B", "R,,B", "R,R"])
def test_channels_flag_syntax(tmp_path, channels, cli):
    code, _, err = cli(["adapt", "--renderer-cmd", f"{sys.executable} {EXAMPLE} {{request}} {{reply}}",
                        "--channels", channels, "--size", "4x4", "--spp", "1", "-o", tmp_path / "o.exr"])
    assert code == 2 and "channels" in err and "--channels R,G,B" in err
    assert len(err.strip().splitlines()) == 1


def test_exchange_files_live_in_a_private_temporary_directory(tmp_path, monkeypatch):
    """Where request/reply files live: $TMPDIR/mcrecon-renderer-PID-XXXX/round-NNNNN.{request,reply}.h5,
    removed after each round and with the renderer."""
    import gc
    import tempfile

    monkeypatch.setenv("TMPDIR", str(tmp_path))
    monkeypatch.setattr(tempfile, "tempdir", None)
    script = tmp_path / "seen.py"
    script.write_text(f"""
import sys
sys.path.insert(0, {str(Path(EXAMPLE).parent)!r})
from example_renderer import main
open({str(tmp_path / 'seen.txt')!r}, "a").write(sys.argv[1] + " " + sys.argv[2] + "\\n")
main(sys.argv[1], sys.argv[2])
""")
    r = CommandRenderer([sys.executable, str(script), "{request}", "{reply}"], width=4, height=4)
    wd = r.workdir
    assert wd.parent == tmp_path and wd.name.startswith(f"mcrecon-renderer-{os.getpid()}-")
    adapt(r, "box", spp=4, seed=1)
    seen = [ln.split() for ln in (tmp_path / "seen.txt").read_text().splitlines()]
    assert seen[0] == [str(wd / "round-00000.request.h5"), str(wd / "round-00000.reply.h5")]
    assert [Path(a).name for a, _ in seen][1] == "round-00001.request.h5"
    assert list(wd.iterdir()) == []  # each accepted round's pair is removed
    del r
    gc.collect()
    assert not wd.exists()

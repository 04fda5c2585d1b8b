"""Nothing lost, nothing silently wrong: checksummed logs, exclusive runs, live reads,
one count of samples, output sanity, failing writes."""

import os
import signal
import subprocess
import sys
import textwrap
import time
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest

import mcrecon
from mcrecon import InputError
from mcrecon.adaptive.run import adapt, resume
from mcrecon.io import append_log, read_log, summarize_log, write_log
from mcrecon.io import reader as samplelog
from mcrecon.io import writer as samplelog_writer
from mcrecon.io.lock import live_writer, lock_path, log_lock
from mcrecon.core.metrics import output_sanity
from mcrecon.renderers.command import CommandRenderer
from mcrecon.core.stats import PixelStats

from helpers import MCRECON, cli_env, run_cli, run_cli_process

FAULT = str(Path(__file__).parent / "renderers" / "fault_renderer.py")


def _log(path, rng, n=200_000, w=64, h=48, **kw):
    pos = rng.random((n, 2)) * [w, h]
    val = rng.random((n, 3)).astype(np.float32)
    write_log(path, pos, val, width=w, height=h, **kw)
    return pos, val


def _damage(path, dataset, chunk=1, nbytes=64, seed=0):
    """Overwrite ``nbytes`` random bytes inside chunk ``chunk`` of ``dataset`` on disk."""
    with h5py.File(path, "r", locking=False) as f:
        info = f[dataset].id.get_chunk_info(chunk)
    with open(path, "r+b") as fh:
        fh.seek(info.byte_offset + min(1000, info.size // 2))
        fh.write(np.random.default_rng(seed).bytes(nbytes))


# ------------------------------------------------------------------ 1. checksums
def test_writer_checksums_every_fixed_size_chunked_dataset(tmp_path, rng):
    path = tmp_path / "a.h5"
    _log(path, rng, n=5000, features={"depth": rng.random(5000).astype(np.float32)}, reference=np.ones((48, 64, 3)))
    append_log(path, rng.random((300, 2)) * [64, 48], rng.random((300, 3)), features={"depth": np.ones(300)},
               round_record={"round": 1, "samples": 300, "note": "a key outside the columns"})
    seen = []

    def visit(name, obj):
        if isinstance(obj, h5py.Dataset):
            seen.append(name)
            is_string = h5py.check_string_dtype(obj.dtype) is not None
            assert obj.chunks is not None, name
            assert obj.fletcher32 or is_string, name  # HDF5 cannot filter variable-length strings

    with h5py.File(path, "r") as f:
        f.visititems(visit)
    assert {"positions", "values", "rounds/end", "features/depth", "reference",
            "run/round_records"} <= set(seen)  # no /round: the rounds' indices are /rounds/end's


def test_random_bytes_in_sample_data_exit_2_with_one_line(tmp_path, rng, capsys):
    path = tmp_path / "damaged.h5"
    _log(path, rng)
    _damage(path, "values", chunk=1)
    for argv in (["info", path], ["info", path, "--json"], ["denoise", path, "-o", tmp_path / "out.exr"],
                 ["denoise", path, "-o", tmp_path / "out.exr", "--method", "splat"]):
        code, out, err = run_cli(argv, capsys)
        assert code == 2, (argv, out)
        assert err.count("\n") == 1, err
        assert f"{path}: dataset /values: rows 65536-131071: checksum mismatch" in err
    assert not (tmp_path / "out.exr").exists()
    with pytest.raises(InputError, match="rows 65536-131071: checksum mismatch"):
        PixelStats.from_log(read_log(path))


@pytest.mark.parametrize("dataset, match", [("positions", "dataset /positions: rows 0-3009: checksum mismatch"),
                                            ("rounds/end", "dataset /rounds/end: rows 0-"),
                                            ("run/round_records", "dataset /run/round_records: rows 0-")])
def test_damage_elsewhere_names_the_dataset(tmp_path, rng, dataset, match):
    path = tmp_path / "a.h5"
    _log(path, rng, n=3000)
    append_log(path, rng.random((10, 2)) * [64, 48], rng.random((10, 3)), round_record={"round": 1})
    _damage(path, dataset, chunk=0, nbytes=8)
    with pytest.raises(InputError, match=match) as exc:
        summarize_log(path)
    assert "\n" not in str(exc.value)


def test_logs_without_checksums_still_read(tmp_path, rng):
    path = tmp_path / "plain.h5"
    pos = rng.random((1000, 2)) * [8, 8]
    with h5py.File(path, "w") as f:  # another writer: contiguous, no filters
        f.attrs.update(format_version=1, width=8, height=8, channels=np.array(["Y"], dtype=h5py.string_dtype()))
        f["positions"] = pos
        f["values"] = np.ones((1000, 1))
    assert summarize_log(path)["samples"] == 1000
    append_log(path, pos[:10], np.ones((10, 1)))  # converted once, checksummed from then on
    assert read_log(path).n_samples == 1010
    with h5py.File(path, "r") as f:
        assert f["values"].fletcher32


# ------------------------------------------------------------------ 2. exclusive runs
def _held_run(tmp_path, log, hold=3, extra_env=None):
    """An adaptive run in a subprocess whose renderer holds round ``hold`` until killed."""
    marker = tmp_path / "rounds.txt"
    env = cli_env({"FAULT_RENDERER_MARKER": str(marker), "FAULT_RENDERER_HOLD": str(hold), **(extra_env or {})})
    cmd = f"{sys.executable} {FAULT} ok -1 {{request}} {{reply}}"
    proc = subprocess.Popen([*MCRECON, "adapt", "--renderer-cmd", cmd, "--size", "12x8", "--spp", "32",
                             "--method", "box", "--seed", "9", "--quiet", "--log", str(log), "-o",
                             str(tmp_path / "held.exr")], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    return proc, marker


def _wait_round(marker, k, proc, timeout=120.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if marker.exists():
            lines = [ln.split() for ln in marker.read_text().splitlines(keepends=True) if ln.endswith("\n")]
            if any(int(r) >= k for r, _ in lines):
                return [int(p) for _, p in lines]
        if proc.poll() is not None:
            pytest.fail(f"the run ended (status {proc.returncode}): {proc.stderr.read()!r}")
        time.sleep(0.02)
    pytest.fail(f"round {k} was not requested within {timeout} s")


def _stop(proc, pids):
    for pid in [proc.pid, *pids]:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    proc.wait()
    proc.stderr.close()


def test_second_run_refused_while_a_run_holds_its_log_then_stale_lock_taken_over(tmp_path):
    log = tmp_path / "run.h5"
    proc, marker = _held_run(tmp_path, log)
    pids = []
    try:
        pids = _wait_round(marker, 3, proc)
        assert lock_path(log).read_text().strip() == str(proc.pid)
        assert live_writer(log) == proc.pid
        # 3. live monitoring: every committed round, read while the run holds the log
        sl = read_log(log)
        assert sl.n_rounds == 3 and len(sl.round_records) == 3
        info = summarize_log(log)
        assert info["samples"] == sl.n_samples == sl.round_ends[-1] and info["writer_pid"] == proc.pid
        # 2. a resume and a new run on the same log are refused, naming the holder
        for argv in (["adapt", "--resume", str(log), "-o", str(tmp_path / "x.exr"), "--quiet"],
                     ["adapt", "--scene", "soft_shadow", "--size", "12x8", "--spp", "2", "--log", str(log),
                      "-o", str(tmp_path / "y.exr"), "--quiet"]):
            out = run_cli_process(argv)
            assert out.returncode == 2, out
            assert out.stderr.count("\n") == 1, out.stderr
            assert f"being written by process {proc.pid}" in out.stderr
        with pytest.raises(InputError, match=f"process {proc.pid}"):
            resume(log)
    finally:
        _stop(proc, pids)
    # the killed run's lock file stays, with its PID, but no live holder: taken over
    assert lock_path(log).read_text().strip() == str(proc.pid)
    assert live_writer(log) is None
    res = resume(log, CommandRenderer([sys.executable, FAULT, "ok", "-1", "{request}", "{reply}"],
                                      width=12, height=8))
    assert res.samples == read_log(log).n_samples == 12 * 8 * 32
    assert not lock_path(log).exists()  # released at the end of the run


def test_lock_is_reentrant_in_process_and_refuses_other_processes(tmp_path):
    log = tmp_path / "a.h5"
    script = textwrap.dedent(f"""
        from mcrecon.io.lock import log_lock
        import sys
        try:
            with log_lock({str(log)!r}, wait=0.1):
                pass
        except Exception as exc:
            print(exc); sys.exit(2)
    """)
    with log_lock(log):
        with log_lock(log):  # re-entrant: the driver holds it while append_log takes it again
            assert lock_path(log).read_text().strip() == str(os.getpid())
        out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
        assert out.returncode == 2 and f"being written by process {os.getpid()}" in out.stdout
        assert live_writer(log) is None  # our own lock is no other writer
    assert not lock_path(log).exists()
    assert subprocess.run([sys.executable, "-c", script]).returncode == 0


# ------------------------------------------------------------------ 3. live monitoring under appends
APPENDER = textwrap.dedent("""
    import sys, numpy as np
    from mcrecon.io import write_log, append_log
    from mcrecon.io.lock import log_lock
    p = sys.argv[1]
    rng = np.random.default_rng(1)
    with log_lock(p):  # as a run does: held for the whole run
        write_log(p, rng.random((1000, 2)) * 32, rng.random((1000, 3)), width=32, height=32)
        print("ready", flush=True)
        for i in range(100000):
            n = int(rng.integers(100, 20000))
            append_log(p, rng.random((n, 2)) * 32, rng.random((n, 3)), round_record={"n": n})
""")


def test_info_and_denoise_read_a_log_while_a_run_appends(tmp_path):
    script = tmp_path / "appender.py"
    script.write_text(APPENDER)
    log = tmp_path / "live.h5"
    proc = subprocess.Popen([sys.executable, str(script), str(log)], stdout=subprocess.PIPE)
    try:
        assert proc.stdout.readline().strip() == b"ready"
        seen, last = 0, 0
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:
            info = summarize_log(log)  # never an error: the committed rounds are read
            sl = read_log(log)
            assert info["samples"] >= last and sl.n_samples >= info["samples"]
            assert info["spp_mean"] * 32 * 32 == pytest.approx(info["samples"])
            assert len(sl.round_records) == sl.n_rounds - 1
            with warnings.catch_warnings():  # pixels still without samples are filled (and said so)
                warnings.simplefilter("ignore", mcrecon.McreconWarning)
                img = mcrecon.reconstruct(sl, method="box")
            assert np.isfinite(img).all()
            last = info["samples"]
            seen += 1
        assert proc.poll() is None and seen >= 3 and last > 1000
    finally:
        proc.kill()
        proc.wait()
        proc.stdout.close()


# ------------------------------------------------------------------ 4. one count of samples
class _NaNRenderer:
    """A renderer whose every 10th sample is NaN."""

    width, height, channels, name = 16, 12, ("R", "G", "B"), "nan-renderer"

    def render(self, req):
        rng = np.random.default_rng(req.seed)
        pix = np.repeat(np.arange(16 * 12), req.counts.ravel())
        pos = np.stack([pix % 16, pix // 16], 1) + rng.random((pix.size, 2))
        val = rng.random((pix.size, 3))
        val[::10, 1] = np.nan
        return mcrecon.SampleBatch(pos, val)


def test_samples_counted_one_way_by_adapt_info_and_records(tmp_path, capsys):
    log = tmp_path / "nan.h5"
    with pytest.warns(mcrecon.McreconWarning):
        res = adapt(_NaNRenderer(), "box", spp=8, log=log)
    budget = 16 * 12 * 8
    info = summarize_log(log)
    assert res.samples == budget == info["samples"] == res.rounds[-1]["samples_total"] == read_log(log).n_samples
    assert sum(r["samples"] for r in res.rounds) == budget
    assert res.samples_dropped == info["nonfinite_samples"] > 0
    assert res.samples_used == info["finite_samples"] == budget - res.samples_dropped
    # the CLI prints the same count as `info`
    cmd = f"{sys.executable} {FAULT} nan 0 {{request}} {{reply}}"
    log2 = tmp_path / "cli.h5"
    code, out, _ = run_cli(["adapt", "--renderer-cmd", cmd, "--size", "12x8", "--spp", "4", "--log", log2,
                            "-o", tmp_path / "o.exr", "--quiet"], capsys)
    assert code == 0 and "384 samples (4.00 spp, 2 non-finite dropped)" in out
    assert summarize_log(log2)["samples"] == 384 and summarize_log(log2)["finite_samples"] == 382


# ------------------------------------------------------------------ 5. output sanity
def test_output_sanity_counts_negatives_and_overshoot(rng):
    pos = rng.random((4000, 2)) * [10, 10]
    stats = PixelStats.from_samples(pos, np.full((4000, 1), 50.0), width=10, height=10, channels=("Y",))
    flat = np.full((10, 10, 1), 50.0)
    assert output_sanity(flat, stats) == {"negative_pixels": 0, "overshoot_pixels": 0, "max_overshoot": 0.0,
                                          "max_overshoot_relative": 0.0, "nonfinite_pixels": 0}
    bad = flat.copy()
    bad[2, 3] = 62.8
    bad[5, 5] = -1.31
    s = output_sanity(bad, stats)
    assert s["negative_pixels"] == 1 and s["overshoot_pixels"] == 2
    assert s["max_overshoot"] == pytest.approx(51.31)
    assert output_sanity(flat, PixelStats.from_moments(flat, flat, np.full((10, 10), 4))) is None


@pytest.mark.parametrize("method", ["box", "awr", "splat"])
def test_every_reconstruction_reports_its_sanity(tmp_path, rng, method, capsys):
    path = tmp_path / "a.h5"
    _log(path, rng, n=20_000, w=32, h=24)
    rec = mcrecon.reconstruct(path, method=method, full=True)
    s = rec.sanity()
    assert set(s) == {"negative_pixels", "overshoot_pixels", "max_overshoot", "max_overshoot_relative",
                      "nonfinite_pixels"}
    if method == "box":  # the pixel mean never leaves its samples' range
        assert s["negative_pixels"] == s["overshoot_pixels"] == 0
    code, out, _ = run_cli(["denoise", path, "-o", tmp_path / "o.exr", "--method", method], capsys)
    assert code == 0 and f"output: {s['negative_pixels']} negative pixel(s)" in out


# ------------------------------------------------------------------ 6. a failing write mid-append
def test_failing_write_mid_append_keeps_committed_rounds_and_resume_matches(tmp_path, monkeypatch):
    from mcrecon.renderers.scenes import SceneRenderer, get_scene

    def renderer():
        return SceneRenderer(get_scene("soft_shadow"), width=16, height=12, seed=2)

    full = adapt(renderer(), "gem", spp=24, seed=5, log=tmp_path / "full.h5", track_error=False)
    assert len(full.rounds) >= 3
    log = tmp_path / "faulty.h5"
    real = h5py.Dataset.__setitem__
    calls = {"appends": 0}
    real_append = samplelog_writer._append

    def counting_append(*a, **kw):
        calls["appends"] += 1
        return real_append(*a, **kw)

    def failing_setitem(self, key, value):
        if calls["appends"] == 3 and self.name == "/values":  # round 2: positions written, values fail
            raise OSError(28, "No space left on device")
        return real(self, key, value)

    monkeypatch.setattr(samplelog_writer, "_append", counting_append)
    monkeypatch.setattr(h5py.Dataset, "__setitem__", failing_setitem)
    with pytest.raises(InputError) as exc:
        adapt(renderer(), "gem", spp=24, seed=5, log=log, track_error=False)
    monkeypatch.undo()
    msg = str(exc.value)
    assert "\n" not in msg and "No space left on device" in msg and "was not committed" in msg
    assert not lock_path(log).exists()
    sl = read_log(log)
    assert sl.n_rounds == 2 and sl.n_samples == full.rounds[1]["samples_total"]
    res = resume(log, renderer(), track_error=False)
    assert res.samples == full.samples and read_log(log).n_samples == read_log(tmp_path / "full.h5").n_samples
    np.testing.assert_array_equal(res.image, full.image)


# ------------------------------------------------------------------ huge films
def test_huge_film_refused_before_any_allocation(tmp_path, capsys):
    path = tmp_path / "huge.h5"
    with h5py.File(path, "w") as f:
        f.attrs.update(format_version=1, width=10**9, height=10**9,
                       channels=np.array(["R"], dtype=h5py.string_dtype()))
        f["positions"] = np.zeros((1, 2))
        f["values"] = np.zeros((1, 1))
    for argv in (["info", path], ["denoise", path, "-o", tmp_path / "o.exr"]):
        code, _, err = run_cli(argv, capsys)
        assert code == 2 and err.count("\n") == 1 and "1000000000x1000000000" in err
    with pytest.raises(InputError, match="beyond"):
        write_log(tmp_path / "w.h5", np.zeros((0, 2)), np.zeros((0, 3)), width=10**9, height=10**9)


# ------------------------------------------------------------------ stale renderer work directories
def test_sigkilled_runs_renderer_workdir_removed_by_the_next_renderer(tmp_path, monkeypatch):
    import tempfile

    from mcrecon.renderers.command import remove_stale_workdirs

    script = textwrap.dedent(f"""
        import sys, time
        from mcrecon.renderers.command import CommandRenderer
        r = CommandRenderer([sys.executable, {FAULT!r}, "ok", "-1", "{{request}}", "{{reply}}"], width=4, height=4)
        (r.workdir / "round-00000.request.h5").write_bytes(b"x")  # a round in flight
        print(r.workdir, flush=True)
        time.sleep(600)
    """)
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, env=env)
    try:
        left = Path(proc.stdout.readline().strip())
        assert left.parent == tmp_path and left.name.startswith(f"mcrecon-renderer-{proc.pid}-")
        assert remove_stale_workdirs(tmp_path) == []  # its owner is alive: kept
        assert left.is_dir()
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
    assert left.is_dir()  # SIGKILL leaves no chance to clean up
    legacy = tmp_path / "mcrecon-renderer-abc123"  # no PID in the name (older versions): left alone
    legacy.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    r = CommandRenderer([sys.executable, FAULT, "ok", "-1", "{request}", "{reply}"], width=4, height=4)
    assert not left.exists() and legacy.is_dir()
    assert r.workdir.is_dir() and r.workdir.name.startswith(f"mcrecon-renderer-{os.getpid()}-")
    assert remove_stale_workdirs(tmp_path) == []  # ours is alive
    workdir = r.workdir
    del r
    assert not workdir.exists()


# ------------------------------------------------------------------ a read-only directory mid-run
@pytest.fixture
def tmpfs(tmp_path):
    """A small tmpfs mounted at ``tmp_path/mnt`` (root only; skipped, with the reason, otherwise)."""
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    out = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64m", "tmpfs", str(mnt)], capture_output=True, text=True)
    if out.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root and mount permission): {out.stderr.strip()}")
    yield mnt
    while subprocess.run(["umount", str(mnt)], capture_output=True).returncode == 0:
        pass  # the read-only bind mount over it, then the tmpfs


def test_read_only_directory_mid_run_one_line_then_resume_matches(tmp_path, tmpfs, uninterrupted, capsys):
    from mcrecon.io import read_exr

    full_log, full_exr = uninterrupted
    log = tmpfs / "run.h5"
    # at round 2 the renderer mounts the log's directory read-only over itself
    out = _adapt_cli(log, tmp_path / "ro.exr", {"FAULT_RENDERER_DISK": f"ro:{tmpfs}", "FAULT_RENDERER_DISK_ROUND": "2"})
    assert out.returncode == 2, out
    assert out.stderr.count("\n") == 1 and out.stderr.startswith("mcrecon: error: "), out.stderr
    assert "cannot be opened for writing" in out.stderr and "Read-only file system" in out.stderr
    assert "regenerate" not in out.stderr  # a healthy log is never called damaged
    sl = read_log(log)  # every round committed before the fault
    assert sl.n_rounds == 2 and list(sl.round_ends) == [512, 1024]
    assert live_writer(log) is None  # the lock left behind (it could not be removed) is stale
    assert subprocess.run(["umount", str(tmpfs)]).returncode == 0  # writable again
    # the resume in this process (test_external.py resumes a killed run in a child of its own)
    code, _, err = run_cli(["adapt", "--resume", log, "-o", tmp_path / "resumed.exr", "--quiet"], capsys)
    assert code == 0, err
    assert read_log(log).n_samples == read_log(full_log).n_samples == 32 * 16 * 32
    np.testing.assert_array_equal(read_exr(tmp_path / "resumed.exr")[0], read_exr(full_exr)[0])
    assert not lock_path(log).exists()


# ------------------------------------------------------------------ a full disk mid-run
def _adapt_cli(log, out, extra_env=None, *, prelude=None):
    return run_cli_process(_adapt_argv(log, out), extra_env=extra_env, prelude=prelude)


def _adapt_argv(log, out):
    return ["adapt", "--renderer-cmd", f"{sys.executable} {FAULT} ok -1 {{request}} {{reply}}", "--size", "32x16",
            "--spp", "32", "--method", "box", "--seed", "9", "--quiet", "--log", str(log), "-o", str(out)]


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """The run the faulted runs are resumed into, once per module (a worker's): its log and image.  In this
    process: the same command as the faulted runs' children, whose exits are what those tests check."""
    d = tmp_path_factory.mktemp("uninterrupted")
    assert run_cli(_adapt_argv(d / "full.h5", d / "full.exr"))[0] == 0
    return d / "full.h5", d / "full.exr"


@pytest.mark.parametrize("path", ["checked", "inside_hdf5"])
def test_full_disk_mid_run_one_line_then_resume_matches(tmp_path, tmpfs, uninterrupted, path, capsys):
    """At round 2 the renderer fills the log's file system (ENOSPC).

    ``checked``: the append sees too little free space and refuses before
    writing.  ``inside_hdf5``: with that check disabled, HDF5 itself hits
    ENOSPC half-way through the round (the race the check cannot close);
    HDF5 then cannot close the file, and its clean-up at exit used to
    crash the process (SIGSEGV, exit 139) after the message.  Both: exit 2,
    one line, the log opens with the two committed rounds, and once space
    is freed the resumed run equals the uninterrupted one.
    """
    from mcrecon.io import read_exr

    full_log, full_exr = uninterrupted
    log, filler = tmpfs / "run.h5", tmpfs / "filler"
    prelude = ("import mcrecon.io.writer as s; s._check_free_space = lambda *a, **k: None"
               if path == "inside_hdf5" else None)
    out = _adapt_cli(log, tmp_path / "o.exr", {"FAULT_RENDERER_DISK": f"fill:{filler}",
                                               "FAULT_RENDERER_DISK_ROUND": "2"}, prelude=prelude)
    assert out.returncode == 2, out
    assert out.stderr.count("\n") == 1 and out.stderr.startswith("mcrecon: error: "), out.stderr
    assert ("not enough free disk space" if path == "checked" else "No space left on device") in out.stderr
    assert "regenerate" not in out.stderr
    sl = read_log(log)
    if path == "checked":
        assert sl.n_rounds == 2 and list(sl.round_ends) == [512, 1024]
    else:  # HDF5 fails when it next needs new space: rounds that fit in the file's free chunks commit
        assert 2 <= sl.n_rounds < read_log(full_log).n_rounds
        assert list(sl.round_ends) == list(read_log(full_log).round_ends[:sl.n_rounds])
    filler.unlink()
    code, _, err = run_cli(["adapt", "--resume", log, "-o", tmp_path / "resumed.exr", "--quiet"], capsys)
    assert code == 0, err
    assert read_log(log).n_samples == read_log(full_log).n_samples == 32 * 16 * 32
    np.testing.assert_array_equal(read_exr(tmp_path / "resumed.exr")[0], read_exr(full_exr)[0])


def test_free_space_estimate_counts_whole_chunks(tmp_path, monkeypatch):
    from mcrecon.io import reader as samplelog
    from mcrecon.io import writer as samplelog_writer

    class FS:
        f_frsize = 4096

        def __init__(self, blocks):
            self.f_bavail = blocks

    chunk, row = 1000, 24
    # n = 1500, m = 1000: chunks 2 (partial) and 3 are written -> 2 * 1000 * 24 bytes + margin
    need = 2 * chunk * row + samplelog_writer.APPEND_SPACE_MARGIN
    monkeypatch.setattr(os, "statvfs", lambda p: FS(need // 4096 + 1))
    samplelog_writer._check_free_space(tmp_path / "x.h5", 1500, 1000, chunk, row)
    monkeypatch.setattr(os, "statvfs", lambda p: FS(need // 4096 - 1))
    with pytest.raises(InputError, match=r"not enough free disk space for the round \(1000 samples"):
        samplelog_writer._check_free_space(tmp_path / "x.h5", 1500, 1000, chunk, row)
    samplelog_writer._check_free_space(tmp_path / "x.h5", 1500, 0, chunk, row)  # nothing to write: no check

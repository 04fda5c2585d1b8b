"""SIGKILL at random moments while rounds are appended: the log stays readable and consistent."""

import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from mcrecon.io import read_log
from mcrecon.core.stats import PixelStats

# Reports each append before it starts and once it has returned (committed), so the
# test knows what the log must hold without opening it while the appender runs.
APPENDER = textwrap.dedent("""
    import sys, numpy as np
    from mcrecon.io import write_log, append_log
    p = sys.argv[1]
    rng = np.random.default_rng(int(sys.argv[2]))
    write_log(p, rng.random((1000, 2)) * 64, rng.random((1000, 3)), width=64, height=64)
    print("committed 1000", flush=True)
    while True:
        n = int(rng.integers(1000, 200000))
        print(f"appending {n}", flush=True)
        total = append_log(p, rng.random((n, 2)) * 64, rng.random((n, 3)), round_record={"n": n})
        print(f"committed {total}", flush=True)
""")


@pytest.mark.slow
def test_kill_during_appends_never_loses_committed_rounds(tmp_path, full_run):
    script = tmp_path / "appender.py"
    script.write_text(APPENDER)
    trials = 30 if full_run else 6
    rng = np.random.default_rng(4)
    for t in range(trials):
        path = tmp_path / f"k{t}.h5"
        proc = subprocess.Popen([sys.executable, str(script), str(path), str(t)], stdout=subprocess.PIPE)
        assert proc.stdout.readline().strip() == b"committed 1000"
        time.sleep(float(rng.uniform(0.05, 1.0)))
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        lines = proc.stdout.read().decode().split("\n")
        proc.stdout.close()
        committed, pending = 1000, None  # from complete lines only
        for ln in lines[:-1]:
            word, num = ln.split()
            committed, pending = (int(num), None) if word == "committed" else (committed, int(num))
        log = read_log(path)  # only now: the appender is dead
        # every append that returned is in the log; the one in flight is either committed or not at all
        assert log.n_samples in (committed, committed + (pending or 0))
        stats = PixelStats.from_log(log)
        assert stats.n_samples == log.n_samples == log.round_ends[-1]
        # every committed round except the initial write carries its record
        assert len(log.round_records) == log.n_rounds - 1
        assert [r["n"] for r in log.round_records] == np.diff(log.round_ends).tolist()
        path.unlink()


# ---- a torn rewrite of the last, partly filled chunk, reproduced without timing luck
#
# An append writes its rows into the partly filled last chunk by rewriting that chunk whole
# (its committed rows with the same bytes) and then its Fletcher-32 checksum.  A SIGKILL in
# the middle leaves the committed rows intact and the checksum wrong.  The state is made
# here exactly: an append stopped just before its commit (everything written and flushed,
# n_committed not updated), then bytes of the chunk past the committed rows (or its
# checksum) overwritten, as a write cut short would leave them.

import h5py  # noqa: E402

from mcrecon.errors import InputError  # noqa: E402
from mcrecon.io import append_log, write_log  # noqa: E402
import mcrecon.io.writer as writer  # noqa: E402


class _Killed(BaseException):
    """Stands for the SIGKILL: not an error any layer catches."""


def _killed_before_commit(monkeypatch, path, rng, m, **kw):
    def kill(f, n):
        raise _Killed

    with monkeypatch.context() as mp:
        mp.setattr(writer, "_commit", kill)
        with pytest.raises(_Killed):
            append_log(path, rng.random((m, 2)) * 64, rng.random((m, 3)), **kw)


def _tear(path, name, row, *, where="rows"):
    """Overwrite bytes of the chunk holding ``row`` of ``/name``: just past ``row`` (``rows``),
    at ``row`` itself (``committed``: damage, not a tear) or its checksum (``checksum``)."""
    with h5py.File(path, "r") as f:
        d = f[name]
        c = d.chunks[0]
        a = row - row % c
        info = d.id.get_chunk_info_by_coord((a,) + (0,) * (d.ndim - 1))
        row_bytes = d.dtype.itemsize * int(np.prod(d.shape[1:]))
    at = {"rows": info.byte_offset + (row + 1 - a) * row_bytes,
          "committed": info.byte_offset + (row - a) * row_bytes,
          "checksum": info.byte_offset + info.size - 4}[where]
    with open(path, "r+b") as fh:
        fh.seek(at)
        old = fh.read(4)
        fh.seek(at)
        fh.write(bytes(x ^ 0x5A for x in old))


def _committed_log(path, rng, features=False, round_labels=False):
    """A log of 1000 + 2 appended rounds (4096-row chunks, a record per round): the last chunk partly full.
    ``round_labels``: with a per-sample /round, as older mcrecon wrote (appends extend it)."""
    feats = lambda m: {"depth": rng.random(m).astype(np.float32)} if features else None  # noqa: E731
    write_log(path, rng.random((1000, 2)) * 64, rng.random((1000, 3)), width=64, height=64,
              features=feats(1000))
    if round_labels:
        with h5py.File(path, "r+") as f:
            f.create_dataset("round", data=np.zeros(1000, np.int32), maxshape=(None,), chunks=(4096,), fletcher32=True)
    for m in (3000, 2500):  # the committed rows end at 6500, inside the chunk of rows 4096-8191
        append_log(path, rng.random((m, 2)) * 64, rng.random((m, 3)), round_record={"samples": m},
                   features=feats(m))
    log = read_log(path)
    return log.read_all(features=("depth",) if features else ()), log.round_ends.tolist(), log.round_records


@pytest.mark.parametrize("name, where", [("values", "rows"), ("values", "checksum"), ("positions", "rows"),
                                         ("round", "rows"), ("features/depth", "rows"), ("rounds/end", "rows"),
                                         ("run/round_records", "rows")])
def test_torn_last_chunk_keeps_committed_rows_and_the_next_append_repairs_it(tmp_path, rng, monkeypatch,
                                                                             name, where):
    path = tmp_path / "torn.h5"
    before, ends, records = _committed_log(path, rng, features=True, round_labels=name == "round")
    _killed_before_commit(monkeypatch, path, rng, 700, round_record={"samples": 700},
                          features={"depth": np.ones(700, np.float32)})
    last = {"rounds/end": len(ends) - 1, "run/round_records": len(ends) - 1}.get(name, ends[-1] - 1)
    _tear(path, name, last, where=where)
    with h5py.File(path, "r") as f, pytest.raises(OSError):
        f[name][:last + 1]  # the chunk really fails its checksum
    log = read_log(path)
    assert log.n_samples == ends[-1] and log.round_ends.tolist() == ends and log.round_records == records
    got = log.read_all(features=("depth",))
    for a, b in ((got.positions, before.positions), (got.values, before.values), (got.round, before.round),
                 (got.features["depth"], before.features["depth"])):
        assert np.array_equal(a, b)
    stats = PixelStats.from_log(log)
    assert stats.n_samples == ends[-1]
    # the resume: the next append repairs the chunk and commits
    pos, val = rng.random((900, 2)) * 64, rng.random((900, 3))
    assert append_log(path, pos, val, round_record={"samples": 900},
                      features={"depth": np.full(900, 2, np.float32)}) == ends[-1] + 900
    with h5py.File(path, "r") as f:
        f[name][:]  # every chunk reads again
    log = read_log(path)
    assert log.round_ends.tolist() == ends + [ends[-1] + 900]
    assert log.round_records == records + [{"samples": 900}]
    got = log.read_all(features=("depth",))
    assert np.array_equal(got.values, np.concatenate([before.values, val]))
    assert np.array_equal(got.positions, np.concatenate([before.positions, pos.astype(got.positions.dtype)]))
    assert np.array_equal(got.features["depth"], np.concatenate([before.features["depth"], np.full(900, 2)]))


def test_resume_twice_after_a_tear_and_a_kill_during_the_repair(tmp_path, rng, monkeypatch):
    """While the chunk is torn its notes in /_tail are what vouches for it: a resume repairs the
    chunk without touching them, and a resume killed again before its commit leaves a log that reads."""
    path = tmp_path / "twice.h5"
    before, ends, _ = _committed_log(path, rng)
    _killed_before_commit(monkeypatch, path, rng, 700)
    _tear(path, "values", ends[-1] - 1)
    _killed_before_commit(monkeypatch, path, rng, 300)  # the resume, itself killed before its commit
    _tear(path, "values", ends[-1] - 1)
    log = read_log(path)
    assert log.n_samples == ends[-1] and np.array_equal(log.read_all().values, before.values)
    assert append_log(path, rng.random((10, 2)) * 64, rng.random((10, 3))) == ends[-1] + 10
    assert np.array_equal(read_log(path).read_all().values[:ends[-1]], before.values)


def test_torn_chunk_found_while_updating_the_last_record_keeps_the_record(tmp_path, rng, monkeypatch):
    path = tmp_path / "update.h5"
    _, ends, records = _committed_log(path, rng)

    def kill(*a, **k):
        raise _Killed

    with monkeypatch.context() as mp:  # the update killed after its notes in /_tail, before its write
        mp.setattr(writer, "_write_round_record", kill)
        with pytest.raises(_Killed):
            writer.update_round_record(path, {"samples": 2500, "wall_seconds": 1.5})
    _tear(path, "run/round_records", len(ends) - 1, where="checksum")
    assert read_log(path).round_records == records  # the record as it was before the update
    writer.update_round_record(path, {"samples": 2500, "wall_seconds": 1.5})
    assert read_log(path).round_records == records[:-1] + [{"samples": 2500, "wall_seconds": 1.5}]


@pytest.mark.parametrize("case", ["committed row of the last chunk", "earlier chunk", "no copy"])
def test_genuine_damage_of_committed_rows_is_still_reported(tmp_path, rng, monkeypatch, case):
    path = tmp_path / "damaged.h5"
    _, ends, _ = _committed_log(path, rng)
    _killed_before_commit(monkeypatch, path, rng, 700)
    n = ends[-1]
    if case == "committed row of the last chunk":  # the stored committed rows lost their digest
        _tear(path, "values", n - 1, where="committed")
        rows = "rows 4096-6499"
    elif case == "earlier chunk":
        _tear(path, "values", 100, where="committed")
        rows = "rows 0-4095"
    else:  # an append of an mcrecon without /_tail, killed the same way
        _tear(path, "values", n - 1)
        with h5py.File(path, "r+") as f:
            del f["_tail"]
        rows = "rows 4096-6499"
    with pytest.raises(InputError) as exc:
        PixelStats.from_log(read_log(path))
    msg = str(exc.value)
    assert "\n" not in msg and str(path) in msg
    assert f"dataset /values: {rows}: checksum mismatch (Fletcher-32)" in msg, msg
    if case != "earlier chunk":  # an append reads the last chunk only (it repairs a torn one, never damage)
        with pytest.raises(InputError, match=f"dataset /values: {rows}: checksum mismatch"):
            append_log(path, rng.random((10, 2)) * 64, rng.random((10, 3)))


def test_tail_notes_are_ignored_once_a_later_round_is_committed(tmp_path, rng):
    """/_tail vouches for a chunk only in the commit state its notes were made in: damage of the
    chunk after the next commit is reported."""
    path = tmp_path / "stale.h5"
    _, ends, _ = _committed_log(path, rng)  # the last append noted rows 0-3999 of state 4000
    _tear(path, "values", ends[-1] - 1)
    with pytest.raises(InputError, match="dataset /values: rows 4096-6499: checksum mismatch"):
        PixelStats.from_log(read_log(path))

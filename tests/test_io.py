"""Sample logs (format v1) and images: round trips, appends, bad files."""

import hashlib
import json
import os
import stat

import h5py
import numpy as np
import pytest

from mcrecon import InputError, PixelStats
from mcrecon.io import append_log, read_exr, read_log, write_exr, write_false_colour, write_log, write_png_preview
from mcrecon.io import reader as samplelog
from mcrecon.io import logformat as samplelog_logformat
from mcrecon.io.logformat import APPEND_CHUNK_ROWS, cast_positions
from mcrecon.io.writer import update_round_record


def _log(tmp_path, rng, n=500, w=9, h=7, c=3, **kw):
    pos = rng.random((n, 2)) * [w, h]
    val = rng.random((n, c)).astype(np.float32)
    path = write_log(tmp_path / "a.h5", pos, val, width=w, height=h,
                     channels=tuple("RGBAXYZ"[:c]), **kw)
    return path, pos, val


def _digest(path):
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


def test_round_trip_and_metadata(tmp_path, rng):
    ref = rng.random((7, 9, 3))
    feats = {"depth": rng.random(500).astype(np.float32), "normal": rng.random((500, 3))}
    path, pos, val = _log(tmp_path, rng, reference=ref, features=feats,
                          metadata={"renderer": "test", "seed": 3, "settings": {"spp": 8}})
    log = read_log(path)
    assert (log.width, log.height, log.channels, log.n_samples, log.n_rounds) == (9, 7, ("R", "G", "B"), 500, 1)
    data = log.read_all()
    np.testing.assert_array_equal(data.positions, pos)  # float64 positions kept exactly
    np.testing.assert_array_equal(data.values, val)
    np.testing.assert_allclose(log.reference(), ref.astype(np.float32))
    np.testing.assert_array_equal(log.read_feature("depth"), feats["depth"])
    assert log.metadata == {"renderer": "test", "seed": 3, "settings": {"spp": 8}}
    assert log.feature_names == ("depth", "normal")


def test_streaming_chunks_equal_whole(tmp_path, rng):
    path, pos, val = _log(tmp_path, rng, n=10_000)
    log = read_log(path)
    chunks = list(log.iter_chunks(chunk_size=777))
    assert len(chunks) == 13 and sum(len(c) for c in chunks) == 10_000
    a = PixelStats.from_log(log, chunk_size=777, subpixels=4)
    b = PixelStats.from_samples(pos, val, width=9, height=7, subpixels=4)
    np.testing.assert_array_equal(a.count, b.count)
    np.testing.assert_allclose(a.mean, b.mean, rtol=1e-12)
    np.testing.assert_allclose(a.m2, b.m2, rtol=1e-9)


def test_append_rounds_and_merge_property(tmp_path, rng):
    path, pos, val = _log(tmp_path, rng, n=300)
    pos2 = rng.random((200, 2)) * [9, 7]
    val2 = rng.random((200, 3))
    assert append_log(path, pos2, val2) == 500
    log = read_log(path)
    assert log.n_rounds == 2 and log.round_slices() == [(0, 300), (300, 500)]
    r1 = log.read_all(rounds=[1])
    np.testing.assert_array_equal(r1.round, 1)
    np.testing.assert_allclose(r1.values, val2.astype(np.float32))  # stored in the log's dtype
    # statistics of round 0 merged with round 1 equal statistics of everything
    s0 = PixelStats.from_log(log, rounds=[0])
    s0.merge(PixelStats.from_log(log, rounds=[1]))
    whole = PixelStats.from_log(log)
    np.testing.assert_allclose(s0.mean, whole.mean, rtol=1e-12)
    np.testing.assert_allclose(s0.m2, whole.m2, rtol=1e-9)


def test_append_refuses_channel_mismatch(tmp_path, rng):
    path, *_ = _log(tmp_path, rng)
    before = _digest(path)
    with pytest.raises(InputError, match="values"):
        append_log(path, rng.random((5, 2)), rng.random((5, 4)))
    with pytest.raises(InputError, match="off the film"):
        append_log(path, np.array([[9.0, 0.0]]), rng.random((1, 3)))
    with pytest.raises(InputError, match="features"):
        append_log(path, rng.random((5, 2)), rng.random((5, 3)), features={"depth": np.zeros(5)})
    assert read_log(path).n_samples == 500 and _digest(path) == before


def test_interrupted_append_is_ignored_then_discarded(tmp_path, rng):
    path, pos, val = _log(tmp_path, rng, n=100)
    with h5py.File(path, "r+") as f:  # rows written but never committed (a crash mid-append)
        for name in ("positions", "values", "round"):
            if name in f:  # /round: only where the labels are not the rounds' indices
                f[name].resize(150, axis=0)
    log = read_log(path)
    assert log.n_samples == 100 and len(log.read_all()) == 100
    append_log(path, rng.random((10, 2)), rng.random((10, 3)))
    log = read_log(path)
    assert log.n_samples == 110 and log.round_slices() == [(0, 100), (100, 110)]


# ---------------------------------------------------------------- logs that grow by rounds
W, H = 16, 8


def _empty_log(path):
    """An empty float32 log, as the adaptive driver creates it."""
    return write_log(path, np.zeros((0, 2), np.float32), np.zeros((0, 3), np.float32), width=W, height=H,
                     metadata={"renderer": "test"})


def _round(rng, m=10):
    return (rng.random((m, 2)) * [W, H]).astype(np.float32), rng.random((m, 3)).astype(np.float32)


def _driver_round(path, rng, r, total, m=10, *, reference=False):
    """One round as mcrecon.adaptive.run._run logs it: append with a record, then the full record
    (with ``reference``, also the error and the time to evaluate it)."""
    pos, val = _round(rng, m)
    rec = {"round": r, "samples": m, "samples_total": total + m, "renderer_seconds": float(rng.random()) * 1e-3}
    append_log(path, pos, val, round_index=r, round_record={**rec, "toolkit_seconds": 1e-4, "wall_seconds": 0.1 * r})
    rec.update(toolkit_seconds=float(rng.random()) * 1e-3, wall_seconds=0.1 * r + 0.05)
    if reference:
        rec.update(error=float(rng.random()), eval_seconds=float(rng.random()) * 1e-3)
    update_round_record(path, rec)
    return rec


def test_log_of_400_driver_rounds_is_at_most_twice_the_samples(tmp_path, rng):
    # The case: 400 rounds of 10 float32 RGB samples logged as the driver does,
    # with the larger records of a run that has a reference.  JSON records (format_minor 1)
    # made it 2.5x the sample bytes, 73 KB of it in HDF5's global heap.
    path = _empty_log(tmp_path / "grow.h5")
    per_sample = 2 * 4 + 3 * 4 + 4  # positions, values, round index
    sizes, expect = {}, []
    for r in range(400):
        expect.append(_driver_round(path, rng, r, 10 * r, reference=True))
        if r + 1 in (200, 400):
            sizes[r + 1] = os.path.getsize(path)
    # The whole log, and the growth over rounds 200..399 (no records rewritten into new space).
    assert sizes[400] <= 2 * 400 * 10 * per_sample
    assert sizes[400] - sizes[200] <= 2 * 200 * 10 * per_sample
    log = read_log(path)
    assert log.n_rounds == 400 and log.n_samples == 4000 and log.round_records == expect
    with h5py.File(path, "r") as f:  # no JSON for records that have only the driver's keys
        assert "records" not in f["run"] and "round_records_extra" not in f["run"]


def test_records_and_round_ends_after_many_appends_and_updates(tmp_path, rng):
    path = _empty_log(tmp_path / "many.h5")
    expect, total = [], 0
    for r in range(300):  # more rows than one chunk of the per-round datasets
        m = 1 + r % 7
        expect.append(_driver_round(path, rng, r, total, m))
        total += m
    log = read_log(path)
    assert log.n_samples == total and log.n_rounds == 300
    np.testing.assert_array_equal(log.round_ends, np.cumsum([1 + r % 7 for r in range(300)]))
    assert log.round_records == expect  # the updated (full) records, one per round
    assert log.format_minor == samplelog_logformat.FORMAT_MINOR
    np.testing.assert_array_equal(log.read_all(rounds=[299]).round, 299)
    with h5py.File(path, "r") as f:  # grown in place: resizable, chunked, one row per round
        for name in ("rounds/end", "run/round_records"):
            assert f[name].maxshape == (None,) and f[name].chunks is not None and f[name].shape == (300,)
        assert f["run/round_records"].dtype == samplelog_logformat.ROUND_RECORD_DTYPE
        assert "records" not in f["run"] and "round_records_extra" not in f["run"]


def test_append_reads_attributes_and_shapes_not_the_log(tmp_path, rng, monkeypatch):
    path = _empty_log(tmp_path / "light.h5")
    _driver_round(path, rng, 0, 0)

    def refuse(*a, **k):
        raise AssertionError("append built a full SampleLog")

    monkeypatch.setattr(samplelog.SampleLog, "__init__", refuse)
    for r in range(1, 4):
        _driver_round(path, rng, r, 10 * r)
    monkeypatch.undo()
    assert read_log(path).n_rounds == 4


def _crash_mid_append(path, k=7):
    """Rows of an append that was killed before its commit, in every dataset."""
    with h5py.File(path, "r+") as f:
        n = int(f.attrs["n_committed"])
        for name in ["positions", "values", "round"] + [f"features/{x}" for x in f.get("features", {})]:
            if name not in f:  # /round: only where the labels are not the rounds' indices
                continue
            d = f[name]
            d.resize(n + k, axis=0)
            d[n:] = 0.5
        e = f["rounds/end"]
        e.resize(e.shape[0] + 1, axis=0)
        e[-1] = n + k
        if "run" in f and "records" in f["run"]:
            d = f["run/records"]
            d.resize(d.shape[0] + 1, axis=0)
            d[-1] = '{"bogus": true}'
        if "run" in f and "round_records" in f["run"]:
            d = f["run/round_records"]
            d.resize(d.shape[0] + 1, axis=0)
            d[-1] = np.array([(0b111, 99, 7, n + k) + (0.5,) * 5], d.dtype)[0]  # a record with 3 keys
            x = f["run"].require_dataset("round_records_extra", shape=(0,), dtype=h5py.string_dtype(),
                                         maxshape=(None,), chunks=(256,), exact=False)
            x.resize(d.shape[0], axis=0)
            x[-1] = '{"bogus":true}'


def test_interrupted_append_is_discarded_in_every_dataset(tmp_path, rng):
    path = _empty_log(tmp_path / "crash.h5")
    depth = []
    for r in range(5):
        pos, val = _round(rng)
        depth.append(rng.random(10).astype(np.float32))
        append_log(path, pos, val, round_index=r, features={"depth": depth[-1]}, round_record={"round": r})
    _crash_mid_append(path)
    log = read_log(path)  # the partial round is invisible
    assert log.n_rounds == 5 and log.n_samples == 50 and log.round_records == [{"round": r} for r in range(5)]
    update_round_record(path, {"round": 4, "full": True})  # the last committed round's, not the partial one
    assert read_log(path).round_records[-1] == {"round": 4, "full": True}
    pos, val = _round(rng, 3)
    depth.append(np.arange(3, dtype=np.float32))
    assert append_log(path, pos, val, round_index=5, features={"depth": depth[-1]}, round_record={"round": 5}) == 53
    log = read_log(path)
    assert log.round_slices()[-2:] == [(40, 50), (50, 53)]
    assert log.round_records == [{"round": r} for r in range(4)] + [{"round": 4, "full": True}, {"round": 5}]
    np.testing.assert_array_equal(log.read_feature("depth"), np.concatenate(depth))
    np.testing.assert_array_equal(log.read_all(rounds=[5]).values, val)
    with h5py.File(path, "r") as f:  # nothing of the partial round is left
        assert {f[x].shape[0] for x in ("positions", "values", "features/depth")} == {53} and "round" not in f
        assert f["rounds/end"].shape == f["run/round_records"].shape == (6,)
        assert f["run/round_records_extra"].shape[0] <= 6  # no extra keys past round 4


def test_refused_record_leaves_the_log_unchanged(tmp_path, rng):
    path = _empty_log(tmp_path / "bad.h5")
    _driver_round(path, rng, 0, 0)
    before = _digest(path)
    with pytest.raises(InputError, match="round_record"):
        append_log(path, *_round(rng), round_record={"t": object()})
    assert _digest(path) == before


def _old_style_log(path, rng, *, rounds=(100, 20, 30), records_from=1, fixed_ends=True):
    """A log as the previous mcrecon wrote it: fixed-size /run/records holding the records
    of the rounds that had one (the first, written whole, had none), no format_minor."""
    n = sum(rounds)
    pos = (rng.random((n, 2)) * [W, H]).astype(np.float32)
    val = rng.random((n, 3)).astype(np.float32)
    ends = np.cumsum(rounds)
    with h5py.File(path, "w") as f:
        f.attrs.update(format="mcrecon-sample-log", format_version=1, width=W, height=H, metadata_json="{}")
        f.attrs["channels"] = np.array(["R", "G", "B"], dtype=h5py.string_dtype())
        f.create_dataset("positions", data=pos, maxshape=(None, 2), chunks=(1 << 16, 2))
        f.create_dataset("values", data=val, maxshape=(None, 3), chunks=(1 << 16, 3))
        f.create_dataset("round", data=np.repeat(np.arange(len(rounds)), rounds).astype(np.int32),
                         maxshape=(None,), chunks=(1 << 16,))
        if fixed_ends:
            f.create_dataset("rounds/end", data=ends.astype(np.int64))
        else:
            f.create_dataset("rounds/end", data=ends.astype(np.int64), maxshape=(None,), chunks=(256,))
        recs = [json.dumps({"round": r}) for r in range(records_from, len(rounds))]
        f.create_dataset("run/records", data=np.array(recs, dtype=h5py.string_dtype()))
        f["run"].attrs["settings_json"] = json.dumps({"method": "box"})
        f.attrs["n_committed"] = n
    return pos, val


@pytest.mark.parametrize("fixed_ends", [True, False])
def test_old_style_log_reads_and_appends(tmp_path, rng, fixed_ends):
    path = tmp_path / "old.h5"
    pos, val = _old_style_log(path, rng, fixed_ends=fixed_ends)
    log = read_log(path)
    assert log.format_minor == 0 and log.n_rounds == 3 and log.round_records == [{"round": 1}, {"round": 2}]
    p2, v2 = _round(rng, 5)
    assert append_log(path, p2, v2, round_record={"round": 3}) == 155
    update_round_record(path, {"round": 3, "full": True})
    append_log(path, *_round(rng, 4), round_record={"round": 4})
    log = read_log(path)
    assert log.round_slices() == [(0, 100), (100, 120), (120, 150), (150, 155), (155, 159)]
    assert log.round_records == [{"round": 1}, {"round": 2}, {"round": 3, "full": True}, {"round": 4}]
    assert log.run_settings == {"method": "box"} and log.format_minor == 1  # continued in the JSON layout
    data = log.read_all()
    np.testing.assert_array_equal(data.positions[:150], pos)
    np.testing.assert_array_equal(data.values[150:155], v2)
    with h5py.File(path, "r") as f:  # converted once into resizable datasets, aligned with the rounds
        for name in ("rounds/end", "run/records"):
            assert f[name].maxshape == (None,) and f[name].shape == (5,)
        assert f["run/records"][0] in (b"null", "null") and "_convert" not in f
        assert "round_records" not in f["run"]


def test_foreign_fixed_size_log_appends(tmp_path, rng):
    # Another writer's log: contiguous datasets, no /round, /rounds/end, n_committed or /run.
    n = 40
    pos = rng.random((n, 2)) * [W, H]
    val = rng.random((n, 3))
    depth = rng.random(n)
    path = tmp_path / "foreign.h5"
    with h5py.File(path, "w") as f:
        f.attrs.update(format_version=1, width=W, height=H, channels=["R", "G", "B"])
        f["positions"], f["values"], f["features/depth"] = pos, val, depth
    assert read_log(path).n_rounds == 1
    p2, v2 = _round(rng, 6)
    assert append_log(path, p2, v2, features={"depth": np.ones(6)}, round_record={"round": 1}) == 46
    append_log(path, *_round(rng, 2), features={"depth": np.zeros(2)})
    log = read_log(path)
    assert log.round_slices() == [(0, 40), (40, 46), (46, 48)] and log.round_records == [{"round": 1}]
    data = log.read_all()
    np.testing.assert_array_equal(data.positions[:n], pos)
    np.testing.assert_array_equal(data.round, [0] * 40 + [1] * 6 + [2] * 2)
    np.testing.assert_array_equal(log.read_feature("depth"), np.concatenate([depth, np.ones(6), np.zeros(2)]))


# ---------------------------------------------------------------- round records (format_minor 2)
def _same(a, b):
    """Equal as JSON values and of the same types, floats bit for bit (repr: -0.0, nan, inf)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return list(a) == list(b) and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return type(a) is type(b) and repr(a) == repr(b)


def _json_round_trip(rec):
    """What the JSON layout returned for ``rec``: keys sorted, numpy scalars as Python numbers."""
    return json.loads(json.dumps(rec, sort_keys=True, default=lambda o: o.item()))


DRIVER = {"round": 0, "samples": 10, "samples_total": 10, "renderer_seconds": 1e-3, "toolkit_seconds": 0.1 + 0.2,
          "wall_seconds": 1 / 3}
ODD_RECORDS = [
    {**DRIVER, "round": 1, "error": 0.12345678901234568, "eval_seconds": 5e-324},  # with the optional keys
    {"round": 2},  # most keys absent
    {**DRIVER, "round": 3, "note": "resumed", "error": float("nan"), "eval_seconds": -0.0},  # an extra key
    {"round": 4, "samples": np.int64(2**62), "samples_total": 2**64, "error": float("inf"),
     "wall_seconds": np.float32(0.1), "toolkit_seconds": 7, "renderer_seconds": True},  # types off the columns
    {},  # an empty record is still a record
    {"round": 6.0, "samples": None, "nested": {"a": [1, 2.5]}, "1": 1},
]


def test_round_records_round_trip_exactly(tmp_path, rng):
    path = _empty_log(tmp_path / "rec.h5")
    append_log(path, *_round(rng), round_record=DRIVER)
    written = [DRIVER]
    for r, rec in enumerate(ODD_RECORDS, start=1):
        append_log(path, *_round(rng), round_record=rec)
        written.append(rec)
        if r == 3:
            append_log(path, *_round(rng))  # a round without record
    log = read_log(path)
    assert log.n_rounds == len(written) + 1 and log.format_minor == 2
    expect = [_json_round_trip(r) for r in written]
    assert all(_same(a, b) for a, b in zip(log.round_records, expect)) and len(log.round_records) == len(expect)
    got = log.round_records[4]  # ints stay ints (2**64 beyond int64), a bool stays a bool, an int in a float column
    assert got["samples_total"] == 2**64 and got["renderer_seconds"] is True and type(got["toolkit_seconds"]) is int
    assert got["wall_seconds"] == float(np.float32(0.1))
    with h5py.File(path, "r") as f:
        rows = f["run/round_records"][...]
        extra = [x.decode() if isinstance(x, bytes) else x for x in f["run/round_records_extra"][...]]
    assert rows.shape == (len(written) + 1,) and rows["present"][4] == 0 and rows["round"][4] == -1  # no record
    assert rows["round"][:4].tolist() == [0, 1, 2, 3] and np.isnan(rows["error"][2])
    assert rows["present"][3] & 1 << 8 and np.isnan(rows["error"][3])  # NaN present, not absent
    # Only records with keys outside the columns have JSON; no empty strings written for the others.
    assert [bool(x) for x in extra] == [False] * 3 + [True, False, True, False, True]
    assert json.loads(extra[3]) == {"note": "resumed"}


def test_update_rewrites_only_the_last_record(tmp_path, rng):
    path = _empty_log(tmp_path / "upd.h5")
    for r in range(70):  # rows in two chunks
        _driver_round(path, rng, r, 10 * r)
    with h5py.File(path, "r") as f:
        before = f["run/round_records"][...]
    full = {**DRIVER, "round": 69, "error": 0.5, "eval_seconds": 0.25}
    for rec in (full, {**full, "note": "x"}, {"round": 69}, full):  # add and drop optional and extra keys
        update_round_record(path, rec)
        assert _same(read_log(path).round_records[-1], _json_round_trip(rec))
    with h5py.File(path, "r") as f:
        after = f["run/round_records"][...]
        extra = f["run/round_records_extra"]
        assert extra.shape[0] <= 70 and not any(extra[...][:69])
    assert after.shape == (70,) and after[:69].tobytes() == before[:69].tobytes()


def test_interrupted_append_in_the_record_rows_is_discarded(tmp_path, rng):
    path = _empty_log(tmp_path / "crash2.h5")
    recs = [_driver_round(path, rng, r, 10 * r) for r in range(3)]
    _crash_mid_append(path)  # a row with a record (and extra keys) past the committed rounds
    assert read_log(path).round_records == recs
    update_round_record(path, {**recs[-1], "wall_seconds": 9.0})
    recs[-1] = {**recs[-1], "wall_seconds": 9.0}
    assert read_log(path).round_records == recs
    append_log(path, *_round(rng), round_index=3)  # no record: the crashed row must not show through
    log = read_log(path)
    assert log.n_rounds == 4 and log.round_records == recs
    with h5py.File(path, "r") as f:
        assert f["run/round_records"].shape == (4,) and f["run/round_records"]["present"][3] == 0
        assert f["run/round_records_extra"].shape[0] <= 3
    append_log(path, *_round(rng), round_index=4, round_record={"round": 4, "k": 1})
    assert read_log(path).round_records == recs + [{"k": 1, "round": 4}]


def _minor1_log(path, rng, records):
    """A log as format_minor 1 wrote it: resizable /run/records of JSON strings, null for no record."""
    n = 10 * len(records)
    with h5py.File(path, "w") as f:
        f.attrs.update(format="mcrecon-sample-log", format_version=1, format_minor=1, width=W, height=H,
                       metadata_json="{}")
        f.attrs["channels"] = np.array(["R", "G", "B"], dtype=h5py.string_dtype())
        f.create_dataset("positions", data=(rng.random((n, 2)) * [W, H]).astype(np.float32), maxshape=(None, 2),
                         chunks=(4096, 2))
        f.create_dataset("values", data=rng.random((n, 3)).astype(np.float32), maxshape=(None, 3), chunks=(4096, 3))
        f.create_dataset("round", data=np.repeat(np.arange(len(records)), 10).astype(np.int32), maxshape=(None,),
                         chunks=(4096,))
        f.create_dataset("rounds/end", data=np.arange(10, n + 1, 10, dtype=np.int64), maxshape=(None,),
                         chunks=(256,))
        rows = [json.dumps(r, sort_keys=True, separators=(",", ":")) for r in records]
        d = f.create_dataset("run/records", shape=(len(rows),), dtype=h5py.string_dtype("utf-8"), maxshape=(None,),
                             chunks=(256,))
        d[...] = rows
        f["run"].attrs["settings_json"] = json.dumps({"method": "box"})
        f.attrs["n_committed"] = np.int64(n)


def test_minor1_json_records_read_and_are_continued_in_their_layout(tmp_path, rng):
    path = tmp_path / "m1.h5"
    old = [{**DRIVER, "round": 0}, None, {**DRIVER, "round": 2, "error": 0.25, "note": "x"}]
    _minor1_log(path, rng, old)
    log = read_log(path)
    assert log.format_minor == 1 and log.n_rounds == 3 and log.round_records == [old[0], old[2]]
    append_log(path, *_round(rng), round_record={**DRIVER, "round": 3})
    update_round_record(path, {**DRIVER, "round": 3, "wall_seconds": 2.0})
    append_log(path, *_round(rng, 4))  # a round without record
    append_log(path, *_round(rng, 2), round_record={"round": 5})
    log = read_log(path)
    assert log.n_rounds == 6 and log.round_slices()[-3:] == [(30, 40), (40, 44), (44, 46)]
    assert log.round_records == [old[0], old[2], {**DRIVER, "round": 3, "wall_seconds": 2.0}, {"round": 5}]
    assert log.format_minor == 1
    with h5py.File(path, "r") as f:  # still the JSON layout, one row per round: older mcrecon reads it
        assert "round_records" not in f["run"] and f["run/records"].shape == (6,)
        assert f["run/records"][4] in (b"null", "null")


def test_rounds_an_older_mcrecon_appended_to_a_minor2_log(tmp_path, rng):
    # An mcrecon before format_minor 2 resuming a newer log adds /run/records beside
    # /run/round_records, aligned with the rounds (null for none): both are read.
    path = _empty_log(tmp_path / "mixed.h5")
    for r in range(2):
        append_log(path, *_round(rng), round_record={"round": r})
    append_log(path, *_round(rng))  # round 2: its row in /run/round_records has no record
    with h5py.File(path, "r+") as f:
        f["run"].create_dataset("records", data=np.array(["null", "null", '{"old":true,"round":2}'],
                                                         dtype=h5py.string_dtype("utf-8")), maxshape=(None,))
    assert read_log(path).round_records == [{"round": 0}, {"round": 1}, {"old": True, "round": 2}]
    append_log(path, *_round(rng), round_record={"round": 3})
    update_round_record(path, {"round": 3, "t": 1.5})
    log = read_log(path)
    assert log.round_records == [{"round": 0}, {"round": 1}, {"old": True, "round": 2}, {"round": 3, "t": 1.5}]
    with h5py.File(path, "r") as f:
        assert f["run/round_records"].shape == (4,) and f["run/records"].shape == (3,)


def test_other_writers_compound_records(tmp_path, rng):
    # Another writer's fixed-size compound rows: own column order and types, an unknown column.
    path = _empty_log(tmp_path / "foreign_rec.h5")
    for r in range(2):
        append_log(path, *_round(rng), round_index=r)
    dt = np.dtype([("wall_seconds", "<f4"), ("present", "u1"), ("round", "<i4"), ("gpu_seconds", "<f8")])
    with h5py.File(path, "r+") as f:
        f.require_group("run")["round_records"] = np.array([(0.5, 0b11, 0, 0.0), (0.25, 0b1111, 1, 3.0)], dt)
    log = read_log(path)
    assert log.round_records == [{"wall_seconds": 0.5}, {"wall_seconds": 0.25, "round": 1, "gpu_seconds": 3.0}]
    append_log(path, *_round(rng), round_index=2, round_record={"round": 2, "wall_seconds": 0.1, "gpu_seconds": 1.5})
    rec = read_log(path).round_records[-1]  # 0.1 is not a float32: kept exactly in the JSON of the extra keys
    assert _same(rec, {"gpu_seconds": 1.5, "round": 2, "wall_seconds": 0.1})
    with h5py.File(path, "r") as f:
        d = f["run/round_records"]
        assert d.dtype == dt and d.maxshape == (None,) and d.shape == (3,) and d["present"][2] == 0b1101  # record, round, gpu_seconds


def test_malformed_round_records_are_refused(tmp_path, rng):
    path = _empty_log(tmp_path / "badrec.h5")
    append_log(path, *_round(rng), round_record={"round": 0})
    with h5py.File(path, "r+") as f:
        del f["run/round_records"]
        f["run/round_records"] = np.zeros(1, [("round", "<i8")])  # no 'present'
    with pytest.raises(InputError, match="/run/round_records"):
        read_log(path)
    before = _digest(path)
    with pytest.raises(InputError, match="/run/round_records"):
        append_log(path, *_round(rng), round_record={"round": 1})
    assert _digest(path) == before


def test_conversion_interrupted_by_a_crash_is_recovered(tmp_path, rng):
    path = tmp_path / "conv.h5"
    _old_style_log(path, rng)
    with h5py.File(path, "r+") as f:  # killed while copying /run/records: a partial copy, original intact
        f.create_dataset("_convert/run/records", data=np.array(["partial"], dtype=h5py.string_dtype()))
    append_log(path, *_round(rng, 5), round_record={"round": 3})
    assert read_log(path).round_records == [{"round": r} for r in range(1, 4)]
    with h5py.File(path, "r+") as f:  # killed between unlinking the original and linking the copy
        f.create_dataset("_convert/rounds/end", data=f["rounds/end"][...], maxshape=(None,), chunks=(256,))
        del f["rounds/end"]
    append_log(path, *_round(rng, 2), round_record={"round": 4})
    log = read_log(path)
    assert log.round_slices()[-3:] == [(120, 150), (150, 155), (155, 157)]
    assert log.round_records == [{"round": r} for r in range(1, 5)]
    with h5py.File(path, "r") as f:
        assert "_convert" not in f


def test_reading_never_modifies(tmp_path, rng):
    path, *_ = _log(tmp_path, rng)
    before = (_digest(path), os.stat(path).st_mtime_ns)
    log = read_log(path)
    log.read_all()
    PixelStats.from_log(log)
    log.reference()
    assert (_digest(path), os.stat(path).st_mtime_ns) == before


def test_not_hdf5_and_truncated(tmp_path, rng):
    bad = tmp_path / "text.h5"
    bad.write_text("hello")
    with pytest.raises(InputError, match="text.h5: file: not a readable HDF5"):
        read_log(bad)
    path, *_ = _log(tmp_path, rng, n=200_000)
    data = open(path, "rb").read()
    cut = tmp_path / "cut.h5"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="cut.h5"):
        log = read_log(cut)
        log.read_all()
    with pytest.raises(InputError, match="does not exist"):
        read_log(tmp_path / "missing.h5")


@pytest.mark.parametrize("breakage, match", [
    (lambda f: f.attrs.__delitem__("format_version"), "format_version"),
    (lambda f: f.attrs.__setitem__("format_version", 7), "version 1"),
    (lambda f: f.__delitem__("values"), "/values: missing"),
    (lambda f: (f.__delitem__("values"), f.create_dataset("values", data=np.zeros((500, 2), np.float32))),
     "expected \\(N, 3\\)"),
    (lambda f: (f.__delitem__("positions"), f.create_dataset("positions", data=np.zeros((500, 2), np.int32))),
     "dtype int32"),
    (lambda f: f.attrs.__setitem__("n_committed", 10**6), "truncated"),
    (lambda f: f.attrs.__setitem__("width", 0), "width/height"),
    (lambda f: f.create_dataset("reference", data=np.zeros((2, 2, 3))), "reference"),
])
def test_malformed_logs(tmp_path, rng, breakage, match):
    path, *_ = _log(tmp_path, rng)
    with h5py.File(path, "r+") as f:
        breakage(f)
    with pytest.raises(InputError, match=match):
        read_log(path)


def test_positions_off_film_in_file_are_reported(tmp_path, rng):
    path, *_ = _log(tmp_path, rng)
    with h5py.File(path, "r+") as f:
        f["positions"][3] = [100.0, 1.0]
    with pytest.raises(InputError, match="a.h5: positions: 1 sample\\(s\\) off the film"):
        PixelStats.from_log(read_log(path))


def test_write_log_validation_and_atomicity(tmp_path, rng):
    with pytest.raises(InputError, match="off the film"):
        write_log(tmp_path / "x.h5", np.array([[1.0, 7.0]]), np.ones((1, 3)), width=9, height=7)
    with pytest.raises(InputError, match="rounds"):
        write_log(tmp_path / "x.h5", np.zeros((2, 2)), np.ones((2, 3)), width=1, height=1, rounds=[1, 0])
    with pytest.raises(InputError, match="metadata"):
        write_log(tmp_path / "x.h5", np.zeros((2, 2)), np.ones((2, 3)), width=1, height=1, metadata={"a": object()})
    assert list(tmp_path.iterdir()) == []  # nothing half-written left behind


def test_one_by_one_and_float64_values(tmp_path):
    path = write_log(tmp_path / "one.h5", np.array([[0.25, 0.75]]), np.array([[1e6 + 1e-3]]), width=1, height=1,
                     channels=["Y"])
    log = read_log(path)
    assert log.value_dtype == np.float64 and log.read_all().values[0, 0] == 1e6 + 1e-3


def test_cast_positions_never_leaves_the_pixel():
    x = np.array([[np.nextafter(128.0, 0), 0.5], [3.2, 0.99999999999]])
    out = cast_positions(x, np.float32)
    assert out.dtype == np.float32 and (np.floor(out) == np.floor(x)).all()


@pytest.mark.parametrize("shape, channels", [((5, 7, 3), ("R", "G", "B")), ((333, 517, 5), ("Z", "R", "G", "B", "d")),
                                             ((1, 1, 1), ("Y",))])
def test_exr_round_trip(tmp_path, rng, shape, channels):
    img = (rng.standard_normal(shape) * 1e3).astype(np.float32)
    img.flat[0] = 65504.0 * 10  # beyond half-float range: must survive as float32
    write_exr(tmp_path / "i.exr", img, channels=channels)
    back, names = read_exr(tmp_path / "i.exr")
    assert names == channels
    np.testing.assert_array_equal(back, img)


def test_png_preview_and_false_colour(tmp_path, rng):
    from PIL import Image

    img = rng.random((6, 8, 3)) * 100
    write_png_preview(tmp_path / "p.png", img, exposure=-3)
    a = np.asarray(Image.open(tmp_path / "p.png"))
    assert a.shape == (6, 8, 3) and a.dtype == np.uint8
    m = np.arange(12.0).reshape(3, 4)
    m[0, 0] = np.nan
    write_false_colour(tmp_path / "m.png", m)
    b = np.asarray(Image.open(tmp_path / "m.png"))
    assert b.shape == (3, 4, 3) and (b[0, 0] == 0).all() and not (b[2, 3] == b[0, 1]).all()
    with pytest.raises(InputError, match="not an OpenEXR file"):
        read_exr(tmp_path / "p.png")


# ------------------------------------------------------------------ found in review (each failed before its fix)
@pytest.mark.parametrize("breakage, match", [
    (lambda f: (f.__delitem__("positions"), f.create_dataset("positions", data=np.zeros((4, 2), np.float16))),
     "dtype float16"),
    (lambda f: f.attrs.__setitem__("format_version", "one"), "expected the integer 1"),
    (lambda f: f.attrs.__setitem__("n_committed", "x"), "expected an integer"),
    (lambda f: f.require_group("run").attrs.__setitem__("settings_json", "{bad"), "not valid JSON"),
    (lambda f: f.attrs.__setitem__("metadata_json", "[1, 2]"), "expected a JSON object"),
])
def test_malformed_attributes_give_one_line_errors(tmp_path, breakage, match):
    path = write_log(tmp_path / "m.h5", np.full((4, 2), 0.5), np.ones((4, 3)), width=2, height=2)
    with h5py.File(path, "r+") as f:
        breakage(f)
    with pytest.raises(InputError, match=match):
        read_log(path)


def test_written_files_get_the_umask_permissions(tmp_path):
    umask = os.umask(0)
    os.umask(umask)
    expect = 0o666 & ~umask
    log = write_log(tmp_path / "p.h5", np.full((1, 2), 0.5), np.ones((1, 3)), width=1, height=1)
    exr = write_exr(tmp_path / "p.exr", np.ones((2, 2, 3)))
    for p in (log, exr):
        assert stat.S_IMODE(os.stat(p).st_mode) == expect


def test_an_unwritten_round_end_of_a_full_disk_is_not_a_round(tmp_path):
    """A disk that filled during an append left /rounds/end = [.., n, 0] (the row's shape reached the
    disk, its value did not): the log must still open with its committed rounds and take appends."""
    path = write_log(tmp_path / "f.h5", np.full((4, 2), 0.5), np.ones((4, 3)), width=1, height=1,
                     rounds=np.array([0, 0, 1, 1]))
    with h5py.File(path, "r+") as f:
        d = f["rounds/end"]
        d.resize(3, axis=0)
        d[2] = 0
    log = read_log(path)
    assert log.n_rounds == 2 and log.round_slices() == [(0, 2), (2, 4)]
    append_log(path, np.full((2, 2), 0.5), np.ones((2, 3)))
    assert read_log(path).round_slices() == [(0, 2), (2, 4), (4, 6)]


def _datasets(path):
    """Every dataset's contents and every attribute of a log, by name."""
    out = {}
    with h5py.File(path, "r") as f:
        def visit(name, obj):
            out[name + "/@"] = {k: np.asarray(v).tolist() for k, v in obj.attrs.items()}
            if isinstance(obj, h5py.Dataset):  # bytes: NaN fields compare equal, unlike floats
                a = obj[()]
                out[name] = a.tolist() if a.dtype.kind == "O" else (a.dtype.str, a.shape, a.tobytes())
        f.visititems(visit)
        out["/@"] = {k: np.asarray(v).tolist() for k, v in f.attrs.items()}
    return out


def test_append_checked_writes_the_same_log_and_the_default_still_validates(tmp_path, rng):
    """``checked=True`` (the driver, for replies it validated) skips the per-sample scan only: the
    file's datasets and attributes are the same as with the default, which still refuses bad rows."""
    paths = []
    for name in ("default", "checked"):
        p = write_log(tmp_path / f"{name}.h5", np.zeros((0, 2)), np.zeros((0, 3), np.float32), width=9, height=7)
        paths.append(p)
    rounds = [(np.ascontiguousarray(rng.random((n, 2)) * [9, 7]), rng.random((n, 3)).astype(np.float32))
              for n in (50, 1, 300)]
    for k, (pos, val) in enumerate(rounds):
        rec = {"round": k, "samples": len(pos), "toolkit_seconds": 0.5}
        assert append_log(paths[0], pos, val, round_index=k, round_record=rec) == \
            append_log(paths[1], pos, val, round_index=k, round_record=rec, checked=True)
    assert _datasets(paths[0]) == _datasets(paths[1])
    off = np.array([[9.5, 1.0]])  # off the film
    with pytest.raises(InputError, match="off the film"):
        append_log(paths[0], off, np.ones((1, 3)))
    # arrays that cannot come from the validation (not contiguous) get the full check anyway
    with pytest.raises(InputError, match="off the film"):
        append_log(paths[1], np.asfortranarray(np.repeat(off, 2, axis=0)), np.ones((2, 3)), checked=True)
    assert read_log(paths[0]).n_samples == read_log(paths[1]).n_samples == 351

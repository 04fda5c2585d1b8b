"""Sample logs (format v1) and images: round trips, appends, bad files."""

import hashlib
import json
import os

import h5py
import numpy as np
import pytest

from mcrecon import InputError, PixelStats
from mcrecon.io import append_log, read_exr, read_log, write_exr, write_false_colour, write_log, write_png_preview
from mcrecon.io import samplelog
from mcrecon.io.samplelog import APPEND_CHUNK_ROWS, cast_positions, update_round_record


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


def _driver_round(path, rng, r, total, m=10):
    """One round as mcrecon.driver._run logs it: append with a record, then the full record."""
    pos, val = _round(rng, m)
    rec = {"round": r, "samples": m, "samples_total": total + m, "renderer_seconds": float(rng.random()) * 1e-3}
    append_log(path, pos, val, round_index=r, round_record={**rec, "toolkit_seconds": 1e-4, "wall_seconds": 0.1 * r})
    rec.update(toolkit_seconds=float(rng.random()) * 1e-3, wall_seconds=0.1 * r + 0.05)
    update_round_record(path, rec)
    return rec


def _stored_record_bytes(path):
    with h5py.File(path, "r") as f:
        return sum(len(x) for x in f["run/records"][...])


def test_log_size_grows_with_the_data_not_with_the_rounds(tmp_path, rng):
    # 200 rounds of 10 float32 RGB samples, logged as the driver does.  The previous
    # layout recreated /rounds/end and /run/records every round (HDF5 never reclaims
    # that space): ~100 KB per round here.
    path = _empty_log(tmp_path / "grow.h5")
    per_sample = 2 * 4 + 3 * 4 + 4  # positions, values, round index
    sizes, rec_bytes = {}, {}
    for r in range(200):
        _driver_round(path, rng, r, 10 * r)
        if r + 1 in (100, 200):
            sizes[r + 1], rec_bytes[r + 1] = os.path.getsize(path), _stored_record_bytes(path)
    data = {k: 10 * k * per_sample + rec_bytes[k] for k in sizes}
    # Appending rounds 100..199 costs at most twice their bytes (samples + JSON records).
    assert sizes[200] - sizes[100] <= 2 * (data[200] - data[100])
    # The whole log: twice the data, plus one partly filled chunk per sample dataset
    # (HDF5 allocates chunks whole) and a fixed allowance for the HDF5 metadata.
    assert sizes[200] <= 2 * data[200] + APPEND_CHUNK_ROWS * per_sample + 64 * 1024
    log = read_log(path)
    assert log.n_rounds == 200 and log.n_samples == 2000 and len(log.round_records) == 200


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
    assert log.format_minor == samplelog.FORMAT_MINOR
    np.testing.assert_array_equal(log.read_all(rounds=[299]).round, 299)
    with h5py.File(path, "r") as f:  # grown in place: resizable, chunked, one row per round
        for name in ("rounds/end", "run/records"):
            assert f[name].maxshape == (None,) and f[name].chunks is not None and f[name].shape == (300,)
        assert h5py.check_string_dtype(f["run/records"].dtype).encoding == "utf-8"


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
        assert {f[x].shape[0] for x in ("positions", "values", "round", "features/depth")} == {53}
        assert f["rounds/end"].shape == f["run/records"].shape == (6,)


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
    assert log.run_settings == {"method": "box"} and log.format_minor == samplelog.FORMAT_MINOR
    data = log.read_all()
    np.testing.assert_array_equal(data.positions[:150], pos)
    np.testing.assert_array_equal(data.values[150:155], v2)
    with h5py.File(path, "r") as f:  # converted once into resizable datasets, aligned with the rounds
        for name in ("rounds/end", "run/records"):
            assert f[name].maxshape == (None,) and f[name].shape == (5,)
        assert f["run/records"][0] in (b"null", "null") and "_convert" not in f


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
        PixelStats.from_log(path)


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
    with pytest.raises(InputError, match="not a readable EXR"):
        read_exr(tmp_path / "p.png")

"""Sample logs (format v1) and images: round trips, appends, bad files."""

import hashlib
import os

import h5py
import numpy as np
import pytest

from mcrecon import InputError, PixelStats
from mcrecon.io import append_log, read_exr, read_log, write_exr, write_false_colour, write_log, write_png_preview
from mcrecon.io.samplelog import cast_positions


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

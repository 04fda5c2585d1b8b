"""Boundary inputs found in review that the other boundary tests do not cover.

Each test failed before its fix: attributes of the wrong type read as
integers, memory bombs (a film or a sample budget this machine cannot hold)
ending in a traceback or an OOM kill, a log's non-finite reference refused
after the work with a message naming neither the file nor the dataset, a
negative /rounds/end read as rows, a non-finite preview exposure, a
half-buffer pair made of one file twice.
"""

import h5py
import numpy as np
import pytest

import mcrecon.samples
from mcrecon import InputError
from mcrecon.cli import main
from mcrecon.io import read_log, write_exr, write_log


def _cli(argv, capsys):
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def _one_line(code, err, match):
    assert code == 2, err
    assert err.count("\n") == 1 and err.startswith("mcrecon: error: ") and "Traceback" not in err, err
    assert match in err, err


def _log(tmp_path, name="b.h5", w=8, h=6, n=200, **kw):
    rng = np.random.default_rng(0)
    return write_log(tmp_path / name, rng.random((n, 2)) * [w, h], rng.random((n, 3)).astype(np.float32),
                     width=w, height=h, **kw)


# ------------------------------------------------------------------ integer attributes
@pytest.mark.parametrize("key, value, match", [
    ("width", 8.5, "attribute width/height"),
    ("width", 8.0, "attribute width/height"),
    ("height", "6", "attribute width/height"),
    ("width", True, "attribute width/height"),
    ("n_committed", 100.5, "attribute n_committed"),
    ("format_minor", 2.5, "attribute format_minor"),
    ("format_version", 1.0, "attribute format_version"),
])
def test_integer_attributes_of_another_type_are_refused(tmp_path, capsys, key, value, match):
    """int(8.5) == 8 and int("6") == 6 read a wrong header as a valid one; the format says integers."""
    path = _log(tmp_path)
    with h5py.File(path, "r+") as f:
        f.attrs[key] = value
    with pytest.raises(InputError, match=match):
        read_log(path)
    code, _, err = _cli(["info", path], capsys)
    _one_line(code, err, match)


def test_integer_attributes_of_any_integer_type_still_read(tmp_path):
    path = _log(tmp_path)
    with h5py.File(path, "r+") as f:
        f.attrs["width"], f.attrs["height"] = np.uint8(8), np.array([6], np.int16)
        f.attrs["n_committed"] = np.uint64(150)
    log = read_log(path)
    assert (log.width, log.height, log.n_samples) == (8, 6, 150)


# ------------------------------------------------------------------ /rounds/end
def test_a_negative_round_end_is_named_not_read_as_rows(tmp_path, capsys):
    path = _log(tmp_path, rounds=np.repeat([0, 1], 100))
    with h5py.File(path, "r+") as f:
        f["rounds/end"][0] = -5
    code, _, err = _cli(["info", path], capsys)
    _one_line(code, err, "dataset /rounds/end")
    assert "rows -5" not in err and "-5" in err

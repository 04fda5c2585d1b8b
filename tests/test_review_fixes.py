"""Regression tests for defects found in review (each failed before its fix)."""

import os
import stat

import h5py
import numpy as np
import pytest

from mcrecon import InputError
from mcrecon.io import read_log, write_exr, write_log


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

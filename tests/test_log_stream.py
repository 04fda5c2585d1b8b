"""A log written piece by piece: published only complete, pieces checked like a whole log."""

import numpy as np
import pytest

from mcrecon.errors import InputError
from mcrecon.io import read_log, write_log
from mcrecon.io.log_stream import stream_log


def _samples(n, w=6, h=4, seed=0):
    rng = np.random.default_rng(seed)
    pix = np.repeat(np.arange(w * h), n // (w * h))
    pos = np.stack([pix % w + rng.random(pix.size), pix // w + rng.random(pix.size)], 1)
    return pos, rng.random((pix.size, 3)).astype(np.float32), rng.random((pix.size, 3)).astype(np.float32)


def test_pieces_read_back_as_the_whole_write(tmp_path):
    pos, val, alb = _samples(96)
    write_log(tmp_path / "whole.h5", pos.astype(np.float32), val, width=6, height=4, features={"albedo": alb})
    with stream_log(tmp_path / "parts.h5", 96, width=6, height=4, features={"albedo": ((3,), np.float32)}) as out:
        for a in range(0, 96, 25):
            out.write(pos[a:a + 25], val[a:a + 25], features={"albedo": alb[a:a + 25]})
    x, y = read_log(tmp_path / "whole.h5").read_all(features=["albedo"]), \
        read_log(tmp_path / "parts.h5").read_all(features=["albedo"])
    for u, v in ((x.positions, y.positions), (x.values, y.values), (x.features["albedo"], y.features["albedo"])):
        assert u.dtype == v.dtype and np.array_equal(u, v)


def test_an_incomplete_or_refused_stream_leaves_no_file(tmp_path):
    pos, val, alb = _samples(48)
    path = tmp_path / "s.h5"
    with pytest.raises(InputError, match="rows"):
        with stream_log(path, 48, width=6, height=4) as out:
            out.write(pos[:20], val[:20])
    assert not path.exists()
    with pytest.raises(InputError, match="positions"):
        with stream_log(path, 48, width=6, height=4) as out:
            out.write(pos + [0, 10], val)   # off the film
    assert not path.exists()
    with pytest.raises(InputError, match="features"):
        with stream_log(path, 48, width=6, height=4, features={"albedo": ((3,), np.float32)}) as out:
            out.write(pos, val)
    assert not path.exists()
    with pytest.raises(InputError, match="beyond the 48"):
        with stream_log(path, 48, width=6, height=4) as out:
            out.write(pos, val)
            out.write(pos[:1], val[:1])
    assert not path.exists()

"""The per-sample round label (/round) is written only where /rounds/end does not already give it.

Labels 0, 1, 2, ... are each round's index, which readers derive from /rounds/end; logs that carry
/round (older mcrecon, other writers, labels with gaps) are still read and appended to.
"""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from mcrecon.errors import InputError
from mcrecon.io import append_log, read_log, write_log

W, H = 8, 4


def _round(rng, n=12):
    return (rng.random((n, 2)) * [W, H]).astype(np.float32), rng.random((n, 3)).astype(np.float32)


def _sizes(path):
    with h5py.File(path, "r") as f:
        return {k: f[k].id.get_storage_size() for k in ("positions", "values", "round") if k in f}


def test_a_written_log_has_no_per_sample_round_and_reads_its_rounds(tmp_path, rng):
    pos, val = _round(rng, 30)
    rounds = np.repeat([0, 1, 2], 10)
    path = write_log(tmp_path / "w.h5", pos, val, width=W, height=H, rounds=rounds)
    with h5py.File(path, "r") as f:
        assert "round" not in f and f["rounds/end"][...].tolist() == [10, 20, 30]
    log = read_log(path)
    assert log.round_slices() == [(0, 10), (10, 20), (20, 30)]
    np.testing.assert_array_equal(log.read_all().round, rounds)
    np.testing.assert_array_equal(log.read_all(rounds=[1]).values, val[10:20])


def test_appended_rounds_write_no_per_sample_round(tmp_path, rng):
    path = write_log(tmp_path / "a.h5", np.zeros((0, 2), np.float32), np.zeros((0, 3), np.float32), width=W, height=H)
    parts = [_round(rng, n) for n in (5, 7, 9)]
    for r, (p, v) in enumerate(parts):
        append_log(path, p, v, round_index=r, round_record={"round": r})
    with h5py.File(path, "r") as f:
        assert "round" not in f
    log = read_log(path)
    assert log.round_slices() == [(0, 5), (5, 12), (12, 21)] and log.round_records == [{"round": r} for r in range(3)]
    np.testing.assert_array_equal(log.read_all().round, np.repeat([0, 1, 2], [5, 7, 9]))
    # the default label of the next round is the next index, still without /round
    append_log(path, *_round(rng, 3))
    with h5py.File(path, "r") as f:
        assert "round" not in f
    assert read_log(path).read_all().round[-3:].tolist() == [3, 3, 3]


def test_an_old_log_with_per_sample_rounds_is_read_and_appended_to(tmp_path, rng):
    """A log as mcrecon wrote it before (/round beside /rounds/end) keeps its /round growing with the rows."""
    pos, val = _round(rng, 20)
    path = tmp_path / "old.h5"
    write_log(path, pos, val, width=W, height=H, rounds=np.repeat([0, 1], 10))
    with h5py.File(path, "r+") as f:  # the per-sample labels an older writer stored
        f.create_dataset("round", data=np.repeat([0, 1], 10).astype(np.int32), maxshape=(None,), chunks=(4096,),
                         fletcher32=True)
    assert read_log(path).round_slices() == [(0, 10), (10, 20)]
    p2, v2 = _round(rng, 6)
    assert append_log(path, p2, v2) == 26
    with h5py.File(path, "r") as f:
        assert f["round"][...].tolist() == [0] * 10 + [1] * 10 + [2] * 6
    log = read_log(path)
    assert log.round_slices() == [(0, 10), (10, 20), (20, 26)]
    np.testing.assert_array_equal(log.read_all(rounds=[2]).positions, p2)


def test_labels_that_are_not_indices_are_kept(tmp_path, rng):
    pos, val = _round(rng, 20)
    path = write_log(tmp_path / "g.h5", pos, val, width=W, height=H, rounds=np.repeat([0, 5], 10))
    assert read_log(path).read_all().round.tolist() == [0] * 10 + [5] * 10
    # a gap in an appended label: /round is created then, the earlier rounds labelled by their indices
    path = write_log(tmp_path / "h.h5", pos, val, width=W, height=H, rounds=np.repeat([0, 1], 10))
    append_log(path, *_round(rng, 4), round_index=7)
    log = read_log(path)
    assert log.round_slices() == [(0, 10), (10, 20), (20, 24)]
    assert log.read_all().round.tolist() == [0] * 10 + [1] * 10 + [7] * 4


def test_a_label_below_the_committed_rounds_is_refused(tmp_path, rng):
    pos, val = _round(rng, 20)
    path = write_log(tmp_path / "r.h5", pos, val, width=W, height=H, rounds=np.repeat([0, 1], 10))
    before = path.read_bytes()
    with pytest.raises(InputError, match="round_index"):
        append_log(path, *_round(rng, 4), round_index=1)
    assert path.read_bytes() == before


def test_bytes_per_sample_drop_by_the_round_label(tmp_path, rng):
    n = 1 << 14
    pos, val = (rng.random((n, 2)) * [W, H]).astype(np.float32), rng.random((n, 3)).astype(np.float32)
    path = write_log(tmp_path / "b.h5", pos, val, width=W, height=H)
    sizes = _sizes(path)
    # 8 + 12 bytes (and a 4-byte checksum per chunk), no 4 for a /round
    assert set(sizes) == {"positions", "values"} and sum(sizes.values()) / n == pytest.approx(20.0, abs=0.01)

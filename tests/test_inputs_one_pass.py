"""The dispatcher reads a log once: gem's prefix halves are filled by the statistics' pass, bit for bit what a
pass of their own gives."""

from __future__ import annotations

import numpy as np
import pytest

import mcrecon
from mcrecon.core.strata import prefix_halves_of
from mcrecon.io import read_log, write_log
from mcrecon.io.reader import SampleLog
from mcrecon.offline.inputs import gather_inputs


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    rng = np.random.default_rng(4)
    w, h, spp = 20, 14, 6
    ys, xs = np.divmod(np.repeat(np.arange(w * h), spp), w)
    pos = np.stack([xs + rng.random(xs.size), ys + rng.random(ys.size)], axis=1)
    val = rng.gamma(2.0, 0.5, (pos.shape[0], 3))
    val[11, 1] = np.nan   # a non-finite sample takes its index in the prefix halves, not a place
    return write_log(tmp_path_factory.mktemp("one_pass") / "l.h5", pos, val, width=w, height=h)


def _passes(monkeypatch):
    reads = []
    for name in ("iter_chunks", "iter_into"):
        real = getattr(SampleLog, name)

        def counted(self, *a, _real=real, _name=name, **k):
            reads.append(_name)
            return _real(self, *a, **k)

        monkeypatch.setattr(SampleLog, name, counted)
    return reads


@pytest.mark.parametrize("chunk", [None, 17])
def test_gem_prefix_halves_come_from_the_statistics_pass(log, monkeypatch, chunk):
    if chunk:   # batches that cut through pixels' runs
        monkeypatch.setattr("mcrecon.core.samples.DEFAULT_READ_ROWS", chunk)
    want = prefix_halves_of(read_log(log))
    reads = _passes(monkeypatch)
    m = mcrecon.get_method("gem")
    assert m.requires.prefix_halves
    with pytest.warns(mcrecon.McreconWarning, match="NaN"):
        inputs = gather_inputs(read_log(log), m)
    assert len(reads) == 1, reads
    got = inputs.strata
    np.testing.assert_array_equal(got.counter, want.counter)
    np.testing.assert_array_equal(got._sums, want._sums)
    np.testing.assert_array_equal(got._counts, want._counts)

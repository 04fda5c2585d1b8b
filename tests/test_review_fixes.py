"""Regression tests for defects found in review (each failed before its fix)."""

import os
import stat

import h5py
import numpy as np
import pytest

from mcrecon import InputError
from mcrecon.driver import adapt
from mcrecon.io import read_log, write_exr, write_log
from mcrecon.protocol import CallableRenderer, SampleBatch, SampleRequest, jittered_positions, validate_reply


def _renderer(w=8, h=6, nan_pixel=False, features=False):
    def fn(req):
        rng = np.random.default_rng(req.seed)
        pos = jittered_positions(req.counts, rng) if req.counts is not None else np.zeros((0, 2))
        if req.positions is not None:
            pos = np.concatenate([pos, req.positions])
        val = rng.random((len(pos), 3))
        if nan_pixel:
            val[(pos[:, 0] < 1) & (pos[:, 1] < 1), 0] = np.nan  # pixel (0, 0) is always NaN
        feats = {"depth": rng.random(len(pos)).astype(np.float32)} if features else {}
        return SampleBatch(pos, val, feats)
    return CallableRenderer(fn, width=w, height=h)


@pytest.mark.parametrize("method", ["box", "ci", "gem"])
def test_dropped_samples_count_against_the_budget(tmp_path, method):
    with pytest.warns(Warning):
        res = adapt(_renderer(nan_pixel=True), method, spp=8, seed=0, log=tmp_path / "r.h5")
    assert res.stopped in ("budget", "converged") and len(res.rounds) < 50
    committed = read_log(tmp_path / "r.h5").n_samples
    assert committed <= 8 * 6 * 8 and committed == res.stats.n_samples + res.stats.n_dropped


def test_renderer_features_are_logged(tmp_path):
    res = adapt(_renderer(features=True), "box", spp=4, seed=0, log=tmp_path / "f.h5")
    log = read_log(tmp_path / "f.h5")
    assert log.feature_names == ("depth",) and log.read_feature("depth").shape == (res.stats.n_samples,)


def test_logged_round_records_are_the_full_ones(tmp_path):
    ref = np.full((6, 8, 3), 0.5)
    res = adapt(_renderer(), "gem", spp=8, seed=0, log=tmp_path / "g.h5", reference=ref)
    logged = read_log(tmp_path / "g.h5").round_records
    assert [r["toolkit_seconds"] for r in logged] == [r["toolkit_seconds"] for r in res.rounds]
    assert all("error" in r for r in logged)


def test_float32_reply_positions_beyond_2048_are_accepted():
    req = SampleRequest(4096, 2, positions=np.array([[3000.123456789, 1.5], [2048.000061, 0.25]]))
    reply = (req.positions.astype(np.float32), np.ones((2, 3)))
    out = validate_reply(req, reply, n_channels=3)
    np.testing.assert_array_equal(out.positions, req.positions)
    with pytest.raises(Exception, match="differ from the requested"):
        validate_reply(req, (req.positions + [[0.01, 0]], np.ones((2, 3))), n_channels=3)


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

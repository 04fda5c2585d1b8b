"""Each pixel's sample index in the protocol, and the built-in scenes' Owen-scrambled Sobol sampler.

Every request carries, per pixel, the index of its first new sample
(``SampleRequest.first_index``): the samples committed there plus those
in flight.  A renderer with a low-discrepancy sampler continues each
pixel's sequence from it, so a run in rounds draws the points of one
render of the same total.
"""

from __future__ import annotations

import numpy as np
import pytest

from mcrecon.adaptive.run import adapt, resume
from mcrecon.adaptive.schedule import _request_counts
from mcrecon.core.requests import SampleRequest, sample_indices
from mcrecon.methods import get_method
from mcrecon.renderers.command import read_request, write_request
from mcrecon.renderers.scenes import SceneRenderer

OPTS = {"gem": {"initial_spp": 4, "iterations": 4}, "awr": {"initial_spp": 2}, "ci": {"min_spp": 2}, "box": {},
        "splat": {"initial_spp": 1}}


class _Recorder(SceneRenderer):
    """A built-in scene that keeps every request it answers."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.seen = []

    def render(self, request):
        self.seen.append(request)
        return super().render(request)


def _rec(**kw):
    return _Recorder("soft_shadow", width=16, height=12, **kw)


def _check_running_count(requests, start=None):
    """Each request's first_index is the sum of the requests before it (committed or in flight)."""
    total = np.zeros((requests[0].height, requests[0].width), np.int64) if start is None else start.copy()
    for req in requests:
        assert req.first_index is not None and req.first_index.dtype == np.int64
        np.testing.assert_array_equal(req.first_index, total, err_msg=f"round {req.round_index}")
        total += _request_counts(req)
    return total


# ------------------------------------------------------------------ the driver fills it
@pytest.mark.parametrize("method, pipeline", [("box", False), ("box", True), ("gem", False), ("gem", True),
                                              ("awr", False), ("awr", True), ("ci", True), ("splat", True)])
def test_first_index_counts_the_samples_committed_and_in_flight(method, pipeline):
    r = _rec()
    res = adapt(r, get_method(method, **OPTS[method]), spp=10, seed=3, track_error=False, pipeline=pipeline)
    assert len(r.seen) >= 3
    total = _check_running_count(r.seen)
    np.testing.assert_array_equal(total, res.counts.reshape(total.shape))


@pytest.mark.filterwarnings("ignore::mcrecon.errors.McreconWarning")
def test_first_index_counts_dropped_nonfinite_samples():
    """A sample dropped by the NaN policy was rendered: it took its index in the pixel's sequence."""
    class NaNs(_Recorder):
        def render(self, request):
            b = super().render(request)
            b.values[::7] = np.nan
            return b

    r = NaNs("soft_shadow", width=16, height=12)
    res = adapt(r, "box", spp=8, seed=1, track_error=False, nonfinite="drop")
    assert res.samples_dropped > 0
    _check_running_count(r.seen)


@pytest.mark.parametrize("method, pipeline, stop_after", [("box", False, 2), ("box", True, 1), ("box", True, 3),
                                                          ("gem", False, 2), ("gem", True, 2), ("awr", True, 3)])
def test_a_resumed_run_gives_the_indices_of_an_uninterrupted_one(tmp_path, method, pipeline, stop_after):
    m = get_method(method, **OPTS[method])
    full = _rec()
    adapt(full, m, spp=10, seed=4, log=tmp_path / "full.h5", track_error=False, pipeline=pipeline)
    part = _rec()
    adapt(part, m, spp=10, seed=4, log=tmp_path / "part.h5", track_error=False, pipeline=pipeline,
          max_rounds=stop_after)
    rest = _rec()
    resume(tmp_path / "part.h5", rest, track_error=False)
    # a pipelined run had the round after the stop in flight: planned, rendered, not committed
    seen = part.seen[:stop_after] + rest.seen
    assert len(seen) == len(full.seen)
    for a, b in zip(seen, full.seen):
        np.testing.assert_array_equal(a.first_index, b.first_index)
    _check_running_count(seen)


# ------------------------------------------------------------------ the request and the file
def test_sample_indices_number_counted_samples_then_positions_per_pixel():
    counts = np.array([[2, 0], [1, 3]])
    first = np.array([[5, 1], [0, 7]])
    pos = np.array([[0.5, 0.5], [1.2, 1.9], [0.1, 0.2], [1.5, 0.5]])
    req = SampleRequest(2, 2, counts=counts, positions=pos, first_index=first)
    # pixel (0,0): 5, 6 counted; (1,1): 7, 8, 9; (0,1): 0; positions: (0,0) -> 7, (1,1) -> 10, (0,0) -> 8, (1,0) -> 1
    np.testing.assert_array_equal(sample_indices(req), [5, 6, 0, 7, 8, 9, 7, 10, 8, 1])
    no_first = SampleRequest(2, 2, counts=counts)
    np.testing.assert_array_equal(sample_indices(no_first), [0, 1, 0, 0, 1, 2])


def test_first_index_is_validated():
    with pytest.raises(ValueError, match="first_index has shape"):
        SampleRequest(2, 2, counts=np.ones((2, 2), int), first_index=np.zeros((3, 2), int))
    with pytest.raises(ValueError, match="non-negative"):
        SampleRequest(2, 2, counts=np.ones((2, 2), int), first_index=-np.ones((2, 2), int))


def test_the_request_file_round_trips_first_index(tmp_path):
    first = np.arange(12, dtype=np.int64).reshape(3, 4) * 1000003
    req = SampleRequest(4, 3, counts=np.ones((3, 4), np.int64), positions=[[0.5, 0.5]], round_index=2, seed=9,
                        first_index=first)
    write_request(tmp_path / "r.h5", req, channels=("R", "G", "B"))
    back = read_request(tmp_path / "r.h5")
    assert back.first_index.dtype == np.int64
    np.testing.assert_array_equal(back.first_index, first)
    # optional: a request without it reads as None
    write_request(tmp_path / "n.h5", SampleRequest(4, 3, counts=np.ones((3, 4), np.int64)), channels=("R",))
    assert read_request(tmp_path / "n.h5").first_index is None


def test_a_malformed_first_index_is_refused_in_one_line(tmp_path):
    import h5py

    from mcrecon.errors import InputError

    write_request(tmp_path / "r.h5", SampleRequest(4, 3, counts=np.ones((3, 4), np.int64)), channels=("R",))
    with h5py.File(tmp_path / "r.h5", "a") as f:
        f["first_index"] = np.zeros((4, 3))
    with pytest.raises(InputError, match="first_index"):
        read_request(tmp_path / "r.h5")
    with h5py.File(tmp_path / "r.h5", "a") as f:
        del f["first_index"]
        f["first_index"] = -np.ones((3, 4), np.int64)
    with pytest.raises(InputError, match="first_index"):
        read_request(tmp_path / "r.h5")

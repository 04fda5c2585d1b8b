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

from helpers import RecordingScene

OPTS = {"gem": {"initial_spp": 4, "iterations": 4}, "awr": {"initial_spp": 2}, "ci": {"min_spp": 2}, "box": {},
        "splat": {"initial_spp": 1}}


def _rec(**kw):
    return RecordingScene("soft_shadow", width=16, height=12, **kw)


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
    class NaNs(RecordingScene):
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


# ------------------------------------------------------------------ the scenes' Sobol sampler
def _elementary_intervals_hit_once(xy, k):
    """Every elementary interval of area 2^-k (shapes 2^-a x 2^-(k-a)) holds exactly one of 2^k points."""
    for a in range(k + 1):
        cell = np.floor(xy[:, 0] * 2 ** a).astype(np.int64) * 2 ** (k - a) + np.floor(xy[:, 1] * 2 ** (k - a))
        if len(np.unique(cell)) != 2 ** k:
            return False
    return True


@pytest.mark.parametrize("pixel", [0, 7, 40_001])
def test_sobol_blocks_of_a_pixel_are_nets_in_every_pair_of_dimensions(pixel):
    from mcrecon.renderers.scenes.sobol import sobol_points

    for k in range(0, 8):
        n = 2 ** k
        for start in (0, n, 5 * n):  # the first 2^k samples, and later aligned blocks (a round after a round)
            pts = sobol_points(np.full(n, pixel), np.arange(start, start + n), 7, seed=11)
            assert pts.min() >= 0.0 and pts.max() < 1.0
            for d in (0, 2, 4):
                assert _elementary_intervals_hit_once(pts[:, d:d + 2], k), (k, start, d)


def test_sobol_points_are_deterministic_and_differ_between_pixels_pairs_and_seeds():
    from mcrecon.renderers.scenes.sobol import sobol_points

    idx = np.arange(64)
    a = sobol_points(np.full(64, 3), idx, 4, seed=1)
    np.testing.assert_array_equal(a, sobol_points(np.full(64, 3), idx, 4, seed=1))
    assert not np.array_equal(a, sobol_points(np.full(64, 4), idx, 4, seed=1))   # another pixel
    assert not np.array_equal(a, sobol_points(np.full(64, 3), idx, 4, seed=2))   # another run seed
    # the pairs are decorrelated (padding): not the same sequence in dims 0-1 and 2-3
    assert abs(np.corrcoef(a[:, 0], a[:, 2])[0, 1]) < 0.5
    # the points of the first 64 samples of 256 pixels spread over the square (no shared pattern)
    many = sobol_points(np.repeat(np.arange(256), 1), np.zeros(256, np.int64), 2, seed=0)
    assert len(np.unique(np.floor(many * 8).astype(int) @ [8, 1])) > 40


def _sorted_by_pixel_then_position(batch, w):
    key = np.floor(batch.positions[:, 1]).astype(np.int64) * w + np.floor(batch.positions[:, 0]).astype(np.int64)
    order = np.lexsort((batch.positions[:, 0], key))
    return batch.positions[order], batch.values[order]


@pytest.mark.parametrize("scene", ["soft_shadow", "checker_dof", "hdr"])
def test_four_rounds_of_8_are_the_samples_of_one_32_spp_render(scene):
    w, h = 12, 9
    r = SceneRenderer(scene, width=w, height=h, seed=7, sampler="sobol")
    one = r.render(SampleRequest(w, h, counts=np.full((h, w), 32), seed=123))
    parts = [r.render(SampleRequest(w, h, counts=np.full((h, w), 8), round_index=k, seed=1000 + k,
                                    first_index=np.full((h, w), 8 * k))) for k in range(4)]
    # pixel p's samples k = 0..31: the 32-spp render lists them pixel by pixel, the rounds 8 at a time
    pos4 = np.concatenate([p.positions.reshape(h * w, 8, 2) for p in parts], axis=1).reshape(-1, 2)
    val4 = np.concatenate([p.values.reshape(h * w, 8, 3) for p in parts], axis=1).reshape(-1, 3)
    np.testing.assert_array_equal(pos4, one.positions)
    np.testing.assert_array_equal(val4, one.values)
    # without the index every round would start each pixel's sequence again
    again = r.render(SampleRequest(w, h, counts=np.full((h, w), 8), round_index=1, seed=1001))
    np.testing.assert_array_equal(again.positions, parts[0].positions)


def test_an_adaptive_run_with_the_sobol_sampler_continues_each_pixels_sequence():
    """Uniform box rounds through the driver (pipelined or not): each pixel's samples are its first n."""
    w, h = 10, 8
    for pipeline in (False, True):
        res = adapt(SceneRenderer("soft_shadow", width=w, height=h, seed=2, sampler="sobol"), "box", spp=16,
                    seed=9, track_error=False, pipeline=pipeline)
        one = SceneRenderer("soft_shadow", width=w, height=h, seed=2, sampler="sobol").render(
            SampleRequest(w, h, counts=np.full((h, w), 16)))
        np.testing.assert_array_equal(res.counts, 16)
        # box's image is the pixel mean: the mean of each pixel's first 16 points
        np.testing.assert_allclose(res.image, one.values.reshape(h, w, 16, 3).mean(axis=2), rtol=1e-12, atol=1e-12)


def test_sobol_keeps_explicit_positions_and_uses_the_rest_of_their_points():
    w, h = 6, 5
    r = SceneRenderer("depth_of_field", width=w, height=h, sampler="sobol")
    pos = np.array([[0.5, 0.5], [3.25, 4.75], [0.75, 0.25]])
    b = r.render(SampleRequest(w, h, counts=np.ones((h, w), np.int64), positions=pos,
                               first_index=np.full((h, w), 4)))
    np.testing.assert_array_equal(b.positions[w * h:], pos)
    assert np.all(np.floor(b.positions[:w * h, 1]) * w + np.floor(b.positions[:w * h, 0]) == np.arange(w * h))


def test_the_sampler_is_an_option_recorded_in_the_spec_and_validated(tmp_path):
    from mcrecon.errors import InputError
    from mcrecon.renderers.spec import check_spec, renderer_from_spec

    assert "sampler" not in SceneRenderer("flat", width=4, height=4).spec()   # the default: specs as before
    spec = SceneRenderer("flat", width=4, height=4, sampler="sobol").spec()
    assert spec["sampler"] == "sobol" and renderer_from_spec(spec).sampler == "sobol"
    with pytest.raises(InputError, match="sampler"):
        SceneRenderer("flat", width=4, height=4, sampler="halton")
    with pytest.raises(InputError, match="sampler"):
        check_spec({**spec, "sampler": "stratified"})


def test_a_resumed_sobol_run_rebuilds_its_sampler_from_the_log(tmp_path):
    from mcrecon.io import read_log

    w, h = 10, 8
    full = adapt(SceneRenderer("soft_shadow", width=w, height=h, sampler="sobol"), "box", spp=12, seed=1,
                 log=tmp_path / "full.h5", track_error=False)
    adapt(SceneRenderer("soft_shadow", width=w, height=h, sampler="sobol"), "box", spp=12, seed=1,
          log=tmp_path / "part.h5", track_error=False, max_rounds=2)
    res = resume(tmp_path / "part.h5", track_error=False)   # the renderer from the recorded spec
    np.testing.assert_array_equal(res.image, full.image)
    a, b = read_log(tmp_path / "part.h5").read_all(), read_log(tmp_path / "full.h5").read_all()
    np.testing.assert_array_equal(a.values, b.values)


def test_cli_sampler_flag(tmp_path):
    from mcrecon.cli import main
    from mcrecon.io import read_log

    log = tmp_path / "run.h5"
    assert main(["adapt", "--scene", "flat", "--size", "8x8", "--spp", "4", "--sampler", "sobol", "-o",
                 str(tmp_path / "o.exr"), "--log", str(log), "--quiet"]) == 0
    assert read_log(log).run_settings["renderer_spec"]["sampler"] == "sobol"
    assert main(["adapt", "--resume", str(log), "--sampler", "independent", "-o", str(tmp_path / "p.exr")]) == 2
    assert main(["render-log", "--scene", "flat", "--size", "8x8", "--spp", "4", "--sampler", "sobol", "-o",
                 str(tmp_path / "l.h5")]) == 0
    assert read_log(tmp_path / "l.h5").metadata["settings"]["sampler"] == "sobol"


# ------------------------------------------------------------------ the example renderers
@pytest.mark.parametrize("which", ["package", "data_tools"])
def test_the_example_renderers_continue_each_pixels_stratified_sequence(tmp_path, which):
    import importlib.util
    from pathlib import Path

    from mcrecon.io import read_log

    if which == "package":
        from mcrecon.renderers import example as mod
    else:
        spec = importlib.util.spec_from_file_location(
            "example_renderer", Path(__file__).parents[1] / "data_tools" / "example_renderer.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    w, h = 5, 4
    offsets = []
    for k in range(4):  # four rounds of 4 samples per pixel, with the index
        req = SampleRequest(w, h, counts=np.full((h, w), 4), round_index=k, seed=k,
                            first_index=np.full((h, w), 4 * k))
        write_request(tmp_path / "q.h5", req, channels=("R", "G", "B"))
        mod.main(str(tmp_path / "q.h5"), str(tmp_path / "r.h5"))
        pos = read_log(tmp_path / "r.h5").read_all().positions
        offsets.append((pos - np.floor(pos)).reshape(h * w, 4, 2))
    per_pixel = np.concatenate(offsets, axis=1)  # (pixels, 16, 2): each pixel's 16 samples in order
    for p in range(h * w):
        assert _elementary_intervals_hit_once(per_pixel[p], 4)
        assert _elementary_intervals_hit_once(per_pixel[p, 4:8], 2)
    assert not np.array_equal(per_pixel[0], per_pixel[1])
    # without the index: independent jitter, as before
    write_request(tmp_path / "q.h5", SampleRequest(w, h, counts=np.full((h, w), 4)), channels=("R", "G", "B"))
    mod.main(str(tmp_path / "q.h5"), str(tmp_path / "r.h5"))
    assert read_log(tmp_path / "r.h5").n_samples == 4 * w * h


def test_the_cli_lists_the_scene_samplers():
    from mcrecon.cli._common import SCENE_SAMPLERS
    from mcrecon.renderers.spec_format import SAMPLERS

    assert SCENE_SAMPLERS == SAMPLERS

"""Adaptive driver: rounds, budget, validation of replies, durability, resume."""

import numpy as np
import pytest

from mcrecon import InputError, RendererError
from mcrecon.adaptive.run import adapt, resume
from mcrecon.adaptive.schedule import round_seeds
from mcrecon.io import read_log
from mcrecon.methods import Method
from mcrecon.renderers import CallableRenderer
from mcrecon.core.requests import SampleBatch, SampleRequest, jittered_positions, validate_reply

from helpers import jittered_renderer


def _shade(pos, seed):
    rng = np.random.default_rng(seed)
    base = 0.2 + 0.6 * (pos[:, :1] > 8)
    return np.repeat(base, 3, axis=1) * rng.uniform(0.5, 1.5, (len(pos), 1))


def _renderer(w=16, h=8, fault=None):
    def shade(pos, rng, req):
        val = _shade(pos, req.seed)
        return fault[1](pos, val) if fault and req.round_index == fault[0] else val
    return jittered_renderer(shade, width=w, height=h, name="test renderer")


def test_uniform_rounds_fill_budget_exactly():
    res = adapt(_renderer(), "box", spp=10, seed=3)
    assert res.stats.n_samples == 16 * 8 * 10 and res.stopped == "budget"
    assert [r["samples"] for r in res.rounds] == [128, 128, 256, 512, 256]
    assert res.counts.min() >= 9 and res.counts.max() <= 11
    assert all(r["renderer_seconds"] >= 0 and r["toolkit_seconds"] >= 0 for r in res.rounds)


def test_fractional_spp_and_reference_error_falls():
    ref = np.repeat((0.2 + 0.6 * (np.arange(16) >= 8) + 0 * np.arange(8)[:, None])[..., None], 3, axis=2)
    res = adapt(_renderer(), "box", spp=64.5, seed=1, reference=ref)
    assert res.stats.n_samples == round(64.5 * 128)
    errs = [r["error"] for r in res.rounds]
    assert errs[-1] < errs[0] / 8  # 1 -> 64 spp: the error of a mean falls ~64x; allow noise


def test_reproducible_from_seed():
    a = adapt(_renderer(), "box", spp=4, seed=7).image
    b = adapt(_renderer(), "box", spp=4, seed=7).image
    c = adapt(_renderer(), "box", spp=4, seed=8).image
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    r1, s1 = round_seeds(7, 2)
    r2, s2 = round_seeds(7, 2)
    assert s1 == s2 and r1.random() == r2.random()


class _Stopper(Method):
    """Stops after two rounds: its own target is met."""

    name = "box"

    def plan(self, run, state):
        if state.round_index >= 2:
            return None
        return super().plan(run, state)

    def reconstruct_run(self, run, inputs):
        return inputs.stats.mean


def test_method_target_and_time_limit_stop_the_run():
    res = adapt(_renderer(), _Stopper(), spp=100, seed=0)
    assert res.stopped == "converged" and len(res.rounds) == 2
    with pytest.warns(Warning, match="no samples"):
        res = adapt(_renderer(), "box", spp=1e6, seed=0, time_limit=1e-9)
    assert res.stopped == "time_limit" and res.stats.n_samples == 0 and np.isfinite(res.image).all()


@pytest.mark.parametrize("fault, match", [
    (lambda p, v: SampleBatch(p[:-1], v[:-1]), "reply length"),
    (lambda p, v: SampleBatch(p, v[:, :2]), "values"),
    (lambda p, v: SampleBatch(np.where(np.arange(len(p))[:, None] == 0, p + [1, 0], p), v), "inside the requested"),
    (lambda p, v: SampleBatch(p + 100, v), "off the film"),
    (lambda p, v: "garbage", "expected a SampleBatch"),
    (lambda p, v: SampleBatch(p, np.full(v.shape, "x")), "dtype"),
])
def test_faulty_replies_leave_a_resumable_log(tmp_path, fault, match):
    log = tmp_path / "run.h5"
    with pytest.raises(RendererError, match=match):
        adapt(_renderer(fault=(2, fault)), "box", spp=8, seed=0, log=log)
    sl = read_log(log)
    assert sl.n_rounds == 2 and sl.n_samples == 256  # the two good rounds are committed
    res = resume(log, _renderer())
    full = adapt(_renderer(), "box", spp=8, seed=0)
    assert res.stats.n_samples == full.stats.n_samples
    np.testing.assert_array_equal(res.image, full.image)


def test_renderer_that_raises():
    def boom(req):
        raise ValueError("GPU on fire")
    with pytest.raises(RendererError, match="raised ValueError: GPU on fire"):
        adapt(CallableRenderer(boom, width=2, height=2), "box", spp=1)


def test_nonfinite_reply_policies(tmp_path):
    def nan_in_round_1(p, v):
        v = v.copy()
        v[0, 0] = np.nan
        return SampleBatch(p, v)
    log = tmp_path / "r.h5"
    with pytest.raises(RendererError, match="NaN or Inf"):
        adapt(_renderer(fault=(1, nan_in_round_1)), "box", spp=4, log=log, nonfinite="raise")
    assert read_log(log).n_rounds == 1
    with pytest.warns(Warning, match="dropped"):
        res = adapt(_renderer(fault=(1, nan_in_round_1)), "box", spp=4)
    assert res.stats.n_dropped == 1 and np.isfinite(res.image).all()


def test_resume_after_stop_matches_uninterrupted(tmp_path):
    log = tmp_path / "run.h5"
    part = adapt(_renderer(), "box", spp=16, seed=5, log=log, max_rounds=3)
    assert part.stopped == "max_rounds"
    res = resume(log, _renderer())
    full = adapt(_renderer(), "box", spp=16, seed=5)
    np.testing.assert_array_equal(res.image, full.image)
    sl = read_log(log)
    assert len(sl.round_records) == sl.n_rounds == len(full.rounds)


def test_bad_arguments(tmp_path):
    with pytest.raises(InputError, match="spp"):
        adapt(_renderer(), "box", spp=0)
    with pytest.raises(InputError, match="unknown method"):
        adapt(_renderer(), "nope", spp=1)
    with pytest.raises(InputError, match="reference"):
        adapt(_renderer(), "box", spp=1, reference=np.zeros((2, 2, 3)))
    (tmp_path / "x.h5").write_text("x")
    with pytest.raises(InputError, match="exists"):
        adapt(_renderer(), "box", spp=1, log=tmp_path / "x.h5")
    with pytest.raises(InputError, match="not written by an adaptive run"):
        from mcrecon.io import write_log
        write_log(tmp_path / "plain.h5", np.zeros((1, 2)), np.zeros((1, 3)), width=1, height=1)
        resume(tmp_path / "plain.h5", _renderer(1, 1))


def test_request_and_reply_validation():
    req = SampleRequest(4, 2, counts=np.array([[1, 0, 2, 0], [0, 0, 0, 1]]), positions=np.array([[0.5, 1.5]]))
    assert req.total == 5
    pos = np.array([[0.1, 0.1], [2.5, 0.5], [2.9, 0.2], [3.5, 1.5], [0.5, 1.5]])
    out = validate_reply(req, (pos, np.ones((5, 1))), n_channels=1)
    assert out.values.shape == (5, 1)
    with pytest.raises(RendererError, match="requested positions"):
        validate_reply(req, (pos + np.array([[0, 0]] * 4 + [[0.5, 0]]), np.ones((5, 1))), n_channels=1)
    with pytest.raises(ValueError):
        SampleRequest(4, 2, counts=np.zeros((3, 3), int))
    with pytest.raises(ValueError):
        SampleRequest(4, 2, positions=np.array([[4.0, 0.0]]))


# ------------------------------------------------------------------ precision
def _offset_renderer(base, spread, dtype, w=6, h=4):
    """Values base + spread * u, u uniform in [-1, 1], in the given dtype."""
    def shade(pos, rng, req):
        return (base + spread * rng.uniform(-1, 1, (len(pos), 1)) * np.ones(3)).astype(dtype)
    return jittered_renderer(shade, width=w, height=h, name="offset renderer")


def test_float64_replies_keep_their_precision_end_to_end(tmp_path):
    """1e6 +- 1e-3: float32 storage made every sample variance exactly 0 (ci stopped, gem skipped)."""
    r = _offset_renderer(1e6, 1e-3, np.float64)
    want = 1e-6 / 3  # variance of spread * U(-1, 1)
    for log in (None, tmp_path / "auto.h5"):
        res = adapt(r, "box", spp=64, seed=1, log=log)
        var = res.stats.sample_variance()
        assert np.all(var > 0.5 * want) and np.all(var < 2 * want)  # 64 samples: within a factor 2
    assert read_log(tmp_path / "auto.h5").value_dtype == np.float64
    # resumed: the same statistics as uninterrupted, bit for bit
    adapt(r, "ci", spp=64, seed=2, log=tmp_path / "k.h5", max_rounds=1)
    full = adapt(r, "ci", spp=64, seed=2, log=tmp_path / "f.h5")
    res = resume(tmp_path / "k.h5", r)
    np.testing.assert_array_equal(res.stats.m2, full.stats.m2)
    np.testing.assert_array_equal(res.image, full.image)
    assert read_log(tmp_path / "k.h5").value_dtype == np.float64


def test_float32_replies_are_stored_as_float32(tmp_path):
    adapt(_offset_renderer(0.5, 0.1, np.float32), "box", spp=4, seed=1, log=tmp_path / "a.h5")
    assert read_log(tmp_path / "a.h5").value_dtype == np.float32


def test_explicit_float32_storage_warns_once_when_it_loses_the_spread(tmp_path):
    r = _offset_renderer(1e6, 1e-3, np.float64)
    import warnings as w
    with w.catch_warnings(record=True) as caught:
        w.simplefilter("always")
        adapt(r, "box", spp=16, seed=1, log=tmp_path / "a.h5", storage_dtype="float32")
    lost = [c for c in caught if "loses the spread" in str(c.message)]
    assert len(lost) == 1 and "24 pixel(s)" in str(lost[0].message) and "float64" in str(lost[0].message)
    with w.catch_warnings():
        w.simplefilter("error")  # a spread float32 holds: no warning
        adapt(_offset_renderer(1.0, 0.1, np.float64), "box", spp=16, seed=1, log=tmp_path / "b.h5",
              storage_dtype="float32")


def test_values_beyond_float32_are_never_turned_into_inf(tmp_path):
    r = _offset_renderer(1e39, 1e37, np.float64)
    res = adapt(r, "box", spp=4, seed=1, log=tmp_path / "auto.h5")
    assert np.isfinite(res.image).all() and res.image.min() > 9e38
    assert np.isfinite(read_log(tmp_path / "auto.h5").read_all().values).all()
    with pytest.raises(InputError, match="beyond float32's range.*storage_dtype='auto'"):
        adapt(r, "box", spp=4, seed=1, log=tmp_path / "f32.h5", storage_dtype="float32")
    assert not (tmp_path / "f32.h5").exists()  # refused on the first reply: no log left to refuse the retry
    adapt(r, "box", spp=4, seed=1, log=tmp_path / "f32.h5")
    with pytest.raises(InputError, match="storage_dtype"):
        adapt(r, "box", spp=4, storage_dtype="float16")


def test_on_round_sees_every_committed_round_as_recorded(tmp_path):
    seen = []
    res = adapt(_renderer(), "gem", spp=8, seed=2, log=tmp_path / "r.h5", reference=np.full((8, 16, 3), 0.5),
                on_round=lambda rec: seen.append((dict(rec), read_log(tmp_path / "r.h5").n_samples)))
    assert [r for r, _ in seen] == res.rounds == read_log(tmp_path / "r.h5").round_records
    # called after the round is committed: the log already holds its samples
    assert [n for _, n in seen] == [r["samples_total"] for r in res.rounds]
    assert all("error" in r for r, _ in seen)
    # and on a resumed run, for the new rounds only
    adapt(_renderer(), "box", spp=8, seed=2, log=tmp_path / "k.h5", max_rounds=2)
    more = []
    resume(tmp_path / "k.h5", _renderer(), on_round=more.append)
    assert [r["round"] for r in more] == list(range(2, 2 + len(more))) and more


# ------------------------------------------------------------------ found in review (each failed before its fix)
def _review_renderer(w=8, h=6, nan_pixel=False, features=False):
    def shade(pos, rng, req):
        val = rng.random((len(pos), 3))
        if nan_pixel:
            val[(pos[:, 0] < 1) & (pos[:, 1] < 1), 0] = np.nan  # pixel (0, 0) is always NaN
        feats = {"depth": rng.random(len(pos)).astype(np.float32)} if features else {}
        return SampleBatch(pos, val, feats)
    return jittered_renderer(shade, width=w, height=h)


@pytest.mark.parametrize("method", ["box", "ci", "gem"])
def test_dropped_samples_count_against_the_budget(tmp_path, method):
    with pytest.warns(Warning):
        res = adapt(_review_renderer(nan_pixel=True), method, spp=8, seed=0, log=tmp_path / "r.h5")
    assert res.stopped in ("budget", "converged") and len(res.rounds) < 50
    committed = read_log(tmp_path / "r.h5").n_samples
    assert committed <= 8 * 6 * 8 and committed == res.stats.n_samples + res.stats.n_dropped


def test_renderer_features_are_logged(tmp_path):
    res = adapt(_review_renderer(features=True), "box", spp=4, seed=0, log=tmp_path / "f.h5")
    log = read_log(tmp_path / "f.h5")
    assert log.feature_names == ("depth",) and log.read_feature("depth").shape == (res.stats.n_samples,)


def test_logged_round_records_are_the_full_ones(tmp_path):
    ref = np.full((6, 8, 3), 0.5)
    res = adapt(_review_renderer(), "gem", spp=8, seed=0, log=tmp_path / "g.h5", reference=ref)
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


def test_reply_checks_are_the_shared_sample_checks():
    req = SampleRequest(4, 3, counts=np.ones((3, 4), np.int64))
    pos = jittered_positions(req.counts, np.random.default_rng(0))
    with pytest.raises(RendererError, match=r"r: values: dtype <U1, expected float32 or float64"):
        validate_reply(req, (pos, np.full((12, 3), "x")), n_channels=3, renderer="r")
    bad = pos.copy()
    bad[5] = [4.0, 0.5]  # x == width: off the film
    with pytest.raises(RendererError, match=r"positions: 1 sample\(s\) off the film \[0, 4\) x \[0, 3\) or non-finite, first at row 5"):
        validate_reply(req, (bad, np.ones((12, 3))), n_channels=3, renderer="r")
    with pytest.raises(RendererError, match="reply length: 11 samples, requested 12"):
        validate_reply(req, (pos[:11], np.ones((11, 3))), n_channels=3, renderer="r")
    with pytest.raises(RendererError, match="features/label: dtype <U1, expected a numeric dtype"):
        validate_reply(req, SampleBatch(pos, np.ones((12, 3)), {"label": np.full(12, "a")}), n_channels=3,
                       renderer="r")
    out = validate_reply(req, (pos.astype(np.float32), np.ones((12, 3), np.float32)), n_channels=3)
    assert out.values.dtype == np.float32  # the renderer's precision is kept


# ------------------------------------------------------------------ found in the redesign's review
@pytest.mark.parametrize("method", ["gem", "ci", "awr", "box", "splat"])
@pytest.mark.parametrize("size", [(1, 1), (4, 3)])
def test_resume_is_bit_identical_with_float64_replies(tmp_path, method, size):
    """A resume rebuilt the statistics in read chunks that ignored round boundaries; with float64
    replies the run merges rounded differently (7 of 162 cases differed by ~1e-17)."""
    from mcrecon.renderers.scenes import SceneRenderer
    w, h = size
    r = SceneRenderer("soft_shadow", width=w, height=h, seed=2)
    full = adapt(r, method, spp=64, seed=5, log=tmp_path / "full.h5", track_error=False)
    adapt(r, method, spp=64, seed=5, log=tmp_path / "cut.h5", max_rounds=2, track_error=False)
    res = resume(tmp_path / "cut.h5", r, track_error=False)
    assert read_log(tmp_path / "cut.h5").value_dtype == np.float64
    np.testing.assert_array_equal(res.stats.mean, full.stats.mean)
    np.testing.assert_array_equal(res.stats.m2, full.stats.m2)
    np.testing.assert_array_equal(res.image, full.image)


def test_adaptive_splat_applies_the_runs_nonfinite_policy(tmp_path):
    """observe() used to drop NaN samples whatever the policy: with nonfinite='zero' the adaptive
    image differed from the offline reconstruction of the same log (by 0.31)."""
    import mcrecon

    def shade(pos, rng, req):
        val = rng.random((len(pos), 3))
        val[::7, 1] = np.nan
        return val
    r = jittered_renderer(shade, width=8, height=6)
    for policy in ("zero", "drop"):
        with pytest.warns(Warning):
            res = adapt(r, "splat", spp=8, seed=1, log=tmp_path / f"{policy}.h5", nonfinite=policy)
        with pytest.warns(Warning):
            offline = mcrecon.reconstruct(tmp_path / f"{policy}.h5", method="splat", nonfinite=policy)
        np.testing.assert_array_equal(res.image, offline)


@pytest.mark.parametrize("n", [50, 70_000])  # the NumPy screen and the compiled one
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_validation_counts_the_nonfinite_rows_of_a_reply_in_its_one_pass(n, dtype):
    """The driver takes the count of rows with a NaN or Inf value from validate_reply's pass:
    the same count as a separate scan of the values (rows, not values)."""
    from mcrecon.core.requests import validate_reply_counted

    rng = np.random.default_rng(n)
    req = SampleRequest(16, 12, positions=rng.random((n, 2)) * [16, 12])
    val = rng.random((n, 3)).astype(dtype)
    for k, c, v in ((3, 0, np.nan), (3, 2, np.inf), (7, 1, -np.inf), (n - 1, 2, np.nan)):
        val[k, c] = v
    batch, n_bad = validate_reply_counted(req, (req.positions, val), n_channels=3)
    assert n_bad == int(np.count_nonzero(~np.isfinite(val).all(axis=1))) == 3
    clean, none = validate_reply_counted(req, (req.positions, rng.random((n, 3)).astype(dtype)), n_channels=3)
    assert none == 0
    np.testing.assert_array_equal(validate_reply(req, (req.positions, val), n_channels=3).values, batch.values)


def test_python_runs_record_their_renderer_and_resume_from_the_log_alone(tmp_path):
    # README: "in Python, resume("run.h5") does the same" -- it raised "renderer_spec: none recorded"
    # for every run not started by the command line
    from mcrecon.adaptive.run import adapt, resume
    from mcrecon.renderers.scenes import SceneRenderer

    whole = adapt(SceneRenderer("checker_wall", width=16, height=16), "gem", spp=8, seed=3, progress=False)
    log = tmp_path / "run.h5"
    part = adapt(SceneRenderer("checker_wall", width=16, height=16), "gem", spp=8, seed=3, log=str(log),
                 progress=False, max_rounds=3)
    assert part.samples < whole.samples
    done = resume(str(log), progress=False)
    assert done.samples == whole.samples
    np.testing.assert_array_equal(done.image, whole.image)
    # features other than the scene's default are recorded too
    plain = tmp_path / "plain.h5"
    adapt(SceneRenderer("checker_wall", width=8, height=8, features=False), "box", spp=4, log=str(plain),
          progress=False, max_rounds=1)
    assert read_log(plain).run_settings["renderer_spec"]["features"] is False
    assert resume(str(plain), progress=False).samples == 4 * 64
    assert read_log(plain).feature_names == ()
    # a renderer without spec() records none: resume(log, renderer) then
    other = tmp_path / "other.h5"
    r = jittered_renderer(lambda pos, rng, req: np.ones((len(pos), 3)), width=4, height=4, stream=lambda req: 0)
    adapt(r, "box", spp=2, log=str(other), progress=False)
    with pytest.raises(InputError, match="none recorded"):
        resume(str(other), progress=False)

"""A pipelined run plans the next round before it observes the round it commits (splat's doubling rounds).

splat's plan with a round in flight reads only the counts (``state.pending`` and the budget left), so the
driver hands the next request to the renderer before ``observe`` splats the committed round
(``mcrecon.adaptive.rounds.plans_before_observe``).  These tests pin that the requests, the log and the
image are those of the order plan-after-observe, bit for bit (with the default's split initial pass and
with N_0 = 1, with features, stopped and resumed), that the toolkit thread does plan first, and that a
failing ``observe`` stops the run with the rounds before it committed and nothing after it.
"""

import numpy as np
import pytest

from mcrecon.adaptive.rounds import plans_before_observe
from mcrecon.adaptive.run import adapt, resume
from mcrecon.core.requests import SampleBatch
from mcrecon.io import read_log
from mcrecon.methods.splat import SplatMethod

from helpers import jittered_renderer


def _renderer(w=16, h=12, features=False):
    def shade(pos, rng, req):
        base = 0.2 + 0.6 * (pos[:, :1] > w / 2) + 0.1 * np.sin(pos[:, 1:2])
        val = np.repeat(base, 3, axis=1) * rng.uniform(0.5, 1.5, (len(pos), 1))
        if not features:
            return val
        return SampleBatch(pos, val, {"albedo": np.repeat(base, 3, axis=1), "depth": 1.0 + pos[:, 1:2] / h})
    return jittered_renderer(shade, width=w, height=h, name="plan-before-observe test renderer")


class _AfterObserve(SplatMethod):
    """splat planned the way every other method is: after the committed round is observed."""

    plans_before_observe = False


class _Failing(SplatMethod):
    """splat whose observe of round ``bad`` raises."""

    bad = 2

    def observe(self, run, batch, round_index):
        if round_index == self.bad:
            raise RuntimeError(f"observe of round {round_index} failed")
        super().observe(run, batch, round_index)


def _same_runs(a, b, log_a, log_b):
    assert [r["samples"] for r in a.rounds] == [r["samples"] for r in b.rounds]
    np.testing.assert_array_equal(a.image, b.image)
    np.testing.assert_array_equal(a.counts, b.counts)
    la, lb = read_log(log_a).read_all(), read_log(log_b).read_all()
    np.testing.assert_array_equal(la.positions, lb.positions)
    np.testing.assert_array_equal(la.values, lb.values)


def test_only_methods_that_read_samples_and_declare_it_plan_first():
    assert plans_before_observe(SplatMethod()) and not plans_before_observe(_AfterObserve())
    from mcrecon import get_method

    for name in ("box", "gem", "awr", "ci"):
        assert not plans_before_observe(get_method(name)), name


def test_the_capabilities_read_from_a_method_are_declared_on_the_base_class():
    """What the driver and the readers ask of a method is a class attribute of Method with its default (no
    getattr with a default of its own at each reader): planning before observe is off, the variance read."""
    from mcrecon.methods import available_methods, method_class
    from mcrecon.methods.base import Method

    assert Method.plans_before_observe is False and Method.reads_variance is True
    assert [n for n in available_methods() if method_class(n).plans_before_observe] == ["splat"]
    assert [n for n in available_methods() if not method_class(n).reads_variance] == ["box"]


@pytest.mark.parametrize("opts, spp, features", [({}, 64, False),           # 8 + 8 (split N_0), 16, 32
                                                  ({}, 64, True),            # the feature gate
                                                  ({"initial_spp": 1}, 40, False),  # 1, 2, 4, 8, 25
                                                  ({"variant": "paper"}, 24, False)])
def test_plan_before_observe_gives_the_rounds_log_and_image_of_plan_after_observe(tmp_path, opts, spp, features):
    first = adapt(_renderer(features=features), SplatMethod(**opts), spp=spp, seed=3, log=tmp_path / "a.h5",
                  pipeline=True, track_error=False)
    after = adapt(_renderer(features=features), _AfterObserve(**opts), spp=spp, seed=3, log=tmp_path / "b.h5",
                  pipeline=True, track_error=False)
    assert len(first.rounds) >= 4 and first.samples == spp * 16 * 12
    _same_runs(first, after, tmp_path / "a.h5", tmp_path / "b.h5")
    # and a sequential run's rounds (N_0 = 1: the initial pass is one round either way)
    if opts.get("initial_spp") == 1:
        seq = adapt(_renderer(), SplatMethod(**opts), spp=spp, seed=3, pipeline=False, track_error=False)
        np.testing.assert_array_equal(seq.image, first.image)
    # the toolkit thread planned round j + 1 before it observed round j - 1
    tl = first.timeline
    plans = {e["round"]: e for e in tl if e["phase"] == "plan"}
    observes = {e["round"]: e for e in tl if e["phase"] == "observe"}
    n = len(first.rounds)
    for j in range(2, n):  # round j renders while round j - 1 is committed and round j + 1 planned
        assert plans[j + 1]["end"] <= observes[j - 1]["start"], (j, plans[j + 1], observes[j - 1])
    assert sorted(observes) == list(range(n))


@pytest.mark.parametrize("stop_after", [1, 2, 3])
def test_a_stopped_run_that_planned_first_resumes_bit_identically(tmp_path, stop_after):
    full = adapt(_renderer(), SplatMethod(), spp=64, seed=5, log=tmp_path / "full.h5", pipeline=True,
                 track_error=False)
    log = tmp_path / "stopped.h5"
    part = adapt(_renderer(), SplatMethod(), spp=64, seed=5, log=log, pipeline=True, max_rounds=stop_after,
                 track_error=False)
    assert part.stopped == "max_rounds" and read_log(log).n_rounds == stop_after
    res = resume(log, _renderer(), track_error=False)
    assert res.samples == full.samples
    _same_runs(res, full, log, tmp_path / "full.h5")


def test_a_failing_observe_stops_the_run_and_commits_nothing_after_it(tmp_path):
    log = tmp_path / "run.h5"
    with pytest.raises(RuntimeError, match="observe of round 2 failed"):
        adapt(_renderer(), _Failing(initial_spp=1), spp=40, seed=2, log=log, pipeline=True, track_error=False)
    # round 2 reached the log before its observe (as when the plan follows observe); round 3, rendered
    # meanwhile, is not committed
    assert read_log(log).n_rounds == 3


def test_the_log_holds_each_rounds_full_record_written_by_the_thread_that_observed_it(tmp_path):
    """The full record of a round observed while the next one renders is written by the toolkit thread (one
    thread writes the log at a time): the log's records are the run's, errors included."""
    from mcrecon.renderers import scenes

    ref = scenes.reference_image("soft_shadow", 24, 16)
    res = adapt(scenes.SceneRenderer("soft_shadow", width=24, height=16, seed=0), SplatMethod(initial_spp=1),
                spp=40, seed=1, log=tmp_path / "r.h5", reference=ref, pipeline=True)
    logged = read_log(tmp_path / "r.h5").round_records
    assert len(logged) == len(res.rounds) >= 5
    for a, b in zip(logged, res.rounds):
        assert "_logged" not in b and "_eval" not in b
        for key in ("round", "samples", "samples_total", "error", "toolkit_seconds", "wall_seconds"):
            assert a[key] == pytest.approx(b[key], rel=1e-12, abs=0), (key, a, b)

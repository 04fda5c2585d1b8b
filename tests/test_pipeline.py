"""Pipelined adaptive rounds (issue 15): one round of lag, reproducible, resumable bit for bit.

While the renderer renders round k+1, the toolkit thread commits round k and
plans round k+2 from the rounds <= k.  These tests pin the lag (what each plan
sees), the exact shortcuts (box is bit-identical with and without the lag; the
driver's one-pass commit equals ``stats.add``), and kill-and-resume of
pipelined runs (in-process stops and SIGKILL at deterministic markers).
"""

import dataclasses
import os
import signal
import subprocess
import sys
import textwrap
import time
import types
import warnings
from pathlib import Path

import numpy as np
import pytest

from mcrecon import InputError, get_method
from mcrecon.adaptive.rounds import _take_round
from mcrecon.adaptive.schedule import _with_seed, method_pipelines
from mcrecon.adaptive.run import adapt, resume
from mcrecon.io import read_log
from mcrecon.methods import Method
from mcrecon.renderers.command import CommandRenderer
from mcrecon.core.requests import SampleBatch, SampleRequest
from mcrecon.core.stats import PixelStats

from helpers import jittered_renderer

FAULT = str(Path(__file__).parent / "renderers" / "fault_renderer.py")


def _renderer(w=16, h=12):
    def shade(pos, rng, req):
        base = 0.2 + 0.6 * (pos[:, :1] > w / 2) + 0.1 * np.sin(pos[:, 1:2])
        return np.repeat(base, 3, axis=1) * rng.uniform(0.5, 1.5, (len(pos), 1))
    return jittered_renderer(shade, width=w, height=h, name="pipeline test renderer")


# splat: N_0 = 1 (the paper's), so its initial pass is one round pipelined or not (the default's 16 is split)
OPTS = {"gem": {"initial_spp": 4, "iterations": 4}, "awr": {"initial_spp": 2}, "ci": {"min_spp": 2}, "box": {},
        "splat": {"initial_spp": 1}}


# ------------------------------------------------------------------ what each plan sees
class _Spy(Method):
    """Uniform doubling (the base plan) that records what every plan saw."""

    name = "box"
    pipeline = True

    def reconstruct_run(self, run, inputs):
        return inputs.stats.mean

    def plan(self, run, state):
        run.seen.append((state.round_index, int(state.stats.n_samples), int(state.n_samples),
                         None if state.pending is None else int(state.pending.sum())))
        return super().plan(run, state)

    def start(self, *a, **kw):
        run = super().start(*a, **kw)
        run.seen = []
        return run


def test_plan_of_round_j_sees_the_rounds_up_to_j_minus_2_and_round_j_minus_1_pending():
    res = adapt(_renderer(), _Spy(), spp=16, seed=1, pipeline=True)
    seen = res.run.seen
    totals = [0] + [r["samples_total"] for r in res.rounds]
    sizes = [r["samples"] for r in res.rounds]
    # round 0 is the driver's initial pass (1 spp): the first plan is round 1's
    assert [s[0] for s in seen] == list(range(1, len(seen) + 1)) and sizes[0] == 16 * 12
    for j, committed, n, pending in seen:
        assert committed > 0  # a plan never sees empty statistics
        if j == 1:  # planned after the one-round initial pass is committed, nothing pending
            assert committed == totals[1] and n == totals[1] and pending is None
        else:
            assert committed == totals[j - 1] and pending == sizes[j - 1] and n == committed + pending
    seq = adapt(_renderer(), _Spy(), spp=16, seed=1, pipeline=False).run.seen
    assert all(s[1] == s[2] and s[3] is None for s in seq)


class _SplitSpy(_Spy):
    initial_spp = 4


def test_a_split_initial_pass_lets_the_first_plan_see_its_first_half(tmp_path):
    """Pipelined, an initial pass of >= 2 spp is the driver's two rounds (half, then the rest, the
    second planned while the first renders): the first plan sees the first half, the rest pending."""
    res = adapt(_renderer(), _SplitSpy(), spp=16, seed=1, pipeline=True)
    seen = res.run.seen
    sizes = [r["samples"] for r in res.rounds]
    assert sizes[:2] == [2 * 16 * 12, 2 * 16 * 12]
    assert seen[0] == (2, 2 * 16 * 12, 4 * 16 * 12, 2 * 16 * 12)
    seq = adapt(_renderer(), _SplitSpy(), spp=16, seed=1, pipeline=False)
    assert [r["samples"] for r in seq.rounds][0] == 4 * 16 * 12
    assert seq.run.seen[0][:3] == (1, 4 * 16 * 12, 4 * 16 * 12)
    # box: stopped after round 0 or 1 and resumed (the resume plans the round in flight again), the same run
    full = adapt(_renderer(), "box", spp=16, seed=1, pipeline=True)
    for stop in (1, 2):
        log = tmp_path / f"blind{stop}.h5"
        adapt(_renderer(), "box", spp=16, seed=1, pipeline=True, log=log, max_rounds=stop)
        done = resume(log, _renderer())
        np.testing.assert_array_equal(done.image, full.image)
        assert [r["samples"] for r in done.rounds] == [r["samples"] for r in full.rounds]


def test_a_plan_asking_for_nothing_waits_for_the_round_in_flight(tmp_path):
    """ci pipelined: rounds 0 and 1 are the two halves of its initial pass; every pixel's pass is
    then in flight, so round 2's plan asks for nothing: the driver commits round 1 and plans again --
    here everything converged, the sequential run's samples."""
    from mcrecon.renderers.scenes import SceneRenderer

    def run(pipe, **kw):
        return adapt(SceneRenderer("flat", width=40, height=28, seed=1), get_method("ci", min_spp=4, tolerance=10.0),
                     spp=24, seed=3, pipeline=pipe, track_error=False, **kw)

    seq, pip = run(False), run(True)
    assert seq.stopped == pip.stopped == "converged" and seq.samples == pip.samples == 4 * 40 * 28
    assert [r["samples"] for r in pip.rounds] == [2 * 40 * 28, 2 * 40 * 28]
    assert [e["round"] for e in pip.timeline if e["phase"] == "plan"].count(2) == 2
    np.testing.assert_array_equal(seq.counts, pip.counts)  # (other samples: the halves are other rounds)

    # with nothing in flight, a plan that asks for nothing ends the run
    class Nothing(_Spy):
        def plan(self, run, state):
            return state.request(counts=np.zeros((state.height, state.width), np.int64))

    res = adapt(_renderer(), Nothing(), spp=4, pipeline=False)
    assert res.stopped == "converged" and [r["samples"] for r in res.rounds] == [16 * 12]


def _half_constant_renderer(w, h):
    """Rows above the middle: the constant 0.5 (converged on the first samples); below: noise."""
    def shade(pos, rng, req):
        noisy = pos[:, 1:2] >= h / 2
        return np.repeat(np.where(noisy, rng.uniform(0.0, 1.0, (len(pos), 1)), 0.5), 3, axis=1)
    return jittered_renderer(shade, width=w, height=h, name="half constant")


@pytest.mark.parametrize("stop_after", [1, 2, 3, 5])
def test_a_pipelined_run_that_waited_resumes_bit_identically(tmp_path, stop_after):
    """ci with a round that waits (asks for nothing): stopped and resumed around the wait (the
    resume plans the waiting round again, commits, plans from it), the same samples and image."""
    m = get_method("ci", min_spp=4, step_spp=4, tolerance=0.02)
    r = lambda: _half_constant_renderer(24, 20)  # noqa: E731
    full = adapt(r(), m, spp=40, seed=6, log=tmp_path / "full.h5", pipeline=True, track_error=False)
    assert len(full.rounds) > stop_after
    # round 2 waited: every pixel's initial pass was in flight (round 1, its second half),
    # so round 2 was planned twice (the second time after round 1's commit)
    assert [e["round"] for e in full.timeline if e["phase"] == "plan"].count(2) == 2
    assert full.rounds[2]["samples"] > 4 * 240  # the noisy half's step (and its border row's, borrowed)
    log = tmp_path / "part.h5"
    adapt(r(), m, spp=40, seed=6, log=log, max_rounds=stop_after, pipeline=True, track_error=False)
    res = resume(log, r(), track_error=False)
    np.testing.assert_array_equal(res.image, full.image)
    a, b = read_log(log).read_all(), read_log(tmp_path / "full.h5").read_all()
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.values, b.values)


def test_which_initial_passes_the_driver_splits():
    from mcrecon.adaptive.schedule import _initial_rounds

    npix, budget = 16 * 12, 32 * 16 * 12
    for name, opts, rounds in (("box", {}, 1), ("splat", {}, 2), ("splat", {"initial_spp": 1}, 1), ("gem", {}, 2),
                               ("awr", {}, 2),
                               ("gem", {"initial_spp": 1}, 1), ("awr", {"initial_spp": 1}, 1), ("ci", {}, 2),
                               ("auto", {}, 2)):
        m = get_method(name, **opts)
        assert _initial_rounds(m, True, budget, npix) == rounds, name
        assert _initial_rounds(m, False, budget, npix) == 1, name


def test_no_plan_of_any_subclass_sees_empty_statistics():
    """The driver takes the initial pass itself: a subclass with a plan of its own (or a mixin's)
    is first asked for round 1 or later, with samples committed, pipelined or not."""
    from mcrecon.methods.box import BoxMethod
    from mcrecon.methods.ci.method import CIMethod

    seen = []

    class PlanMixin:
        def plan(self, run, state):
            seen.append((state.round_index, int(state.stats.count.sum())))
            return super().plan(run, state)

    class OwnBox(PlanMixin, BoxMethod):
        pass

    class OwnCI(PlanMixin, CIMethod):
        pass

    for m in (OwnBox(), OwnCI(min_spp=2, tolerance=1e-4)):
        for pipe in (False, True):
            seen.clear()
            adapt(_renderer(), m, spp=8, seed=1, pipeline=pipe)
            assert seen and all(n > 0 for _, n in seen) and seen[0][0] >= 1, (m, pipe, seen)


@pytest.mark.parametrize("method", ["box", "splat"])
def test_box_and_splat_are_bit_identical_with_and_without_the_lag(method):
    """Uniform doubling depends only on the sample count, which counts the round in flight
    (splat reads its schedule from the rounds observed plus the pending one; with N_0 = 1, whose
    initial pass the driver does not split)."""
    a = adapt(_renderer(), get_method(method, **OPTS[method]), spp=12.5, seed=4, pipeline=False)
    b = adapt(_renderer(), get_method(method, **OPTS[method]), spp=12.5, seed=4, pipeline=True)
    assert method_pipelines(get_method(method))
    assert b.pipelined and not a.pipelined
    assert [r["samples"] for r in a.rounds] == [r["samples"] for r in b.rounds]
    np.testing.assert_array_equal(a.image, b.image)
    np.testing.assert_array_equal(a.counts, b.counts)


class _Preparing:
    """A renderer with ``prepare`` (as the Mitsuba bridge): positions computed ahead, same replies."""

    def __init__(self, inner):
        self.inner, self.width, self.height, self.channels = inner, inner.width, inner.height, inner.channels
        self.prepared = []  # (round, thread)

    def prepare(self, req):
        import threading

        self.prepared.append((req.round_index, threading.current_thread().name))

    def render(self, req):
        return self.inner.render(req)


@pytest.mark.parametrize("method", ["box", "gem"])
def test_renderer_prepare_is_called_from_the_toolkit_thread_and_changes_nothing(method):
    opts = OPTS[method]
    plain = adapt(_renderer(), get_method(method, **opts), spp=12, seed=2, pipeline=True)
    r = _Preparing(_renderer())
    res = adapt(r, get_method(method, **opts), spp=12, seed=2, pipeline=True)
    np.testing.assert_array_equal(plain.image, res.image)
    assert [k for k, _ in r.prepared] == list(range(len(res.rounds)))
    # rounds >= 2 are planned (and prepared) while the round before renders: in the toolkit thread
    assert all(t.startswith("mcrecon-toolkit") for k, t in r.prepared if k >= 2)
    assert any(e["phase"] == "prepare" for e in res.timeline)
    # sequential runs do not call it
    r2 = _Preparing(_renderer())
    adapt(r2, get_method(method, **opts), spp=12, seed=2, pipeline=False)
    assert r2.prepared == []


@pytest.mark.parametrize("method", ["gem", "awr", "ci"])
def test_pipelined_runs_are_reproducible_and_fill_the_budget(method, tmp_path):
    m = get_method(method, **OPTS[method])
    assert not method_pipelines(m)  # gem, awr, ci: allowed, off by default (quality cost, changed rule)
    a = adapt(_renderer(), m, spp=12, seed=3, log=tmp_path / "a.h5", pipeline=True)
    b = adapt(_renderer(), m, spp=12, seed=3, pipeline=True)
    assert a.pipelined and read_log(tmp_path / "a.h5").run_settings["pipeline"] is True
    np.testing.assert_array_equal(a.image, b.image)
    assert [r["samples"] for r in a.rounds] == [r["samples"] for r in b.rounds]
    if method != "ci":  # ci may stop early: every pixel converged
        assert a.samples == 16 * 12 * 12 and a.stopped == "budget"
    assert a.samples <= 16 * 12 * 12
    assert sum(r["samples"] for r in a.rounds) == a.samples == read_log(tmp_path / "a.h5").n_samples


def test_pipeline_choice_is_validated_and_defaults_follow_the_method():
    assert method_pipelines(get_method("box")) and method_pipelines(get_method("splat"))
    assert not any(method_pipelines(get_method(m)) for m in ("awr", "gem", "ci", "auto"))
    assert adapt(_renderer(), get_method("awr", initial_spp=2), spp=4, pipeline=True).pipelined

    class NoLag(_Spy):  # a method whose plans need every round: sequential unless asked
        pipeline = False

    assert not adapt(_renderer(), NoLag(), spp=4).pipelined

    class Unclear(_Spy):  # the declaration is a bool, nothing else
        pipeline = "no"

    with pytest.raises(InputError, match="pipeline.*expected True"):
        adapt(_renderer(), Unclear(), spp=4)


# ------------------------------------------------------------------ exact shortcuts
def _intake(method, run, stats):
    """What _take_round reads of a run's context."""
    return types.SimpleNamespace(method=method, run=run, stats=stats, nonfinite="drop")


def test_one_pass_commit_equals_stats_add_bit_for_bit(rng):
    """The driver ingests the validated reply without re-checking it: the same statistics as stats.add."""
    pos = rng.random((5000, 2)) * [16, 12]
    val = rng.random((5000, 3)) * 1e3
    val[7, 1] = np.nan
    for dtype in (np.float32, np.float64):
        p, v = pos.astype(dtype), val.astype(dtype)
        m = get_method("box")
        a, b = PixelStats(16, 12, ("R", "G", "B")), PixelStats(16, 12, ("R", "G", "B"))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            a.add(p, v, nonfinite="drop")
            _take_round(_intake(m, None, b), SampleBatch(p, v), 0, source="x", n_nonfinite=1)
        for f in ("count", "mean", "m2", "min", "max"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
        assert a.n_dropped == b.n_dropped == 1


@pytest.mark.parametrize("n_bad", [0, 1])
def test_ingest_beside_observe_equals_one_after_the_other(rng, n_bad):
    """A helper thread ingests the round while splat observes it (n_bad = 0; with a NaN row the two run
    one after the other, the warning in the caller's thread): statistics and image as without it."""
    from concurrent.futures import ThreadPoolExecutor

    from mcrecon.errors import McreconWarning

    pos = np.ascontiguousarray(rng.random((20_000, 2)) * [16, 12])
    val = rng.random((20_000, 3)) * 1e3
    if n_bad:
        val[7, 1] = np.nan
    m = get_method("splat")
    runs, stats = [m.start(16, 12), m.start(16, 12)], [PixelStats(16, 12, ("R", "G", "B")) for _ in range(2)]
    with ThreadPoolExecutor(1) as helper:
        for run, st, h in zip(runs, stats, (None, helper)):
            with pytest.warns(McreconWarning) if n_bad else warnings.catch_warnings():
                _take_round(_intake(m, run, st), SampleBatch(pos, val), 0, source="x", n_nonfinite=n_bad, observe=h)
    for f in ("count", "mean", "m2", "min", "max"):
        np.testing.assert_array_equal(getattr(stats[0], f), getattr(stats[1], f))
    np.testing.assert_array_equal(runs[0].splatter.image, runs[1].splatter.image)
    assert stats[1].n_dropped == n_bad and runs[1].splatter.rounds == runs[0].splatter.rounds


def test_request_seed_without_revalidation_equals_dataclasses_replace():
    req = SampleRequest(8, 4, counts=np.ones((4, 8), np.int64), positions=np.array([[1.5, 2.5]]))
    a = dataclasses.replace(req, round_index=3, seed=2**63 + 1)
    b = _with_seed(req, 3, 2**63 + 1)
    assert (a.round_index, a.seed, a.total) == (b.round_index, b.seed, b.total) and req.seed == 0
    np.testing.assert_array_equal(a.counts, b.counts)
    np.testing.assert_array_equal(a.positions, b.positions)


def test_gem_plan_with_nothing_pending_is_the_plan_without_pending():
    from mcrecon.adaptive.schedule import Schedule, _adaptive_state, round_seeds

    st = PixelStats.from_samples(np.random.default_rng(0).random((3000, 2)) * [16, 12],
                                 np.random.default_rng(1).random((3000, 3)), width=16, height=12)
    m = get_method("gem")
    reqs = []
    for pending in (None, np.zeros((12, 16), np.int64)):
        rng, _ = round_seeds(0, 3)
        reqs.append(m.plan(m.start(16, 12), _adaptive_state(st, Schedule(budget=16 * 12 * 32, seed=0), 3, 3000,
                                                             rng, pending=pending)))
    np.testing.assert_array_equal(reqs[0].positions, reqs[1].positions)


# ------------------------------------------------------------------ stop and resume (in process)
@pytest.mark.parametrize("method, stop_after", [("gem", 1), ("gem", 2), ("gem", 4), ("awr", 1), ("awr", 3),
                                                ("ci", 2), ("box", 1), ("box", 3), ("splat", 1), ("splat", 2)])
def test_stopped_pipelined_run_resumes_bit_identically(tmp_path, method, stop_after):
    """Stopped after ``stop_after`` rounds (the next one was planned and in flight): the resume plans
    it again from the same statistics and ends where the uninterrupted run ends."""
    m = get_method(method, **OPTS[method])
    full = adapt(_renderer(), m, spp=12, seed=5, log=tmp_path / "full.h5", track_error=False, pipeline=True)
    assert len(full.rounds) > stop_after
    log = tmp_path / "stopped.h5"
    part = adapt(_renderer(), m, spp=12, seed=5, log=log, max_rounds=stop_after, track_error=False,
                 pipeline=True)
    assert part.stopped == "max_rounds" and read_log(log).n_rounds == stop_after
    res = resume(log, _renderer(), track_error=False)
    assert res.pipelined and res.samples == full.samples
    np.testing.assert_array_equal(res.image, full.image)
    a, b = read_log(log).read_all(), read_log(tmp_path / "full.h5").read_all()
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.values, b.values)


def test_faulty_reply_mid_pipeline_keeps_the_rounds_before_and_resumes(tmp_path):
    bad_round = 3

    def shade(pos, rng, req):
        val = rng.random((len(pos), 3))
        return val[:-1] if req.round_index == bad_round else val

    from mcrecon import RendererError

    m = get_method("gem", **OPTS["gem"])
    log = tmp_path / "run.h5"
    with pytest.raises(RendererError, match="rows but"):
        adapt(jittered_renderer(shade, width=16, height=12), m, spp=12, seed=2, log=log, pipeline=True)
    assert read_log(log).n_rounds == bad_round  # every round before the bad reply is committed


# ------------------------------------------------------------------ SIGKILL and resume
DRIVER = textwrap.dedent("""
    import os, sys
    from mcrecon.adaptive import adapt
    from mcrecon.methods.gem import GEMMethod
    from mcrecon.renderers.command import CommandRenderer

    log, marker, w, h, FAULT = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), sys.argv[5]

    class MarkedGEM(GEMMethod):
        # each plan is made by the toolkit thread after it committed the round before the
        # one in flight: "planned J" means the rounds <= J-2 are in the log
        def plan(self, run, state):
            req = super().plan(run, state)
            with open(marker, "a") as f:
                f.write(f"planned {state.round_index}\\n")
            return req

    r = CommandRenderer([sys.executable, FAULT, "ok", "-1", "{request}", "{reply}"], width=w, height=h)
    adapt(r, MarkedGEM(initial_spp=4, iterations=6), spp=16, seed=7, log=log, progress=False, track_error=False,
          pipeline=True)
""")


def _wait_for(path: Path, line: str, proc, timeout: float = 120.0) -> None:
    """Wait for a complete marker line (a safety deadline only: the writer is the event's own process)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.exists() and line + "\n" in path.read_text():
            return
        if proc.poll() is not None:
            pytest.fail(f"the run ended (status {proc.returncode}) before {line!r}: {proc.stderr.read()!r}")
        time.sleep(0.02)
    pytest.fail(f"no {line!r} within {timeout} s")


#: The round the renderer holds: 4 (killed with round 4 in flight); with MCRECON_FULL=1 also 2, the same path
#: two rounds earlier (about 6 CPU s: two interpreters and three runs).
HOLDS = [pytest.param(2, marks=pytest.mark.slow), 4] if os.environ.get("MCRECON_FULL", "") not in ("", "0") else [4]


@pytest.mark.parametrize("hold", HOLDS)
def test_sigkill_of_a_pipelined_run_then_resume_matches_uninterrupted(tmp_path, hold):
    """The renderer holds round ``hold`` (the driver blocks in that call); the toolkit thread then commits
    round hold-1 and plans round hold+1 ("planned hold+1"): killed there, the log holds rounds 0..hold-1
    and round ``hold`` was in flight.  The resume re-plans it and ends bit-identical to a run never killed."""
    w, h = 12, 8
    script = tmp_path / "driver.py"
    script.write_text(DRIVER)
    log, marker, rmarker = tmp_path / "killed.h5", tmp_path / "plans.txt", tmp_path / "rounds.txt"
    env = {**os.environ, "FAULT_RENDERER_MARKER": str(rmarker), "FAULT_RENDERER_HOLD": str(hold)}
    proc = subprocess.Popen([sys.executable, str(script), str(log), str(marker), str(w), str(h), FAULT],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    try:
        _wait_for(marker, f"planned {hold + 1}", proc)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        proc.stderr.close()
        if rmarker.exists():
            for line in rmarker.read_text().splitlines():
                try:
                    os.kill(int(line.split()[1]), signal.SIGKILL)  # the held renderer
                except (ProcessLookupError, IndexError, ValueError):
                    pass
    killed = read_log(log)
    assert killed.n_rounds == hold and len(killed.round_records) == hold
    assert killed.run_settings["pipeline"] is True

    def renderer():
        return CommandRenderer([sys.executable, FAULT, "ok", "-1", "{request}", "{reply}"], width=w, height=h)

    res = resume(log, renderer(), track_error=False)
    full = adapt(renderer(), get_method("gem", initial_spp=4, iterations=6), spp=16, seed=7,
                 log=tmp_path / "full.h5", track_error=False, pipeline=True)
    assert res.samples == full.samples == read_log(log).n_samples == w * h * 16
    np.testing.assert_array_equal(res.image, full.image)
    np.testing.assert_array_equal(read_log(log).read_all().positions,
                                  read_log(tmp_path / "full.h5").read_all().positions)


def test_cli_pipeline_flags(tmp_path, capsys):
    from mcrecon.cli import main

    common = ["adapt", "--scene", "flat", "--size", "12x8", "--spp", "8", "--quiet"]
    for flag, method in (("--pipeline", "box"), ("--no-pipeline", "box"), ("--pipeline", "gem"),
                         ("--pipeline", "splat")):
        log = tmp_path / f"{flag}{method}.h5"
        assert main(common + ["--method", method, flag, "--log", str(log), "-o", str(log.with_suffix(".exr"))]) == 0
        assert read_log(log).run_settings["pipeline"] is (flag == "--pipeline")
    capsys.readouterr()
    assert main(["adapt", "--resume", str(tmp_path / "--pipelinebox.h5"), "--no-pipeline", "-o",
                 str(tmp_path / "r.exr")]) == 2
    assert "--pipeline/--no-pipeline cannot change a recorded run" in capsys.readouterr().err


def test_pipelined_ci_never_exceeds_max_spp():
    # samples in flight count toward the cap: a pixel at max_spp - step with a step pending gets nothing more
    m = get_method("ci", min_spp=4, step_spp=4, max_spp=12, tolerance=1e-6)  # nothing converges: the cap binds
    res = adapt(_renderer(), m, spp=64, seed=2, pipeline=True, track_error=False)
    assert res.pipelined and res.stats.count.max() <= 12
    assert (res.stats.count == 12).mean() > 0.5  # most pixels reached the cap (constant ones stop), none beyond


def test_box_rounds_are_capped_and_still_bit_identical_with_the_lag():
    """Box doubles its rounds up to 1/8 of the budget in whole spp (the pipelined run's last commit is
    its unoverlapped tail); the floor that keeps small runs uncapped is lowered to see the cap here."""
    from mcrecon.methods.box import BoxMethod

    class SmallFloor(BoxMethod):
        max_round_floor = 0

    w, h = 16, 12
    a = adapt(_renderer(w, h), SmallFloor(), spp=40, seed=2, pipeline=False)
    b = adapt(_renderer(w, h), SmallFloor(), spp=40, seed=2, pipeline=True)
    assert [r["samples"] // (w * h) for r in a.rounds] == [1, 1, 2, 4, 5, 5, 5, 5, 5, 5, 2]  # cap: 40/8 = 5 spp
    assert [r["samples"] for r in a.rounds] == [r["samples"] for r in b.rounds] and b.pipelined
    np.testing.assert_array_equal(a.image, b.image)
    np.testing.assert_array_equal(a.counts, np.full((h, w), 40))
    # the default floor (2^20 samples) leaves small runs doubling
    assert [r["samples"] // (w * h) for r in adapt(_renderer(w, h), "box", spp=40, seed=2).rounds] == [1, 1, 2, 4, 8, 16, 8]


@pytest.mark.parametrize("name", ["awr", "auto", "gem"])
def test_a_pipelined_round_1_is_never_placed_from_empty_statistics(name):
    """Round 1 of a pipelined run is planned while round 0 renders: with nothing committed, it must
    be uniform counts (the driver's initial pass in two rounds), not positions chosen from empty
    statistics (awr used to put every sample of that round into the first rows)."""
    import numpy as np

    from mcrecon.adaptive.schedule import Schedule, _initial_rounds
    from mcrecon.methods import get_method
    from mcrecon.core.stats import PixelStats

    w = h = 32
    m = get_method(name)
    run = m.start(w, h)
    budget = 32 * w * h
    k = _initial_rounds(m, True, budget, w * h)
    schedule = Schedule(budget=budget, seed=1, initial_rounds=k)
    r0, _ = schedule.plan(m, run, PixelStats(w, h), 0, 0)
    r1, _ = schedule.plan(m, run, PixelStats(w, h), 1, r0.total, pending=r0.counts)
    assert r0.positions is None and r1.positions is None
    assert r1.counts.max() - r1.counts.min() <= 1
    assert r0.total + r1.total == m.option_default("initial_spp") * w * h


@pytest.mark.parametrize("pipeline", [False, True])
def test_a_placement_of_no_positions_asks_for_nothing(pipeline):
    """place() returning an empty (0, 2) array is a round of nothing: the run ends (or, pipelined, waits
    for the round in flight first), never an invalid request."""
    class Nowhere(_Spy):
        def place(self, run, state, n):
            return np.zeros((0, 2))

    res = adapt(_renderer(), Nowhere(), spp=4, seed=1, pipeline=pipeline)
    assert res.stopped == "converged" and res.samples == 16 * 12

"""The adaptive driver's run context: one object built by one path for adapt and resume, and no function of
the driver that threads the run through a long list of parameters."""

from __future__ import annotations

import ast
import time
from pathlib import Path

import numpy as np
import pytest

from mcrecon.adaptive import context as context_mod
from mcrecon.adaptive.context import RunClock, RunContext
from mcrecon.adaptive.run import adapt, resume

from helpers import jittered_renderer

ADAPTIVE = Path(__file__).resolve().parents[1] / "mcrecon" / "adaptive"
#: The most parameters a function of mcrecon/adaptive/ may take (``self``/``cls`` not counted).
MAX_PARAMETERS = 8
#: Public entry points whose keyword-only options are the documented API (each a flag of `mcrecon adapt`),
#: not state handed from one step of the run to the next: counted without those options.
PUBLIC_OPTIONS = {("run.py", "adapt")}


def _parameter_counts():
    """(file, function, parameters, keyword-only parameters) of every function in mcrecon/adaptive/."""
    for path in sorted(ADAPTIVE.glob("*.py")):
        def visit(node, in_class):
            for child in ast.iter_child_nodes(node):
                if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    a = child.args
                    names = [x.arg for x in a.posonlyargs + a.args]
                    if in_class and names and names[0] in ("self", "cls"):
                        names = names[1:]
                    n_kw = len(a.kwonlyargs)
                    yield (path.name, child.name, len(names) + n_kw + bool(a.vararg) + bool(a.kwarg), n_kw)
                    yield from visit(child, False)
                else:
                    yield from visit(child, isinstance(child, ast.ClassDef) or in_class)
        yield from visit(ast.parse(path.read_text()), False)


def test_no_function_of_the_driver_takes_more_than_eight_parameters():
    counts = list(_parameter_counts())
    assert len(counts) > 40  # the files were read
    over = [(f, name, n) for f, name, n, n_kw in counts
            if n - (n_kw if (f, name) in PUBLIC_OPTIONS else 0) > MAX_PARAMETERS]
    assert over == [], f"functions over {MAX_PARAMETERS} parameters (pass the RunContext instead): {over}"
    public = {(f, name): (n, n_kw) for f, name, n, n_kw in counts if (f, name) in PUBLIC_OPTIONS}
    assert set(public) == PUBLIC_OPTIONS and all(n - n_kw <= 3 for n, n_kw in public.values())


def test_the_loops_take_the_context_and_nothing_else_of_the_run():
    import inspect

    from mcrecon.adaptive import rounds

    for fn in (rounds._loop_sequential, rounds._loop_pipelined):
        assert list(inspect.signature(fn).parameters) == ["ctx", "rnd", "writes"]


# ------------------------------------------------------------------ one path for adapt and resume
W, H = 12, 8


def _renderer():
    def shade(pos, rng, req):
        return np.repeat(0.2 + 0.6 * (pos[:, :1] > W / 2), 3, axis=1) * rng.uniform(0.5, 1.5, (len(pos), 1))

    return jittered_renderer(shade, width=W, height=H, name="context test")


@pytest.fixture
def assembled(monkeypatch):
    """Every RunContext the driver assembles, in order."""
    made = []
    real = RunContext.assemble.__func__

    def spy(cls, *a, **kw):
        made.append(real(cls, *a, **kw))
        return made[-1]

    monkeypatch.setattr(RunContext, "assemble", classmethod(spy))
    return made


@pytest.mark.parametrize("pipeline", [False, True])
def test_adapt_and_resume_assemble_the_same_run_once_each(tmp_path, assembled, pipeline):
    log = tmp_path / "run.h5"
    ref = np.full((H, W, 3), 0.5)
    adapt(_renderer(), "gem", spp=12, seed=3, log=log, pipeline=pipeline, max_rounds=3, reference=ref,
          time_limit=1e6, nonfinite="zero", progress=False)
    res = resume(log, _renderer(), progress=False)
    assert len(assembled) == 2
    new, resumed = assembled
    for field in ("budget", "seed", "initial_rounds", "pipeline", "time_limit"):
        assert getattr(new.schedule, field) == getattr(resumed.schedule, field), field
    np.testing.assert_array_equal(new.reference, resumed.reference)
    assert (new.nonfinite, new.storage_dtype, resumed.storage_dtype) == ("zero", "auto", "float64")
    assert new.schedule.max_rounds == 3 and resumed.schedule.max_rounds == 10_000  # a session's own choice
    # the resumed context starts where the first session stopped: its rounds, index and wall time
    assert resumed.round_index == 3 == res.resumed_rounds and resumed.rounds is res.rounds
    assert resumed.clock.elapsed == pytest.approx(res.rounds[2]["wall_seconds"])
    assert resumed.clock.new_rounds == len(res.rounds) - 3 > 0
    full = adapt(_renderer(), "gem", spp=12, seed=3, pipeline=pipeline, nonfinite="zero", progress=False)
    np.testing.assert_array_equal(res.image, full.image)
    assert [r["samples"] for r in res.rounds] == [r["samples"] for r in full.rounds]


def test_the_result_accounts_from_the_clock(assembled):
    res = adapt(_renderer(), "box", spp=16, seed=1, progress=False)
    clock = assembled[0].clock
    assert clock.new_rounds == len(res.rounds) and res.resumed_rounds == 0
    assert res.toolkit_cpu_seconds >= clock.toolkit_cpu > 0
    assert 0 <= clock.render_seconds <= res.loop_seconds and res.idle_seconds >= 0
    assert res.timeline is clock.timeline.events and {e["phase"] for e in res.timeline} >= {"plan", "render"}


def test_run_clock_goes_on_from_the_sessions_before_and_leaves_out_what_is_excluded():
    clock = RunClock(elapsed=100.0)
    clock.start()
    assert 100.0 <= clock.wall() < 101.0
    assert clock.past(50.0) and not clock.past(None) and not clock.past(1e9)
    before = clock.wall()
    clock.exclude(30.0)
    assert clock.wall() == pytest.approx(before - 30.0, abs=0.5)
    t0 = time.perf_counter()
    clock.start()  # a session starts: the wall clock from ``elapsed`` again, a new timeline
    assert clock.wall() <= 100.0 + (time.perf_counter() - t0) + 1e-3 and clock.timeline.events == []


def test_the_context_module_draws_what_the_class_holds():
    """The diagram at the top of context.py names every field of RunContext."""
    import dataclasses

    doc = context_mod.__doc__
    for f in dataclasses.fields(RunContext):
        assert f.name in doc, f.name

"""The run context: one adaptive run's parts, assembled once by :func:`adapt` and by :func:`resume`.

::

    RunContext
     |- renderer, method, run (RunState), stats (PixelStats)
     |- schedule   Schedule: budget, seed, initial pass, reference, max_rounds, time limit, pipeline
     |- log_path, nonfinite, storage_dtype          where and how rounds are committed
     |- rounds, round_index, planned                 what the run holds before this session
     |- rendered   per pixel, the samples committed (NaN/Inf included): each request's first_index
     |- strata     PrefixHalves of the committed samples (methods with stratified_gain on): the plans' gain
     |- feature_layout  the features of the rounds of a method that reads no statistics (they keep none)
     |- sampler    what the renderer's samples of a pixel are (Renderer.sampler): the plans' AdaptiveState.sampler
     |- sampler_known, sampler_checked              whether a reply or the log decided it; whether replies must agree
     |- track_error, eps, on_round, bar             what this session's caller asked for
     `- clock      RunClock: wall time over sessions, renderer seconds, toolkit CPU,
                   rounds finished this session, the timeline of phases

:meth:`RunContext.assemble` is the one path from recorded run settings to a
context: a new run passes the settings it records, a resume the settings
its log recorded and the log itself, so the two cannot assemble a run
differently.  The loops (:mod:`.rounds`) read and account through the
context; nothing is threaded through their parameters.
"""

from __future__ import annotations

import contextlib
import dataclasses
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from .._lazy import public_dir as _public_dir
from ..core.stats import PixelStats
from ..core.requests import check_sampler
from ..core.strata import PrefixHalves
from ..errors import InputError, RendererError
from ..io.logformat import MAX_PIXELS
from ..methods.base import Method, RunState
from .schedule import Committed, Schedule, _committed, _initial_rounds

__all__ = ["RunContext", "RunClock", "SessionOptions"]


def _renderer_name(renderer) -> str:
    return str(getattr(renderer, "name", type(renderer).__name__))


def _check_renderer(renderer):
    """(width, height, channels) of a renderer, refused where it cannot be a film."""
    for attr in ("width", "height", "channels", "render"):
        if not hasattr(renderer, attr):
            raise InputError("renderer", attr, "missing: a renderer needs width, height, channels and "
                             "render(request) (see mcrecon.renderers.protocol.Renderer)")
    w, h = int(renderer.width), int(renderer.height)
    if w < 1 or h < 1:
        raise InputError("renderer", "width/height", f"{w}x{h}, expected at least 1x1")
    if w * h > MAX_PIXELS:
        raise InputError("renderer", "width/height", f"{w}x{h} = {w * h} pixels, beyond the {MAX_PIXELS} pixels "
                         "mcrecon can hold images of")
    if getattr(renderer, "sampler", None) is not None:  # declared up front: refused before anything renders
        check_sampler(renderer.sampler, where=f"renderer {_renderer_name(renderer)}")
    return w, h, tuple(str(c) for c in renderer.channels)


class _Progress:
    """Per-round progress on stderr: one line redrawn on a terminal, a line per event otherwise (forced on)."""

    def __init__(self, enabled: bool | None, budget: int):
        tty = sys.stderr.isatty()
        self.enabled = tty if enabled is None else bool(enabled)
        self.tty = tty
        self.budget = max(budget, 1)
        self.n, self.wall = 0, 0.0

    def _write(self, text: str):
        sys.stderr.write(f"\r{text}\033[K" if self.tty else f"{text}\n")
        sys.stderr.flush()

    def _bar(self, n: int) -> str:
        frac = min(n / self.budget, 1.0)
        return f"[{'#' * int(30 * frac):<30}] {100 * frac:5.1f}%"

    def rendering(self, rnd: int, samples: int):
        # said when a round starts: a long round (or a run of one round) is not silent until its end
        if self.enabled:
            self._write(f"{self._bar(self.n)}  round {rnd}: rendering {samples} samples  ({self.wall:.1f} s so far)")

    def update(self, n: int, rnd: int, wall: float):
        self.n, self.wall = n, wall
        if self.enabled:
            self._write(f"{self._bar(n)}  round {rnd}  {n} samples  {wall:6.1f} s")

    def close(self):
        if self.enabled and self.tty:
            sys.stderr.write("\n")
            sys.stderr.flush()


class _Timeline:
    """Wall interval and thread CPU time of each phase of the loop (a few per round: negligible cost)."""

    def __init__(self):
        self.t0 = time.perf_counter()
        self.events = []
        self._renderer_thread = threading.get_ident()

    @contextlib.contextmanager
    def phase(self, name, round_index, **extra):
        t, c = time.perf_counter(), time.thread_time()
        try:
            yield extra
        finally:
            self.add(name, round_index, t, time.perf_counter(), time.thread_time() - c, **extra)

    def add(self, name, round_index, start, end, cpu, **extra):
        self.events.append({"phase": name, "round": int(round_index), "start": start - self.t0,
                            "end": end - self.t0, "cpu": cpu,
                            "thread": "renderer" if threading.get_ident() == self._renderer_thread else "toolkit",
                            **extra})


class RunClock:
    """A run's wall clock over its sessions, and what this session spent.

    The run's wall time is this session's time since :meth:`start` plus
    the ``elapsed`` seconds of the sessions before it, less the seconds
    :meth:`exclude` took out (the error after each round is not part of
    the run's time).

    Attributes
    ----------
    elapsed : float
        Wall seconds of the sessions before this one (a resume's).
    render_seconds : float
        Seconds the renderer rendered in this session (what it reports as its own, at most its calls).
    toolkit_cpu : float
        CPU seconds of the toolkit's work in the threads of the loop (helpers' phases are on the timeline).
    new_rounds : int
        Rounds this session finished (committed and recorded).
    timeline : _Timeline
        The phases of this session's loop.
    """

    def __init__(self, elapsed: float = 0.0):
        self.elapsed = float(elapsed)
        self.render_seconds = 0.0
        self.toolkit_cpu = 0.0
        self.new_rounds = 0
        self._wall_start = time.perf_counter() - self.elapsed
        self.timeline = _Timeline()

    def start(self) -> None:
        """The session's loop starts now: the wall clock goes on from ``elapsed``, the timeline from 0."""
        self._wall_start = time.perf_counter() - self.elapsed
        self.timeline = _Timeline()

    def wall(self) -> float:
        """The run's wall seconds now."""
        return time.perf_counter() - self._wall_start

    def exclude(self, seconds: float) -> None:
        """Take ``seconds`` (spent outside the run's time) out of the wall clock."""
        self._wall_start += seconds

    def past(self, limit: float | None) -> bool:
        """Whether the run's wall time has reached ``limit`` (never, without one)."""
        return limit is not None and self.wall() >= limit


@dataclasses.dataclass(frozen=True)
class SessionOptions:
    """What the caller of one session chooses: not recorded with the run, may differ on a resume.

    ``time_limit`` None: the recorded one.
    """

    progress: bool | None = None
    time_limit: float | None = None
    track_error: bool = True
    eps: float = 0.01
    max_rounds: int = 10_000
    on_round: Callable[[dict], Any] | None = None


@dataclasses.dataclass(eq=False)
class RunContext:
    """One adaptive run: its parts, its schedule and its accounting (see the module's diagram).

    Built by :meth:`assemble` only.  ``rounds`` holds the records of the
    committed rounds (the earlier sessions' first, then this session's);
    ``round_index`` is the index of this session's first round, ``planned``
    the plan a pipelined resume made again for it (None: plan it).
    """

    renderer: Any
    method: Method
    run: RunState
    stats: PixelStats
    schedule: Schedule
    log_path: Path | None
    nonfinite: str
    storage_dtype: str
    rounds: list
    round_index: int
    track_error: bool
    eps: float
    on_round: Callable[[dict], Any] | None
    bar: _Progress
    clock: RunClock
    planned: tuple | None = None
    rendered: np.ndarray | None = None
    strata: PrefixHalves | None = None
    #: ``{name: components}`` of the features a method that reads no statistics gets with its rounds
    #: (the statistics keep none for it); None until the first round says which the renderer sends.
    feature_layout: dict | None = None
    #: The renderer's sampler (:data:`~mcrecon.core.requests.SAMPLERS`) every plan sees; ``sampler_known``:
    #: decided (recorded in the run settings, or a reply came), ``sampler_checked``: later replies must agree.
    sampler: str = "independent"
    sampler_known: bool = False
    sampler_checked: bool = True

    def __post_init__(self):
        if self.rendered is None:
            self.rendered = np.zeros((self.stats.height, self.stats.width), np.int64)
        # only for a method that reads them (requires.prefix_halves) or may plan in whole nets (net_counts:
        # the net gate of mcrecon.core.nets.net_plan); the sums cost 3 x 8 bytes per pixel and channel
        if self.strata is None and (self.method.requires.prefix_halves or self.method.params.get("net_counts", 0)):
            self.strata = PrefixHalves(self.stats.width, self.stats.height, len(self.stats.channels))

    @classmethod
    def assemble(cls, renderer, method, settings: Mapping, *, reference, log_path, session: SessionOptions,
                 resumed=None) -> "RunContext":
        """The context of a run from its settings (what :func:`adapt` records in its log).

        Parameters
        ----------
        renderer, method
            Checked already: the renderer against the settings' film.
        settings : mapping
            The run settings (``spp``, ``seed``, ``nonfinite``, ``time_limit``, ``width``, ``height``,
            ``channels``, ``storage_dtype``, ``pipeline``).
        reference : ndarray (H, W, C) or None
        log_path : Path or None
        session : SessionOptions
        resumed : SampleLog, optional
            The log a resume continues: its committed rounds' records, their count and, once it holds
            samples, its storage precision.  The statistics stay empty: the resume replays the rounds.
        """
        w, h, channels = int(settings["width"]), int(settings["height"]), tuple(settings["channels"])
        budget = int(round(float(settings["spp"]) * w * h))
        pipeline = bool(settings.get("pipeline", False))  # logs of runs before pipelining: sequential
        schedule = Schedule(budget=budget, seed=int(settings["seed"]),
                            initial_rounds=_initial_rounds(method, pipeline, budget, w * h), reference=reference,
                            max_rounds=session.max_rounds,
                            time_limit=(session.time_limit if session.time_limit is not None
                                        else settings.get("time_limit")),
                            pipeline=pipeline)
        storage_dtype = settings.get("storage_dtype", "float32")
        rounds = []
        if resumed is not None:
            rounds = list(resumed.round_records)
            if resumed.n_samples:
                storage_dtype = str(resumed.value_dtype)
        stats = PixelStats(w, h, channels, subpixels=method.requires.subpixels)
        run = method.start(w, h, channels, reference=reference)
        # the sampler decided by the run's first reply, or its log's record; a log of a run before renderers
        # declared one had independent plans: it keeps them whatever its renderer declares now
        recorded, legacy = settings.get("sampler"), resumed is not None and resumed.n_rounds > 0
        sampler = dict(sampler=check_sampler(recorded, where=str(log_path), field="run settings sampler"),
                       sampler_known=recorded is not None or legacy, sampler_checked=not legacy or recorded is not None)
        return cls(renderer=renderer, method=method, run=run, stats=stats, schedule=schedule, log_path=log_path,
                   nonfinite=settings["nonfinite"], storage_dtype=storage_dtype, rounds=rounds,
                   round_index=0 if resumed is None else resumed.n_rounds,
                   track_error=session.track_error, eps=session.eps, on_round=session.on_round,
                   bar=_Progress(session.progress, budget),
                   clock=RunClock(float(rounds[-1]["wall_seconds"]) if rounds else 0.0), **sampler)

    @property
    def committed(self) -> Committed:
        """The committed samples' prefix halves and the renderer's sampler, as the plans see them."""
        return Committed(self.strata, self.sampler)

    @property
    def name(self) -> str:
        """The renderer's name (in errors and warnings about its replies)."""
        return _renderer_name(self.renderer)

    @property
    def reference(self) -> np.ndarray | None:
        return self.schedule.reference

    def start(self) -> None:
        """This session's loop starts: the clock runs, the progress bar starts from what is committed."""
        self.clock.start()
        self.bar.n, self.bar.wall = _committed(self.stats), self.clock.elapsed

    def note_sampler(self, round_index: int) -> str | None:
        """The renderer's sampler after a reply (its ``sampler`` attribute, which a command renderer takes from
        its reply files): the first reply of a run decides it (returned then, for the run settings: None
        otherwise), every later one must declare the same (a :class:`RendererError` names the round)."""
        own = check_sampler(getattr(self.renderer, "sampler", None), where=self.name)
        if not self.sampler_known:
            self.sampler, self.sampler_known = own, True
            return own
        if self.sampler_checked and own != self.sampler:
            raise RendererError(self.name, "sampler", f"declares {own!r} in round {round_index}, the run's first "
                                f"reply {self.sampler!r}: a run keeps one sampler (resume it with the same renderer)")
        return None

    def plan(self, round_index: int, *, in_flight: int = 0, pending=None):
        """The plan of round ``round_index`` from what is committed, with ``in_flight`` samples (``pending``,
        per pixel) requested and not committed yet: see :meth:`Schedule.plan`.

        The request's ``first_index`` is each pixel's committed samples plus those in flight: the
        renderer's sequence of a pixel goes on where the rounds before it (committed or rendering) end,
        the same in a resume (its replay counts the log's rounds) as in the live run."""
        first = self.rendered if pending is None else self.rendered + pending
        return self.schedule.plan(self.method, self.run, self.stats, round_index, _committed(self.stats) + in_flight,
                                  pending=pending, first_index=first, committed=self.committed)


__dir__ = _public_dir(__name__)

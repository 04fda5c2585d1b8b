"""The adaptive driver: rounds of plan -> request -> render -> validate -> commit.

:func:`adapt` runs an adaptive (or uniform) sampling run against any
renderer (:class:`~mcrecon.renderers.protocol.Renderer`): an in-process callable,
a built-in scene, an out-of-process command or Mitsuba.  Each round is
validated and committed to the sample log *before* the statistics and
the method see it, so a run killed at any point resumes from its log
(:func:`resume`) without losing a committed sample.

Randomness is derived from ``(seed, round index)``: the method's
decisions use ``default_rng([seed, round, 1])`` and the renderer gets
the seed ``SeedSequence([seed, round, 2])``.  A resumed run therefore
takes exactly the decisions the uninterrupted run would have taken.

The driver owns the schedule: it takes the uniform initial pass itself
(``Method.initial_pass``), so a method's ``plan`` never sees empty
statistics.  Pipelined rounds (``adapt(..., pipeline=True)``, the default
for methods that declare ``pipeline = True``): while the renderer renders
round k+1 in the calling thread, one toolkit thread validates and commits
round k (log append, statistics, ``observe``) and plans round k+2 from the
rounds <= k.  A plan therefore sees the rounds <= j-2 and, as
``state.pending``, the per-pixel counts of the round in flight; never
anything that depends on timing.  The initial pass is split in two rounds
(half, then the rest, both the driver's) when it has two or more samples
per pixel, so the first plan sees its first half; a pass of one sample per
pixel is committed before the first plan.  A plan that asks for nothing
while a round is in flight waits for it: the driver commits that round and
plans again.  A pipelined run is reproducible from
its seed and resumes bit-identically (the resume re-plans the round that
was in flight from the same statistics); the run settings record
``pipeline`` so a resume continues the same way.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import math
import sys
import threading
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from .errors import InputError, McreconWarning, RendererError
from .io.samplelog import (MAX_PIXELS, append_log, cast_positions, log_lock, read_log, set_run_settings,
                           update_round_record, write_log)
from .methods import Method, get_method
from .methods.base import AdaptiveState, RunState, uniform_counts
from .renderers.protocol import SampleBatch, _validate_reply
from .renderers.spec import renderer_from_spec
from .samples import (FLOAT32_MAX, NONFINITE_POLICIES, apply_nonfinite, check_memory, check_reference,
                      float32_loses_spread)
from .stats import PixelStats

__all__ = ["adapt", "resume", "AdaptiveResult", "round_seeds", "STORAGE_DTYPES", "method_pipelines"]

#: Precisions a run's log can store samples in (see :func:`adapt`).
STORAGE_DTYPES = ("auto", "float32", "float64")


@dataclasses.dataclass(eq=False)
class AdaptiveResult:
    """Outcome of an adaptive run.

    Attributes
    ----------
    image : ndarray (H, W, C) float64
    stats : PixelStats
        Statistics of every committed sample.
    rounds : list of dict
        Per round: ``round``, ``samples`` (this round), ``samples_total``,
        ``renderer_seconds``, ``toolkit_seconds``, ``wall_seconds``
        (cumulative run time, over the sessions of a resumed run; renderer +
        toolkit when sequential, less when pipelined: they overlap), ``error`` (relative MSE of the
        image after the round, when a reference is given) and
        ``eval_seconds`` (time to compute that error, not counted in the
        toolkit time).
    stopped : str
        Why the run ended: ``budget``, ``converged`` (the method's target),
        ``time_limit`` or ``max_rounds``.
    log : Path or None
    method : Method
    run : RunState
        The method's state of this run (``method.diagnostics(result.run)``).

    Samples are counted one way everywhere (the printed summary, ``mcrecon
    info``, the round records, the budget): :attr:`samples` is what the
    renderer delivered and the log committed, of which :attr:`samples_dropped`
    (NaN/Inf under the ``drop`` policy) the statistics do not hold;
    :attr:`samples_used` = samples - samples_dropped.
    """

    image: np.ndarray
    stats: PixelStats
    rounds: list
    stopped: str
    log: Path | None
    method: Method
    run: RunState
    #: Whether the rounds were pipelined (see :func:`adapt`).
    pipelined: bool = False
    #: Rounds committed before this call (by the sessions a :func:`resume` continues):
    #: ``rounds[resumed_rounds:]`` are this session's, those the times below describe.
    resumed_rounds: int = 0
    #: Wall seconds of the adaptive loop (first request to last commit; the final
    #: image is not part of it) and the part of them the renderer was not
    #: rendering: waiting for a plan or a commit (this process's rounds only).
    loop_seconds: float = 0.0
    idle_seconds: float = 0.0
    #: CPU seconds of the threads doing the toolkit's work (validation, commit,
    #: statistics, planning; the filtering pool's helper threads not counted).
    toolkit_cpu_seconds: float = 0.0
    #: Seconds of the final reconstruction (``method.finish``).
    finish_seconds: float = 0.0
    #: The loop's phases in order of their end, for profiling: dicts with ``phase``
    #: (``render``, ``validate``, ``append``, ``ingest``, ``observe``, ``plan``,
    #: ``prepare`` (the renderer's, pipelined runs), ``evaluate``), ``round``, ``start`` and ``end`` (wall seconds from the
    #: loop's start), ``cpu`` (CPU seconds of the thread that ran it) and
    #: ``thread`` (``renderer`` or ``toolkit``); ``render`` also has ``own``, the
    #: seconds the renderer reports as its own.
    timeline: list = dataclasses.field(default_factory=list)

    def diagnostics(self) -> dict:
        """The method's diagnostic maps of this run."""
        return dict(self.method.diagnostics(self.run))

    @property
    def counts(self) -> np.ndarray:
        """Samples per pixel (H, W)."""
        return self.stats.count

    @property
    def samples(self) -> int:
        """Samples the renderer delivered and the run committed (what the budget counts)."""
        return int(self.stats.n_samples + self.stats.n_dropped)

    @property
    def samples_dropped(self) -> int:
        """Committed samples with a NaN or Inf value the ``drop`` policy left out of the statistics."""
        return int(self.stats.n_dropped)

    @property
    def samples_used(self) -> int:
        """Committed samples in the statistics (``zero``-policy samples included, set to 0)."""
        return int(self.stats.n_samples)

    def sanity(self) -> dict:
        """Output sanity of the image (see :func:`mcrecon.metrics.output_sanity`)."""
        from .metrics import output_sanity

        return output_sanity(self.image, self.stats)

    @property
    def renderer_seconds(self) -> float:
        return float(sum(r["renderer_seconds"] for r in self.rounds))

    @property
    def toolkit_seconds(self) -> float:
        return float(sum(r["toolkit_seconds"] for r in self.rounds))


def round_seeds(seed: int, round_index: int) -> tuple[np.random.Generator, int]:
    """(decision RNG, renderer seed) of a round, derived from the run seed."""
    rng = np.random.default_rng([int(seed), int(round_index), 1])
    renderer_seed = int(np.random.SeedSequence([int(seed), int(round_index), 2]).generate_state(1)[0])
    return rng, renderer_seed


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


def _renderer_name(renderer) -> str:
    return str(getattr(renderer, "name", type(renderer).__name__))


def _check_renderer(renderer):
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
    return w, h, tuple(str(c) for c in renderer.channels)


def adapt(renderer, method, *, spp: float, seed: int = 0, log=None, reference=None,
          time_limit: float | None = None, progress: bool | None = None, nonfinite: str = "drop",
          max_rounds: int = 10_000, track_error: bool = True, eps: float = 0.01,
          metadata: Mapping | None = None, renderer_spec: Mapping | None = None,
          overwrite: bool = False, storage_dtype: str = "auto",
          on_round: Callable[[dict], Any] | None = None, pipeline: bool | None = None) -> AdaptiveResult:
    """Run adaptive rounds until the budget, the method's target or a time limit.

    Parameters
    ----------
    renderer : Renderer
        Answers :class:`~mcrecon.renderers.protocol.SampleRequest` s.
    method : str or Method
        A registered method name or an instance.
    spp : float
        Sample budget as average samples per pixel (total = round(spp * W * H)).
    seed : int
        Run seed: the whole run is reproducible from it.
    log : path-like, optional
        Sample log to create; every round is committed to it before the
        next request.  Refused if it exists, unless ``overwrite``.
    reference : ndarray (H, W, C), optional
        Ground truth for the per-round error (and oracle modes).
    time_limit : float, optional
        Wall seconds; no new round starts after it.
    progress : bool, optional
        Progress bar on stderr; default: only on a terminal.
    nonfinite : {'drop', 'zero', 'raise'}
        Policy for NaN/Inf sample values (see :mod:`mcrecon.stats`); with
        ``raise`` a reply holding one is refused before it is committed.
    track_error : bool
        Reconstruct after every round to record its error (needs a
        reference; excluded from the toolkit time).
    renderer_spec : mapping, optional
        How to recreate the renderer (stored with the run for ``--resume``).
    storage_dtype : {'auto', 'float32', 'float64'}
        Precision of the stored positions and values.  ``auto`` (default)
        stores what the renderer sends: float32 replies as float32,
        float64 (and integer) replies as float64, decided on the first
        reply.  The statistics ingest exactly the stored numbers, so a
        resumed run sees what the uninterrupted one saw; without a log
        they ingest the replies in their own precision.  With ``float32``
        and float64 replies, a round whose values exceed float32's range is
        refused before it is stored, and a warning (once per run) counts
        pixels whose spread float32 cannot hold (1e6 +- 1e-3).
    pipeline : bool, optional
        Pipelined rounds: the renderer renders round k+1 while a toolkit
        thread commits round k and plans round k+2 from the rounds <= k
        (one round of lag, the same in every run: reproducible and
        resumable).  Default: what the method declares
        (:func:`method_pipelines`).  Recorded in the run settings.
        A pipelined run hands each reply to the toolkit thread while the
        renderer answers the next request: a renderer must not modify a
        reply's arrays after ``render`` returned them.  A renderer with a
        ``prepare(request)`` method (optional; the Mitsuba bridge computes
        its jittered positions there) has it called from the toolkit thread
        right after a round is planned there, while it renders the round
        before (rounds planned in the caller's thread -- round 0, a re-plan
        after a plan that waited -- and a resume's first round are not
        prepared); ``render(request)`` must return the same reply with or
        without it.

    Returns
    -------
    AdaptiveResult
    """
    if not isinstance(method, Method):
        method = get_method(str(method))
    w, h, channels = _check_renderer(renderer)
    if not (isinstance(spp, (int, float, np.number)) and math.isfinite(spp) and spp > 0):
        raise InputError("adapt", "spp", f"got {spp!r}, expected a positive number of samples per pixel")
    if nonfinite not in NONFINITE_POLICIES:
        raise InputError("adapt", "nonfinite", f"got {nonfinite!r}; valid: {', '.join(NONFINITE_POLICIES)}")
    if time_limit is not None and not time_limit > 0:
        raise InputError("adapt", "time_limit", f"got {time_limit!r}, expected seconds > 0")
    ref = check_reference(reference, (h, w, len(channels)))
    if storage_dtype not in STORAGE_DTYPES:
        raise InputError("adapt", "storage_dtype", f"got {storage_dtype!r}; valid: {', '.join(STORAGE_DTYPES)}")
    if float(spp) * w * h >= 2.0 ** 62:
        raise InputError("adapt", "spp", f"{spp} samples per pixel on {w}x{h} is beyond any budget "
                         "(at most 2^62 samples)")
    budget = int(round(float(spp) * w * h))
    if pipeline is None:
        pipeline = method_pipelines(method)
    elif pipeline not in (True, False):
        raise InputError("adapt", "pipeline", f"got {pipeline!r}, expected True, False or None (the method's choice)")
    settings = {
        "method": method.name, "method_options": dict(method.params), "spp": float(spp), "seed": int(seed),
        "nonfinite": nonfinite, "time_limit": time_limit, "width": w, "height": h,
        "channels": list(channels), "renderer": _renderer_name(renderer),
        "renderer_spec": dict(renderer_spec or {}), "storage_dtype": storage_dtype,
        "pipeline": bool(pipeline),
    }
    log_path = None
    held = contextlib.ExitStack()
    if log is not None:
        log_path = Path(log)
        # The run holds its log's writer lock from creation to the end: a second run or
        # a resume on the same log is refused (naming this process), see log_lock.
        held.enter_context(log_lock(log_path))
    with held:
        return _start(renderer, method, w=w, h=h, channels=channels, ref=ref, budget=budget, settings=settings,
                      seed=seed, log_path=log_path, overwrite=overwrite, metadata=metadata, storage_dtype=storage_dtype,
                      time_limit=time_limit, progress=progress, nonfinite=nonfinite, max_rounds=max_rounds,
                      track_error=track_error, eps=eps, on_round=on_round, pipeline=bool(pipeline))


def _start(renderer, method, *, w, h, channels, ref, budget, settings, seed, log_path, overwrite, metadata,
           storage_dtype, time_limit, progress, nonfinite, max_rounds, track_error, eps, on_round, pipeline):
    if log_path is not None:
        if log_path.exists() and not overwrite:
            raise InputError(str(log_path), "file", "exists; resume it with --resume / mcrecon.driver.resume, "
                             "or choose another path")
        meta = {"renderer": _renderer_name(renderer), "seed": int(seed), **dict(metadata or {}),
                "settings": settings}
        # ``auto`` creates float32 datasets; the first reply may turn them into float64
        # (the log is still empty then, see _resolve_storage).
        placeholder = "float32" if storage_dtype == "auto" else storage_dtype
        write_log(log_path, np.zeros((0, 2), placeholder), np.zeros((0, len(channels)), placeholder),
                  width=w, height=h, channels=channels, reference=ref, metadata=meta)
        set_run_settings(log_path, settings)
    stats = PixelStats(w, h, channels, subpixels=method.requires.subpixels)
    run = method.start(w, h, channels, reference=ref)
    return _run(renderer, method, run, stats=stats, rounds=[], round_index=0, budget=budget, seed=int(seed),
                log_path=log_path, ref=ref, time_limit=time_limit, progress=progress, nonfinite=nonfinite,
                max_rounds=max_rounds, track_error=track_error, eps=eps, elapsed=0.0, on_round=on_round,
                storage_dtype=storage_dtype, pipeline=pipeline)


def resume(log, renderer=None, *, progress: bool | None = None, time_limit: float | None = None,
           track_error: bool = True, on_round=None) -> AdaptiveResult:
    """Continue a killed or stopped run from its log with its recorded settings.

    Rebuilds the statistics from the committed samples, replays
    ``method.observe`` for every committed round, and goes on with the
    next round index, so the run takes the same decisions as one that was
    never interrupted.  Rows of an interrupted append are discarded.

    Parameters
    ----------
    log : path-like
        The run's sample log.
    renderer : Renderer, optional
        The run's renderer; by default it is rebuilt from the spec the run
        recorded (``adapt(..., renderer_spec=...)``, see
        :mod:`mcrecon.renderers.spec`).
    progress, time_limit, track_error, on_round
        As for :func:`adapt`; ``time_limit`` defaults to the recorded one.
    """
    log_path = Path(log)
    with log_lock(log_path):  # refused while another run or resume writes this log
        return _resume(log_path, renderer, progress=progress, time_limit=time_limit, track_error=track_error,
                       on_round=on_round)


def _resume(log_path, renderer, *, progress, time_limit, track_error, on_round) -> AdaptiveResult:
    sl = read_log(log_path)
    s = sl.run_settings
    if not s:
        raise InputError(str(log_path), "run settings", "none recorded: this log was not written by an "
                         "adaptive run (use `mcrecon denoise` for offline logs)")
    if renderer is None:
        spec = s.get("renderer_spec")
        if not spec:
            raise InputError(str(log_path), "run settings renderer_spec", "none recorded: the run did not say "
                             "how to build its renderer; give it: resume(log, renderer)")
        renderer = renderer_from_spec(spec, where=str(log_path), field="run settings renderer_spec")
    w, h, channels = _check_renderer(renderer)
    if (w, h, list(channels)) != (s["width"], s["height"], list(s["channels"])):
        raise InputError(str(log_path), "renderer", f"renderer is {w}x{h} {channels}, the run was "
                         f"{s['width']}x{s['height']} {s['channels']}")
    method = get_method(s["method"], **s["method_options"])
    ref = sl.reference()
    run = method.start(w, h, channels, reference=ref)
    pipeline = bool(s.get("pipeline", False))  # logs of runs before pipelining: sequential
    budget = int(round(float(s["spp"]) * w * h))
    # Replay the committed rounds exactly as the live run took them: one batch
    # per round (the statistics merge runs of same-pixel samples within a batch,
    # so other batch boundaries would round differently for float64 values),
    # one round in memory at a time; observe() only for methods that read samples.
    # A pipelined run had planned round K (the one in flight when it stopped) from
    # the rounds <= K-2 with round K-1 pending: that plan is made again between
    # the replays of rounds K-2 and K-1, exactly as the live run made it (round 1,
    # when the driver split the initial pass, depends only on the sample count).
    stats = PixelStats(w, h, channels, subpixels=method.requires.subpixels)
    k = sl.n_rounds
    planned = None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", McreconWarning)  # the live run reported them
        for r in range(k):
            chunk = sl.read_all(rounds=[r])
            if pipeline and r == k - 1 and k >= 2:
                pending = _pixel_counts_of(chunk.positions, w, h)
                planned = _plan_round(method, run, stats, k, budget, _committed(stats) + len(chunk.positions),
                                      int(s["seed"]), ref, pending=pending,
                                      initial_rounds=_initial_rounds(method, pipeline, budget, w * h))
                if planned[0] is None and planned[1] == "wait":
                    # the live run committed round K-1 first, then planned round K from it
                    planned = None
            _take_round(method, run, stats, SampleBatch(chunk.positions, chunk.values), r, s["nonfinite"],
                        str(log_path))
    records = list(sl.round_records)
    elapsed = float(records[-1]["wall_seconds"]) if records else 0.0
    tl = time_limit if time_limit is not None else s.get("time_limit")
    return _run(renderer, method, run, stats=stats, rounds=records, round_index=k, budget=budget,
                seed=int(s["seed"]), log_path=log_path, ref=ref, time_limit=tl, progress=progress,
                nonfinite=s["nonfinite"], max_rounds=10_000, track_error=track_error, eps=0.01,
                elapsed=elapsed, on_round=on_round,
                storage_dtype=s.get("storage_dtype", "float32") if sl.n_samples == 0 else str(sl.value_dtype),
                pipeline=pipeline, planned=planned)


def _take_round(method, run, stats, batch, round_index, nonfinite, source, n_nonfinite=None,
                timeline=None, helper=None) -> None:
    """A committed round into the statistics and, for methods that read samples, into ``observe``.

    The one path of the live run and of a resume's replay.  ``observe`` sees
    the round after the run's NaN/Inf policy, exactly as the statistics did.
    ``n_nonfinite`` (rows with a NaN or Inf value) is given by the live run,
    whose reply :func:`validate_reply` has already checked (shapes, dtypes,
    positions on the film): the statistics then take the arrays without
    checking them again -- the same numbers as ``stats.add`` would ingest
    (``check_samples`` returns contiguous arrays of the given float dtype).
    ``helper`` (an idle one-thread executor, live runs only): the statistics
    ingest the round there while ``observe`` runs here -- they read the
    same arrays and write disjoint state, both compiled kernels that release
    the GIL -- and both are done when this returns.
    """
    if n_nonfinite is None:
        stats.add(batch.positions, batch.values, nonfinite=nonfinite, source=source)
        pos, val = np.asarray(batch.positions), np.asarray(batch.values)
        if val.ndim == 1:
            val = val[:, None]
        n_bad = int((~np.isfinite(val)).any(axis=1).sum()) if (method.requires.samples and val.size) else 0
    else:
        pos = np.ascontiguousarray(batch.positions)
        val = np.ascontiguousarray(batch.values)
        if val.ndim == 1:
            val = val[:, None]
        n_bad = int(n_nonfinite)

        def ingest(**where):
            t, c = time.perf_counter(), time.thread_time()
            if pos.shape[0]:
                p2, v2 = apply_nonfinite(pos, val, n_bad, nonfinite, where=source)
                stats._ingest(p2, v2, n_bad, nonfinite=nonfinite, source=source)
            if timeline is not None:
                timeline.add("ingest", round_index, t, time.perf_counter(), time.thread_time() - c, **where)

        # In the helper only when the ingest cannot warn (no NaN/Inf row): the warnings
        # machinery is not thread-safe, and observe() may filter warnings meanwhile.
        if helper is not None and method.requires.samples and not n_bad:
            pending = helper.submit(ingest, helper=True)
            try:
                _observe(method, run, pos, val, n_bad, nonfinite, source, round_index, timeline)
            finally:
                pending.result()  # the statistics are complete before anything else happens
            return
        ingest()
    if method.requires.samples:
        _observe(method, run, pos, val, n_bad, nonfinite, source, round_index, timeline)


def _observe(method, run, pos, val, n_bad, nonfinite, source, round_index, timeline):
    pos, val = apply_nonfinite(pos, val, n_bad, nonfinite, where=source)
    with (timeline.phase("observe", round_index) if timeline is not None else contextlib.nullcontext()):
        method.observe(run, SampleBatch(pos, val), round_index)


def _pixel_counts_of(positions, w, h) -> np.ndarray:
    """Samples per pixel (H, W) of film positions (on the film: validated)."""
    pos = np.asarray(positions)
    if pos.shape[0] == 0:
        return np.zeros((h, w), np.int64)
    idx = pos[:, 1].astype(np.int64) * w + pos[:, 0].astype(np.int64)
    return np.bincount(idx, minlength=w * h).reshape(h, w)


def _request_counts(req) -> np.ndarray:
    """Samples per pixel (H, W) a request asks for (what its reply will add)."""
    c = np.zeros((req.height, req.width), np.int64) if req.counts is None else req.counts.copy()
    if req.positions is not None:
        c += _pixel_counts_of(req.positions, req.width, req.height)
    return c


def _committed(stats) -> int:
    # Samples dropped by the non-finite policy were rendered and committed: they
    # count against the budget, or a renderer that keeps returning NaN never ends.
    return stats.n_samples + stats.n_dropped


def method_pipelines(method) -> bool:
    """Whether ``method`` plans with one round of lag by default (:func:`adapt`'s ``pipeline``):
    what its class declares (``Method.pipeline``, a bool)."""
    v = getattr(type(method), "pipeline", False)
    if not isinstance(v, bool):
        raise InputError(f"method {getattr(method, 'name', type(method).__name__)}", "pipeline",
                         f"class attribute {v!r}; expected True (plans are safe from statistics one round "
                         "old) or False")
    return v


def _initial_rounds(method, pipeline: bool, budget: int, pixels: int) -> int:
    """Rounds of the uniform initial pass the driver takes: two when pipelined and the pass has
    two or more samples per pixel (half, then the rest), else one."""
    return 2 if pipeline and method.initial_pass(budget, pixels) >= 2 else 1


def _initial_request(method, state: AdaptiveState, initial_rounds: int):
    """The driver's round of the uniform initial pass (round 0, or round 1 of a split pass)."""
    w, h = state.width, state.height
    spp = method.initial_pass(state.budget, w * h)
    if state.round_index == 0:
        return state.uniform_request((spp + 1) // 2 if initial_rounds == 2 else spp)
    n = min(state.remaining, spp * w * h - state.n_samples)
    return state.request(counts=uniform_counts(w, h, max(n, 0), state.rng))


def _with_seed(req, round_index, seed):
    """``req`` with its round index and renderer seed, without validating it again.

    (``dataclasses.replace`` would re-run ``SampleRequest.__post_init__``: the
    method built the request through its constructor, which checked it.)
    """
    out = copy.copy(req)
    object.__setattr__(out, "round_index", int(round_index))
    object.__setattr__(out, "seed", int(seed))
    return out


def _adaptive_state(stats, round_index, budget, n_samples, rng, ref, *, pending=None,
                    initial_rounds=1) -> AdaptiveState:
    return AdaptiveState(stats, round_index, budget, n_samples, rng, ref, pending=pending,
                         iteration=max(int(round_index) - int(initial_rounds), 0))


def _plan_round(method, run, stats, round_index, budget, n_total, seed, ref, *, pending=None, initial_rounds=1):
    """(request with its seeds, None) or (None, why the run stops) for round ``round_index``.

    ``n_total``: samples committed plus in flight (``pending``, per pixel).
    The rounds of the initial pass are the driver's own; later ones the
    method's plan.  Depends only on its arguments: the same in a live run
    and in a resume.  ``(None, "wait")``: with a round in flight the plan
    asked for nothing (the round in flight is committed first, then this
    round is planned again without ``pending``).
    """
    if n_total >= budget:
        return None, "budget"
    rng, rseed = round_seeds(seed, round_index)
    state = _adaptive_state(stats, round_index, budget, n_total, rng, ref, pending=pending,
                            initial_rounds=initial_rounds)
    if round_index < initial_rounds:
        req = _initial_request(method, state, initial_rounds)
    else:
        req = method.plan(run, state)
    if req is None:
        return None, "converged"
    if req.total == 0:
        return None, ("wait" if pending is not None else "converged")
    if req.total > state.remaining:
        raise RuntimeError(f"method {method.name} planned {req.total} samples with only "
                           f"{state.remaining} left in the budget (a bug in the method)")
    return _with_seed(req, round_index, rseed), None


def _resolve_storage(log_path, reply_dtype) -> str:
    """``auto`` storage: float32 replies stay float32, anything else is stored as float64.

    Called on the first reply, while the log holds no sample: a float64
    log replaces the float32 placeholder (same metadata, reference and
    run settings), atomically.
    """
    dtype = "float32" if np.dtype(reply_dtype) in (np.float32, np.float16) else "float64"
    if log_path is not None and dtype == "float64":
        sl = read_log(log_path)
        if sl.value_dtype != np.float64:
            if sl.n_samples:  # a resumed auto run keeps the log's dtype
                return str(sl.value_dtype)
            c = len(sl.channels)
            write_log(log_path, np.zeros((0, 2), dtype), np.zeros((0, c), dtype), width=sl.width,
                      height=sl.height, channels=sl.channels, reference=sl.reference(), metadata=sl.metadata)
            set_run_settings(log_path, {**(sl.run_settings or {}), "storage_dtype": "auto"})
    return dtype


def _to_storage(batch, storage_dtype, stats, name, round_index, warned, log_path) -> SampleBatch:
    """Cast a validated reply to the log's dtype, refusing what float32 cannot hold."""
    val = np.asarray(batch.values)
    if storage_dtype == "float32" and val.dtype != np.float32:
        big = np.isfinite(val) & (np.abs(val) > FLOAT32_MAX)
        if big.any():
            raise InputError(str(log_path), "storage_dtype", f"round {round_index} from {name} holds "
                             f"{int(big.any(axis=1).sum())} sample(s) beyond float32's range (up to "
                             f"{float(np.abs(val[big]).max()):.3g}); nothing of this round was stored, but this "
                             "log stores float32: start the run again with a new log and storage_dtype='auto' "
                             "or 'float64' (--storage-dtype auto)")
        if "spread" not in warned:
            lost = float32_loses_spread(batch.positions, val, width=stats.width, height=stats.height)
            if lost:
                warned.add("spread")
                warnings.warn(f"{name}: round {round_index}: float32 storage loses the spread of the samples in "
                              f"{lost} pixel(s) (e.g. 1e6 +- 1e-3 rounds to one value, variance 0); keep it with "
                              "storage_dtype='auto' or 'float64' (--storage-dtype auto)", McreconWarning,
                              stacklevel=4)
    return SampleBatch(cast_positions(batch.positions, storage_dtype), val.astype(storage_dtype, copy=False),
                       batch.features)


class _Round:
    """What the toolkit does with one reply: validate, store, count (shared by both modes)."""

    def __init__(self, method, run, stats, *, name, c, log_path, nonfinite, ref, track_error, eps, budget,
                 storage_dtype, wall, timeline):
        self.method, self.run, self.stats = method, run, stats
        self.timeline = timeline
        self.name, self.c, self.log_path, self.nonfinite = name, c, log_path, nonfinite
        self.ref, self.track_error, self.eps, self.budget = ref, track_error, eps, budget
        self.storage_dtype = storage_dtype
        self.warned = set()
        self.wall = wall  # () -> run wall seconds now

    def receive(self, req, reply, round_index):
        """The validated reply (stored precision) and its count of non-finite rows; nothing stored yet."""
        with self.timeline.phase("validate", round_index):
            return self._receive(req, reply, round_index)

    def _receive(self, req, reply, round_index):
        # the rows with a NaN or Inf value are counted in the validation's one pass; the cast to
        # the log's dtype keeps them (finite values beyond float32's range are refused there)
        batch, n_bad = _validate_reply(req, reply, n_channels=self.c, renderer=self.name)
        if self.storage_dtype == "auto":
            self.storage_dtype = _resolve_storage(self.log_path, np.asarray(batch.values).dtype)
        if self.log_path is not None:
            batch = _to_storage(batch, self.storage_dtype, self.stats, self.name, round_index, self.warned,
                                self.log_path)
        val = np.ascontiguousarray(batch.values)
        if self.nonfinite == "raise" and n_bad:
            raise RendererError(self.name, "values", f"{n_bad} sample(s) with NaN or Inf in round "
                                f"{round_index} (policy nonfinite='raise'); nothing of this round was stored")
        return SampleBatch(np.ascontiguousarray(batch.positions), val, batch.features), n_bad

    def commit(self, batch, n_bad, record, toolkit_s, helper=None):
        """Append to the log, then into the statistics (and ``observe``; with ``helper``, an idle
        one-thread executor, the two at once: see :func:`_take_round`)."""
        if self.log_path is not None:
            with self.timeline.phase("append", record["round"]):
                # checked: receive() validated the reply (validate_reply, then the log's dtype):
                # the commit does not scan it again
                append_log(self.log_path, batch.positions, batch.values, round_index=record["round"],
                           features=batch.features if batch.features else None, checked=True,
                           round_record={**record, "toolkit_seconds": toolkit_s, "wall_seconds": self.wall()})
        _take_round(self.method, self.run, self.stats, batch, record["round"], self.nonfinite, self.name,
                    n_nonfinite=n_bad, timeline=self.timeline, helper=helper)

    def evaluate(self, record, round_index):
        """The error of the image after the round (not part of the run's time)."""
        from .metrics import relative_mse

        if self.ref is None or not self.track_error:
            return 0.0
        te = time.perf_counter()
        rng, _ = round_seeds(0, 0)
        st = _adaptive_state(self.stats, round_index, self.budget, _committed(self.stats), rng, self.ref)
        with self.timeline.phase("evaluate", round_index):
            record["error"] = relative_mse(self.method.finish(self.run, st), self.ref, eps=self.eps)
        record["eval_seconds"] = time.perf_counter() - te
        return record["eval_seconds"]


def _run(renderer, method, run, *, stats, rounds, round_index, budget, seed, log_path, ref, time_limit,
         progress, nonfinite, max_rounds, track_error, eps, elapsed, on_round,
         storage_dtype, pipeline=False, planned=None) -> AdaptiveResult:
    name = _renderer_name(renderer)
    bar = _Progress(progress, budget)
    clock = {"wall_start": time.perf_counter() - elapsed}
    timeline = _Timeline()
    rnd = _Round(method, run, stats, name=name, c=len(stats.channels), log_path=log_path, nonfinite=nonfinite,
                 ref=ref, track_error=track_error, eps=eps, budget=budget, storage_dtype=storage_dtype,
                 wall=lambda: time.perf_counter() - clock["wall_start"], timeline=timeline)
    acct = {"render": 0.0, "cpu": 0.0, "timeline": timeline, "bar": bar,
            "initial_rounds": _initial_rounds(method, pipeline, budget, stats.width * stats.height)}
    bar.n, bar.wall = _committed(stats), elapsed
    n_before = len(rounds)
    loop_t0 = time.perf_counter()
    try:
        loop = _loop_pipelined if pipeline else _loop_sequential
        stopped, round_index = loop(renderer, method, run, stats=stats, rounds=rounds, round_index=round_index,
                                    budget=budget, seed=seed, ref=ref, time_limit=time_limit, max_rounds=max_rounds,
                                    on_round=on_round, bar=bar, clock=clock, rnd=rnd, acct=acct, planned=planned)
    finally:
        bar.close()
    loop_s = time.perf_counter() - loop_t0
    tf = time.perf_counter()
    rng, _ = round_seeds(seed, round_index)
    final = _adaptive_state(stats, round_index, budget, _committed(stats), rng, ref)
    image = method.finish(run, final)
    eval_s = sum(float(r.get("eval_seconds", 0.0)) for r in rounds[len(rounds) - acct.get("new", 0):])
    return AdaptiveResult(image=np.asarray(image, dtype=np.float64), stats=stats, rounds=rounds,
                          stopped=stopped, log=log_path, method=method, run=run, pipelined=bool(pipeline),
                          resumed_rounds=n_before,
                          loop_seconds=loop_s - eval_s, idle_seconds=max(loop_s - eval_s - acct["render"], 0.0),
                          toolkit_cpu_seconds=acct["cpu"] + sum(e["cpu"] for e in timeline.events
                                                                 if e.get("helper")),
                          finish_seconds=time.perf_counter() - tf,
                          timeline=timeline.events)


def _render(renderer, req, acct):
    """Call the renderer: (reply, seconds it reports as its own, seconds of the call beyond them)."""
    # A round this machine cannot hold (box doubles its rounds up to 1/8 of the budget) is refused
    # before the renderer fills the memory with it (an --spp of 1e12 on 8x8 was killed by the kernel's
    # OOM killer at 24 GB).  A round's peak is about 4x its positions and values as float64 (the reply,
    # the renderer's and the validation's temporaries: measured 160 B a sample for RGB on a scene).
    check_memory("adapt", "spp", 32.0 * req.total * (2 + len(renderer.channels)),
                 f"round {req.round_index}'s {req.total} samples",
                 "lower the budget (--spp); the rounds committed before are in the log")
    acct["bar"].rendering(req.round_index, req.total)
    t1 = time.perf_counter()
    reply = renderer.render(req)
    t2 = time.perf_counter()
    render_s = getattr(renderer, "last_render_seconds", None)
    render_s = float(render_s) if render_s is not None else t2 - t1
    acct["timeline"].add("render", req.round_index, t1, t2, 0.0, own=render_s)
    # Time in the renderer call beyond what the renderer reports as its own
    # (file exchange, conversions) belongs to the toolkit side of the run.
    acct["render"] += min(render_s, t2 - t1)
    return reply, render_s, max((t2 - t1) - render_s, 0.0)


def _finish_round(record, rounds, on_round, bar, stats, log_path, acct):
    if log_path is not None:
        # The commit stored the times known then; now the full round
        # (statistics, observe, error) is known: a resume reports these.
        update_round_record(log_path, record)
    rounds.append(record)
    acct["new"] = acct.get("new", 0) + 1
    if on_round is not None:
        on_round(record)
    bar.update(_committed(stats), record["round"], record["wall_seconds"])


def _loop_sequential(renderer, method, run, *, stats, rounds, round_index, budget, seed, ref, time_limit,
                     max_rounds, on_round, bar, clock, rnd, acct, planned):
    """Plan, render, validate, commit, one round after the other."""
    # a method that reads samples observes a round while a helper thread ingests it
    helper = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mcrecon-ingest") \
        if method.requires.samples else None
    try:
        return _sequential_rounds(renderer, method, run, stats=stats, rounds=rounds, round_index=round_index,
                                  budget=budget, seed=seed, ref=ref, time_limit=time_limit, max_rounds=max_rounds,
                                  on_round=on_round, bar=bar, clock=clock, rnd=rnd, acct=acct, helper=helper)
    finally:
        if helper is not None:
            helper.shutdown(wait=True)


def _sequential_rounds(renderer, method, run, *, stats, rounds, round_index, budget, seed, ref, time_limit,
                       max_rounds, on_round, bar, clock, rnd, acct, helper):
    while True:
        if _committed(stats) >= budget:
            return "budget", round_index
        if round_index >= max_rounds:
            return "max_rounds", round_index
        if time_limit is not None and time.perf_counter() - clock["wall_start"] >= time_limit:
            return "time_limit", round_index
        t0, c0 = time.perf_counter(), time.thread_time()
        with acct["timeline"].phase("plan", round_index):
            req, why = _plan_round(method, run, stats, round_index, budget, _committed(stats), seed, ref,
                                   initial_rounds=acct["initial_rounds"])
        if req is None:
            return why, round_index
        tp, cp = time.perf_counter(), time.thread_time()
        reply, render_s, extra_s = _render(renderer, req, acct)
        t2, c2 = time.perf_counter(), time.thread_time()
        batch, n_bad = rnd.receive(req, reply, round_index)
        toolkit_s = (tp - t0) + (time.perf_counter() - t2) + extra_s
        record = {"round": round_index, "samples": len(batch),
                  "samples_total": _committed(stats) + len(batch), "renderer_seconds": render_s}
        t3 = time.perf_counter()
        rnd.commit(batch, n_bad, record, toolkit_s, helper=helper)
        toolkit_s += time.perf_counter() - t3
        acct["cpu"] += (cp - c0) + (time.thread_time() - c2)
        record["toolkit_seconds"] = toolkit_s
        record["wall_seconds"] = rnd.wall()
        clock["wall_start"] += rnd.evaluate(record, round_index)  # evaluation is not part of the run's time
        _finish_round(record, rounds, on_round, bar, stats, rnd.log_path, acct)
        round_index += 1


def _loop_pipelined(renderer, method, run, *, stats, rounds, round_index, budget, seed, ref, time_limit,
                    max_rounds, on_round, bar, clock, rnd, acct, planned):
    """Render round j in this thread while the toolkit thread commits round j-1 and plans round j+1.

    The plan of round j+1 sees the rounds <= j-1 and round j as ``pending``
    counts; the plan of round 1 waits for round 0 (there is nothing to plan
    from before) unless it is the second half of the driver's split initial
    pass: then it is made while round 0 renders, and round 0's commit
    overlaps round 1.  The renderer stays in the calling thread (renderers with
    thread affinity, signals, Ctrl-C); the toolkit's heavy parts release
    the GIL (the statistics' and the methods' compiled kernels run with
    ``nogil``, numpy's large-array loops, the filtering pool); h5py's
    writes hold it for their duration.
    """

    def commit(prev, carry, helper=None):
        """Validate and commit ``prev`` = (round, request, reply, renderer s, extra s): its finished record.

        ``helper``: the toolkit thread when it is idle (round 0 and the last round, committed by
        this thread while nothing renders), to ingest while ``observe`` runs.
        """
        t0, c0 = time.perf_counter(), time.thread_time()
        k, preq, reply, render_s, extra_s = prev
        batch, n_bad = rnd.receive(preq, reply, k)
        record = {"round": k, "samples": len(batch), "samples_total": _committed(stats) + len(batch),
                  "renderer_seconds": render_s}
        rnd.commit(batch, n_bad, record, carry + extra_s + (time.perf_counter() - t0), helper=helper)
        # a round's toolkit time: its validation and commit, the beyond-renderer part
        # of its render call, and the plan that made its request
        record["toolkit_seconds"] = carry + extra_s + (time.perf_counter() - t0)
        record["wall_seconds"] = rnd.wall()
        acct["cpu"] += time.thread_time() - c0
        return record

    def plan(j, req_j):
        """The plan of round j+1 from what is committed, round j (``req_j``) in flight: ((req, why), seconds)."""
        t0, c0 = time.perf_counter(), time.thread_time()
        with acct["timeline"].phase("plan", j + 1):
            if j + 1 >= max_rounds:
                out = (None, "max_rounds")
            elif req_j is None:
                out = _plan_round(method, run, stats, j + 1, budget, _committed(stats), seed, ref,
                                  initial_rounds=acct["initial_rounds"])
            else:
                out = _plan_round(method, run, stats, j + 1, budget, _committed(stats) + req_j.total, seed, ref,
                                  pending=_request_counts(req_j), initial_rounds=acct["initial_rounds"])
        if out[0] is not None and prepare is not None:
            # the renderer's own preparation of the request (e.g. the Mitsuba bridge's jittered
            # positions), here while it still renders round j rather than inside its next call
            with acct["timeline"].phase("prepare", j + 1):
                prepare(out[0])
        acct["cpu"] += time.thread_time() - c0
        return out, time.perf_counter() - t0

    # optional: a renderer that computes part of its reply ahead (same reply with or without)
    prepare = getattr(renderer, "prepare", None)
    prepare = prepare if callable(prepare) else None

    def job(prev, carry, j, req_j):
        # the toolkit thread's work while round j renders
        record = None
        if prev is not None:
            record = commit(prev, carry)
            record["_eval"] = rnd.evaluate(record, record["round"])
        out, secs = plan(j, req_j)
        # round 1 planned blind (prev None): round 0's plan time goes with round 1's
        return record, (out, secs + (carry if prev is None else 0.0))

    def done(record):
        clock["wall_start"] += record.pop("_eval", 0.0)  # evaluation is not part of the run's time
        _finish_round(record, rounds, on_round, bar, stats, rnd.log_path, acct)

    blind = acct["initial_rounds"] == 2  # round 1 is the second half of the driver's initial pass
    j = round_index
    if planned is None:
        # a new run (round 0: nothing to plan from) or a resume after round 0 (round 1 sees it)
        (req, why), carry = plan(j - 1, None)
    else:
        (req, why), carry = planned, 0.0
    uncommitted = None   # the rendered round not yet committed
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mcrecon-toolkit")
    fut = None
    try:
        while True:
            if req is None:
                stopped = why
                break
            if j >= max_rounds:
                stopped = "max_rounds"
                break
            if time_limit is not None and time.perf_counter() - clock["wall_start"] >= time_limit:
                stopped = "time_limit"
                break
            # round 1 is planned from round 0, after it (no toolkit work to overlap), unless
            # it is the driver's second half of a split initial pass
            first = j == 0 and not blind
            if not first:
                fut = pool.submit(job, uncommitted, carry, j, req)
                uncommitted = None
            try:
                reply, render_s, extra_s = _render(renderer, req, acct)
            except BaseException:
                if fut is not None:
                    # the round before is committed first (nothing committed is lost);
                    # a failure of that commit is the run's first error
                    f, fut = fut, None
                    exc = f.exception()
                    if exc is not None:
                        raise exc from None
                    if f.result()[0] is not None:
                        done(f.result()[0])
                raise
            rendered = (j, req, reply, render_s, extra_s)
            if first:
                record = commit(rendered, carry, helper=pool)
                record["_eval"] = rnd.evaluate(record, j)
                done(record)
                (req, why), carry = plan(j, None)
            else:
                f, fut = fut, None
                record, ((req, why), carry) = f.result()
                if record is not None:
                    done(record)
                uncommitted = rendered
                if req is None and why == "wait":
                    # the method waits for the round just rendered (it asked for nothing):
                    # commit it here, then plan the next round from it, as round 1 after round 0
                    prev, uncommitted = uncommitted, None
                    record = commit(prev, carry, helper=pool)
                    record["_eval"] = rnd.evaluate(record, record["round"])
                    done(record)
                    (req, why), carry = plan(j, None)
            j += 1
        if uncommitted is not None:
            # the last round: commit it (nothing is left to plan)
            prev, uncommitted = uncommitted, None
            record = commit(prev, carry, helper=pool)
            record["_eval"] = rnd.evaluate(record, record["round"])
            done(record)
        return stopped, j
    finally:
        if fut is not None:
            with contextlib.suppress(BaseException):
                fut.result()
        pool.shutdown(wait=True)


from ._lazy import public_dir as _public_dir  # noqa: E402

__dir__ = _public_dir(__name__)

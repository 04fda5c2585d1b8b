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
import dataclasses
import math
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from ..errors import InputError, McreconWarning
from ..io.logformat import MAX_PIXELS
from ..io.writer import set_run_settings, write_log
from ..io.lock import log_lock
from ..io.reader import read_log
from ..methods.base import Method
from ..methods import get_method
from ..methods.base import RunState
from ..core.requests import SampleBatch
from ..renderers.spec import renderer_from_spec
from ..core.samples import (NONFINITE_POLICIES, check_reference)
from ..core.stats import PixelStats


from .._lazy import public_dir as _public_dir
from .rounds import _Progress, _Round, _Timeline, _loop_pipelined, _loop_sequential, _take_round
from .schedule import (STORAGE_DTYPES, _adaptive_state, _committed, _initial_rounds, _pixel_counts_of,
                       _plan_round, method_pipelines, round_seeds)

__all__ = ['adapt', 'resume', 'AdaptiveResult']

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
        """Output sanity of the image (see :func:`mcrecon.core.metrics.output_sanity`)."""
        from ..core.metrics import output_sanity

        return output_sanity(self.image, self.stats)

    @property
    def renderer_seconds(self) -> float:
        return float(sum(r["renderer_seconds"] for r in self.rounds))

    @property
    def toolkit_seconds(self) -> float:
        return float(sum(r["toolkit_seconds"] for r in self.rounds))


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
        Answers :class:`~mcrecon.core.requests.SampleRequest` s.
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
        Policy for NaN/Inf sample values (see :mod:`mcrecon.core.stats`); with
        ``raise`` a reply holding one is refused before it is committed.
    track_error : bool
        Reconstruct after every round to record its error (needs a
        reference; excluded from the toolkit time).
    renderer_spec : mapping, optional
        How to recreate the renderer (stored with the run for ``--resume``).
        Default: the renderer's own ``spec()`` when it has one (the built-in
        scenes, the command renderer and the Mitsuba bridge do, for what a
        spec can say), so ``resume(log)`` rebuilds it without being told.
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
    if renderer_spec is None:
        own = getattr(renderer, "spec", None)
        renderer_spec = own() if callable(own) else None
    if pipeline is None:
        pipeline = method_pipelines(method)
    elif pipeline not in (True, False):
        raise InputError("adapt", "pipeline", f"got {pipeline!r}, expected True, False or None (the method's choice)")
    settings = {
        "method": method.name, "method_options": dict(method.params), "spp": float(spp), "seed": int(seed),
        "nonfinite": nonfinite, "time_limit": time_limit, "width": w, "height": h,
        "channels": list(channels), "renderer": _renderer_name(renderer),
        "renderer_spec": dict(renderer_spec or {}), "storage_dtype": storage_dtype,
        "pipeline": bool(pipeline), "options_version": OPTIONS_VERSION,
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
            raise InputError(str(log_path), "file", "exists; resume it with --resume / mcrecon.adaptive.run.resume, "
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


#: Version of the recorded method options: 2 since ci's ``exposure`` is in stops (it was a linear factor).
OPTIONS_VERSION = 2


def _current_options(settings: Mapping) -> dict:
    """The recorded method options as today's options mean them (a log of an older run is resumed alike)."""
    opts = dict(settings["method_options"])
    if int(settings.get("options_version", 1)) < 2 and settings["method"] == "ci" and "exposure" in opts:
        opts["exposure"] = math.log2(float(opts["exposure"]))  # a linear factor then, stops now: 1.0 -> 0.0
    return opts


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
                         "adaptive run (use `mcrecon reconstruct` for offline logs)")
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
    method = get_method(s["method"], **_current_options(s))
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
            chunk = sl.read_all(rounds=[r], features=sl.feature_names if method.requires.features != "none" else ())
            if pipeline and r == k - 1 and k >= 2:
                pending = _pixel_counts_of(chunk.positions, w, h)
                planned = _plan_round(method, run, stats, k, budget, _committed(stats) + len(chunk.positions),
                                      int(s["seed"]), ref, pending=pending,
                                      initial_rounds=_initial_rounds(method, pipeline, budget, w * h))
                if planned[0] is None and planned[1] == "wait":
                    # the live run committed round K-1 first, then planned round K from it
                    planned = None
            _take_round(method, run, stats, SampleBatch(chunk.positions, chunk.values, chunk.features), r,
                        s["nonfinite"], str(log_path))
    records = list(sl.round_records)
    elapsed = float(records[-1]["wall_seconds"]) if records else 0.0
    tl = time_limit if time_limit is not None else s.get("time_limit")
    return _run(renderer, method, run, stats=stats, rounds=records, round_index=k, budget=budget,
                seed=int(s["seed"]), log_path=log_path, ref=ref, time_limit=tl, progress=progress,
                nonfinite=s["nonfinite"], max_rounds=10_000, track_error=track_error, eps=0.01,
                elapsed=elapsed, on_round=on_round,
                storage_dtype=s.get("storage_dtype", "float32") if sl.n_samples == 0 else str(sl.value_dtype),
                pipeline=pipeline, planned=planned)


def _run(renderer, method, run, *, stats, rounds, round_index, budget, seed, log_path, ref, time_limit,
         progress, nonfinite, max_rounds, track_error, eps, elapsed, on_round,
         storage_dtype, pipeline=False, planned=None) -> AdaptiveResult:
    name = _renderer_name(renderer)
    bar = _Progress(progress, budget)
    clock = {"wall_start": time.perf_counter() - elapsed}
    timeline = _Timeline()
    rnd = _Round(method, run, stats, name=name, c=len(stats.channels), log_path=log_path, nonfinite=nonfinite,
                 ref=ref, track_error=track_error, eps=eps, budget=budget, storage_dtype=storage_dtype,
                 wall=lambda: time.perf_counter() - clock["wall_start"], timeline=timeline,
                 fresh_replies=bool(getattr(renderer, "fresh_replies", False)))
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
        loop_s = time.perf_counter() - loop_t0
        tf = time.perf_counter()
        try:
            rng, _ = round_seeds(seed, round_index)
            final = _adaptive_state(stats, round_index, budget, _committed(stats), rng, ref)
            image = method.finish(run, final)
        finally:
            # the last round's log write (a sequential loop leaves it running behind): committed before
            # the run returns, whatever the final image did
            drain = acct.pop("drain", None)
            if drain is not None:
                drain()
    finally:
        bar.close()
    eval_s = sum(float(r.get("eval_seconds", 0.0)) for r in rounds[len(rounds) - acct.get("new", 0):])
    return AdaptiveResult(image=np.asarray(image, dtype=np.float64), stats=stats, rounds=rounds,
                          stopped=stopped, log=log_path, method=method, run=run, pipelined=bool(pipeline),
                          resumed_rounds=n_before,
                          loop_seconds=loop_s - eval_s, idle_seconds=max(loop_s - eval_s - acct["render"], 0.0),
                          toolkit_cpu_seconds=acct["cpu"] + sum(e["cpu"] for e in timeline.events
                                                                 if e.get("helper")),
                          finish_seconds=time.perf_counter() - tf,
                          timeline=timeline.events)

__dir__ = _public_dir(__name__)

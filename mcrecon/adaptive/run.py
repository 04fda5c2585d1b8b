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
import os
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from ..errors import InputError, McreconWarning
from ..io.writer import set_run_settings, write_log
from ..io.lock import log_lock
from ..io.reader import read_log
from ..methods.base import Method, RunState
from ..methods import get_method
from ..core.halves import split_halves
from ..core.requests import SampleBatch
from ..renderers.spec import renderer_from_spec
from ..core.samples import (NONFINITE_POLICIES, check_reference)
from ..core.stats import PixelStats


from .._lazy import public_dir as _public_dir
from .context import RunContext, SessionOptions, _check_renderer, _renderer_name
from .rounds import _LogWrites, _Round, _loop_pipelined, _loop_sequential, _take_round
from .schedule import STORAGE_DTYPES, _pixel_counts_of, method_pipelines, round_seeds

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


def adapt(renderer, method, *, spp: float, seed: int = 0, log=None, reference=None,
          time_limit: float | None = None, progress: bool | None = None, nonfinite: str = "drop",
          max_rounds: int = 10_000, track_error: bool = True, eps: float = 0.01,
          metadata: Mapping | None = None, renderer_spec: Mapping | None = None,
          overwrite: bool = False, storage_dtype: str = "auto",
          on_round: Callable[[dict], Any] | None = None, pipeline: bool | None = None) -> AdaptiveResult:
    """Run adaptive rounds: ask a renderer for samples where they pay off, until the budget is spent.

    Each round the method plans a request (samples per pixel, or at film
    positions), the renderer answers it, the reply is validated and (with
    ``log``) committed to the sample log before the method sees it; at the
    end the method reconstructs the image.  A run with a log survives a
    kill: :func:`resume` (``mcrecon adapt --resume LOG``) continues it with
    the same decisions.  It stops at the budget, the method's target, a
    time limit or ``max_rounds``.  This is ``mcrecon.adapt``.

    Parameters
    ----------
    renderer : Renderer
        An object with ``width``, ``height``, ``channels`` and
        ``render(request) -> SampleBatch`` (:class:`mcrecon.renderers.Renderer`),
        answering :class:`~mcrecon.core.requests.SampleRequest` s.
        A Python function ``fn(request) -> (positions, values)`` becomes
        one with ``mcrecon.CallableRenderer(fn, width=W, height=H)``; the
        package's others are ``mcrecon.renderers.command.CommandRenderer``
        (an external program exchanging HDF5 files),
        ``mcrecon.renderers.scenes.SceneRenderer`` (a built-in scene) and
        ``mcrecon.renderers.mitsuba.MitsubaRenderer`` (Mitsuba 3).
    method : str or Method
        A registered method name (``mcrecon.available_methods()``: ``gem``,
        ``awr``, ``ci`` and ``auto`` place their samples, the others take
        them uniformly; ``nfor`` needs a renderer that sends features) or
        a method object (``mcrecon.get_method("gem", gamma=0.1)``).
    spp : float
        The sample budget as average samples per pixel (in all
        ``round(spp * width * height)`` samples).
    seed : int, default 0
        Run seed: the whole run is reproducible from it.
    log : path-like, optional
        The sample log to create (``.h5``); every round is committed to it
        before the next request.  Refused if it exists, unless
        ``overwrite``.  Without it the run cannot be resumed, and nothing
        is written but where a method that reads half buffers (``auto``,
        ``nfor``) meets a renderer that declares a stratified sampler: the
        run then keeps its samples in a temporary log, removed when it
        returns, whose prefix-block halves its image reads (``result.log``
        None).  A run that raises before its first round reaches the
        log (a renderer that fails in round 0, a method that refuses the
        first reply) removes the log and the empty directories it created:
        there is nothing to resume, and the retry is not refused.  Once a
        round is committed, the log stays resumable.  A run interrupted
        (Ctrl-C) before then keeps its log, which :func:`resume` starts
        from the first round.
    reference : ndarray (H, W, C), optional
        The exact image, for the per-round error (``track_error``) and the
        methods that read one; stored in the log.
    time_limit : float, optional
        Wall seconds; no new round starts after them (the run stops with
        ``stopped == "time_limit"`` and can be resumed).
    progress : bool, optional
        A progress bar on stderr; default: only on a terminal.
    nonfinite : {'drop', 'zero', 'raise'}, default 'drop'
        What happens to NaN/Inf sample values (see :mod:`mcrecon.core.stats`):
        left out of the statistics (and counted), taken as 0, or refused
        (a reply holding one) before they are committed.
    max_rounds : int, default 10000
        Rounds at most.
    track_error : bool, default True
        With a ``reference``: reconstruct after every round and record its
        relative MSE (not counted in the toolkit time).
    eps : float, default 0.01
        The ε of that relative MSE, (img - ref)² / (ref² + ε).
    metadata : mapping, optional
        Extra JSON metadata stored in the log.
    renderer_spec : mapping, optional
        How to build the renderer again on resume, stored with the run
        (:mod:`mcrecon.renderers.spec`).  Default: the renderer's own
        ``spec()`` when it has one (the built-in scenes, the command
        renderer and the Mitsuba bridge do, for what a spec can say), so
        ``resume(log)`` rebuilds it without being told.  A
        :class:`~mcrecon.renderers.CallableRenderer` has none: resume it
        with ``resume(log, renderer)``.
    overwrite : bool, default False
        Replace an existing ``log``.  The old log stays as it is until the
        new run commits its first round (the new one is written beside it
        and renamed over it then): a run that fails or is interrupted
        before then leaves it bit-identical.
    storage_dtype : {'auto', 'float32', 'float64'}, default 'auto'
        Precision of the stored positions and values.  ``auto`` stores
        what the renderer sends: float32 replies as float32, float64 (and
        integer) replies as float64, decided on the first reply.  The
        statistics ingest exactly the stored numbers, so a resumed run sees
        what the uninterrupted one saw; without a log they ingest the
        replies in their own precision.  With ``float32`` and float64
        replies, a round whose values exceed float32's range is refused
        before it is stored, and a warning (once per run) counts pixels
        whose spread float32 cannot hold (1e6 +- 1e-3).
    on_round : callable, optional
        Called with each round's record (a dict, as in
        ``AdaptiveResult.rounds``) once the round is committed.
    pipeline : bool, optional
        Pipelined rounds: the renderer renders round k+1 while a toolkit
        thread commits round k and plans round k+2 from the rounds <= k
        (one round of lag, the same in every run: reproducible and
        resumable).  Default: what the method declares
        (:func:`method_pipelines`).  Recorded in the run settings.
        A renderer must then not modify a reply's arrays after ``render``
        returned them.  A renderer with a ``prepare(request)`` method
        (optional; the Mitsuba bridge computes its jittered positions
        there) has it called from the toolkit thread right after a round
        is planned there, while it renders the round before (rounds
        planned in the caller's thread -- round 0, a re-plan after a plan
        that waited -- and a resume's first round are not prepared);
        ``render(request)`` must return the same reply with or without it.

    Returns
    -------
    AdaptiveResult
        ``image`` (H, W, C) float64, ``stats`` (the statistics of every
        committed sample), ``rounds`` (per round: samples, renderer,
        toolkit and wall seconds, error), ``stopped`` (``budget``,
        ``converged``, ``time_limit`` or ``max_rounds``), ``log``;
        ``diagnostics()`` gives the method's per-pixel maps.

    Raises
    ------
    InputError
        Bad arguments (a plain function as the renderer, an unknown
        method, a budget that is not a positive number, an existing
        ``log``), each naming the argument and the fix, before anything is
        rendered.
    RendererError
        The renderer failed or answered wrongly; every earlier round is
        committed, so a run with a log can be resumed.

    See Also
    --------
    resume : continue a run from its log.
    mcrecon.reconstruct : an image from samples already taken.

    Examples
    --------
    >>> import numpy as np, mcrecon
    >>> from mcrecon.core.requests import jittered_positions
    >>> def render(request):
    ...     g = np.random.default_rng(request.round_index)
    ...     pos = np.zeros((0, 2))
    ...     if request.counts is not None:
    ...         pos = jittered_positions(request.counts, g)
    ...     if request.positions is not None:
    ...         pos = np.concatenate([pos, request.positions])
    ...     return pos, 0.5 + g.normal(0, 0.1, (len(pos), 3))
    >>> renderer = mcrecon.CallableRenderer(render, width=16, height=12)
    >>> result = mcrecon.adapt(renderer, "gem", spp=8)
    >>> result.image.shape, result.stopped
    ((12, 16, 3), 'budget')
    """
    if callable(renderer) and not hasattr(renderer, "render"):
        raise InputError("adapt", "renderer", f"{getattr(renderer, '__name__', type(renderer).__name__)} is a plain "
                         "function; wrap it: mcrecon.CallableRenderer(fn, width=W, height=H), so the run knows "
                         "the film size and the channels")
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
    session = SessionOptions(progress=progress, time_limit=time_limit, track_error=track_error, eps=eps,
                             max_rounds=max_rounds, on_round=on_round)
    private = _private_log(renderer, method) if log is None else None
    if private is not None:
        log = Path(private.name) / "run.h5"
    if log is None:
        return _drive(RunContext.assemble(renderer, method, settings, reference=ref, log_path=None, session=session))
    log_path = Path(log)
    made = _missing_dirs(log_path.parent)
    try:
        # The run holds its log's writer lock from creation to the end: a second run or
        # a resume on the same log is refused (naming this process), see log_lock.
        with log_lock(log_path):
            if log_path.exists() and not overwrite:
                raise InputError(str(log_path), "file", "exists; resume it with --resume / "
                                 "mcrecon.adaptive.run.resume, or choose another path")
            first = _FirstCommit(log_path)
            _create_log(first.path, settings, reference=ref, metadata=metadata)
            try:
                ctx = RunContext.assemble(renderer, method, settings, reference=ref, log_path=first.path,
                                          session=session)
                result = _drive(ctx, first)
            except BaseException as exc:
                first.abandon(interrupted=not isinstance(exc, Exception))
                raise
            first.publish(ctx)  # a run that ends without a round (max_rounds=0) still replaces the old log
            result.log = None if private is not None else log_path
            return result
    finally:
        for d in made:  # a refused run leaves no empty directory it created (a kept log keeps its own)
            with contextlib.suppress(OSError):
                d.rmdir()
        if private is not None:
            private.cleanup()


def _private_log(renderer, method):
    """A temporary directory for the log of a run asked for without one, where its image needs the log: a
    method that reads half buffers, with a renderer that declares a stratified sampler up front.  Its
    final halves are the log's prefix blocks (:func:`_prefix_block_halves`), which the rounds' own
    alternating halves cannot give; the directory goes when the run returns.  None otherwise (a
    command renderer that declares its sampler with its first reply keeps the rounds' halves)."""
    sampler = getattr(renderer, "sampler", None)
    if not method.requires.half_buffers or sampler in (None, "independent"):
        return None
    return tempfile.TemporaryDirectory(prefix="mcrecon-run-")


class _FirstCommit:
    """Where a new run writes its log, and what becomes of it at the first committed round or a failure.

    A new path is written in place.  An existing log the run replaces
    (``overwrite``) stays as it is until the new run commits its first
    round: the new log is written beside it (``.NAME.new``, under the
    old log's lock) and renamed over it right after that round's append
    returns.  A run that fails or is interrupted before then leaves the
    old log bit-identical, and a process killed then leaves it too.
    """

    def __init__(self, final: Path):
        self.final = final
        self.path = final.with_name(f".{final.name}.new") if final.exists() else final
        self.committed = False  # set once an append has returned: a round is on disk

    def appended(self, ctx, rnd) -> None:
        """Called after each append: the first one publishes the new log (from the writing thread,
        before the round counts as committed, so every later write goes to the published path)."""
        if not self.committed:
            self.committed = True
            self.publish(ctx)
            rnd.log_path = self.path

    def publish(self, ctx) -> None:
        if self.path != self.final:
            os.replace(self.path, self.final)
            self.path = ctx.log_path = self.final

    def abandon(self, *, interrupted: bool) -> None:
        """The run raised.  A round that reached the disk keeps the log, whatever the records in memory
        say (an append is committed before the round's record is finished).  Without one, a log the run
        wrote beside an old one is removed (the old one stays); a log at a new path is removed unless
        the run was interrupted (Ctrl-C: it stays resumable, from its first round)."""
        if self.committed or _rounds_on_disk(self.path) != 0:
            return
        if self.path != self.final or not interrupted:
            _remove_log(self.path)


def _rounds_on_disk(path) -> int | None:
    """The committed rounds of the log at ``path`` as the reader sees them (None: none readable)."""
    try:
        return read_log(path).n_rounds
    except Exception:  # noqa: BLE001 -- a log that cannot be read is kept as it is
        return None


def _missing_dirs(folder: Path) -> list[Path]:
    """The directories of ``folder``'s path that do not exist yet, deepest first."""
    out = []
    for d in (folder, *folder.parents):
        if d.exists():
            break
        out.append(d)
    return out


def _create_log(log_path, settings, *, reference, metadata):
    """A new run's empty log, its metadata and run settings (a log that fails half way is removed)."""
    meta = {"renderer": settings["renderer"], "seed": settings["seed"], **dict(metadata or {}),
            "settings": settings}
    # ``auto`` creates float32 datasets; the first reply may turn them into float64
    # (the log is still empty then, see _resolve_storage).
    placeholder = "float32" if settings["storage_dtype"] == "auto" else settings["storage_dtype"]
    c = len(settings["channels"])
    # written atomically: a failure leaves the path as it was
    write_log(log_path, np.zeros((0, 2), placeholder), np.zeros((0, c), placeholder), width=settings["width"],
              height=settings["height"], channels=tuple(settings["channels"]), reference=reference, metadata=meta)
    try:
        set_run_settings(log_path, settings)
    except Exception:
        _remove_log(log_path)
        raise


def _remove_log(log_path) -> None:
    """Remove a log this run created (a log a resume continues is never removed); the run's own error,
    raised after this, is what the caller hears of: a removal that fails is left at that."""
    with contextlib.suppress(OSError):
        log_path.unlink()


#: Version of the recorded method options: 2 since ci's ``exposure`` is in stops (it was a linear factor).
OPTIONS_VERSION = 2


def _current_options(settings: Mapping) -> dict:
    """The recorded method options as today's options mean them (a log of an older run is resumed alike)."""
    opts = dict(settings["method_options"])
    if int(settings.get("options_version", 1)) < 2 and settings["method"] == "ci" and "exposure" in opts:
        opts["exposure"] = math.log2(float(opts["exposure"]))  # options_version 1 stored a linear factor; stops since
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
    session = SessionOptions(progress=progress, time_limit=time_limit, track_error=track_error, on_round=on_round)
    with log_lock(log_path):  # refused while another run or resume writes this log
        return _resume(log_path, renderer, session)


def _resume(log_path, renderer, session) -> AdaptiveResult:
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
    ctx = RunContext.assemble(renderer, method, s, reference=sl.reference(), log_path=log_path, session=session,
                              resumed=sl)
    ctx.planned = _replay(ctx, sl)
    return _drive(ctx)


def _replay(ctx, sl):
    """The log's committed rounds into the context's statistics and method, exactly as the live run took them.

    One batch per round (the statistics merge runs of same-pixel samples
    within a batch, so other batch boundaries would round differently for
    float64 values), one round in memory at a time; ``observe`` only for
    methods that read samples.  A pipelined run had planned round K (the one
    in flight when it stopped) from the rounds <= K-2 with round K-1 pending:
    that plan is made again between the replays of rounds K-2 and K-1,
    exactly as the live run made it (round 1, when the driver split the
    initial pass, depends only on the sample count).  Returns that plan
    (None: the session plans its first round itself).
    """
    k, w, h = sl.n_rounds, ctx.stats.width, ctx.stats.height
    features = sl.feature_names if ctx.method.requires.features != "none" else ()
    planned = None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", McreconWarning)  # the live run reported them
        for r in range(k):
            chunk = sl.read_all(rounds=[r], features=features)
            if ctx.schedule.pipeline and r == k - 1 and k >= 2:
                planned = ctx.plan(k, in_flight=len(chunk.positions),
                                   pending=_pixel_counts_of(chunk.positions, w, h))
                if planned[0] is None and planned[1] == "wait":
                    # the live run committed round K-1 first, then planned round K from it
                    planned = None
            _take_round(ctx, SampleBatch(chunk.positions, chunk.values, chunk.features), r, source=str(ctx.log_path))
    return planned


def _prefix_block_halves(ctx, writes) -> None:
    """A stratified run's final halves: its log split by prefix blocks, as the offline reconstruction of the log.

    The rounds' halves alternate within each pixel (a round cannot know how many samples a pixel will
    end with, which its prefix blocks need), and alternate samples of a Sobol sequence differ by the
    integrand's left-right difference, not by the mean's error: auto's estimates read from them
    are several times the error on a smooth pixel.  Once the last round is committed, the log holds
    every sample in each pixel's sequence order, so one counting pass and one splitting pass
    (:func:`~mcrecon.core.halves.split_halves`) give the halves an offline reconstruction of the same
    log reads, and the run's image is that reconstruction's.  Independent samples, a method without
    halves and a run without a log keep the rounds' halves."""
    halves = ctx.run.halves
    if halves is None or ctx.sampler == "independent" or ctx.log_path is None:
        return
    writes.written(wait=True)  # the last round on disk before the log is read
    log = read_log(ctx.log_path)
    ctx.run.halves = split_halves(log, nonfinite=ctx.nonfinite, features=tuple(halves.a.features))


def _drive(ctx, first=None) -> AdaptiveResult:
    """This session of the run: its loop, then the final image (``first``: a new run's :class:`_FirstCommit`)."""
    ctx.start()
    rnd, writes = _Round(ctx, first), _LogWrites(ctx)
    n_before = len(ctx.rounds)
    loop_t0 = time.perf_counter()
    try:
        try:
            loop = _loop_pipelined if ctx.schedule.pipeline else _loop_sequential
            stopped, round_index = loop(ctx, rnd, writes)
            loop_s = time.perf_counter() - loop_t0
            tf = time.perf_counter()
            rng, _ = round_seeds(ctx.schedule.seed, round_index)
            _prefix_block_halves(ctx, writes)
            image = ctx.method.finish(ctx.run, ctx.schedule.final_state(ctx.stats, round_index, rng,
                                                                        committed=ctx.committed))
        finally:
            # the last round's log write (a sequential loop leaves it running behind): committed before
            # the run returns, whatever the final image did
            writes.drain()
    finally:
        ctx.bar.close()
    clock = ctx.clock
    eval_s = sum(float(r.get("eval_seconds", 0.0)) for r in ctx.rounds[len(ctx.rounds) - clock.new_rounds:])
    return AdaptiveResult(image=np.asarray(image, dtype=np.float64), stats=ctx.stats, rounds=ctx.rounds,
                          stopped=stopped, log=ctx.log_path, method=ctx.method, run=ctx.run,
                          pipelined=ctx.schedule.pipeline, resumed_rounds=n_before,
                          loop_seconds=loop_s - eval_s, idle_seconds=max(loop_s - eval_s - clock.render_seconds, 0.0),
                          toolkit_cpu_seconds=clock.toolkit_cpu + sum(e["cpu"] for e in clock.timeline.events
                                                                      if e.get("helper")),
                          finish_seconds=time.perf_counter() - tf,
                          timeline=clock.timeline.events)

__dir__ = _public_dir(__name__)

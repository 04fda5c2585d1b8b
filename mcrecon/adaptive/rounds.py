"""One round of an adaptive run: render, validate, commit; the sequential and pipelined loops.

Every function here reads the run from its :class:`~.context.RunContext`
(``ctx``) and accounts into the context's clock.
"""

from __future__ import annotations

import contextlib
import time
import warnings
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from ..errors import InputError, McreconWarning, RendererError
from ..io.logformat import cast_positions
from ..io.writer import append_log, set_run_settings, update_round_record, write_log
from ..io.reader import read_log
from ..core.requests import SampleBatch, validate_reply_counted
from ..core.features import check_features, layout_of, take_rows, usable_layout
from ..core.samples import (FLOAT32_MAX, apply_nonfinite, check_memory, float32_loses_spread)
from .schedule import _adaptive_state, _committed, _pixel_counts_of, _request_counts, round_seeds


#: ``observe=`` of :func:`_take_round` and :meth:`Rounds.commit`: ``observe`` is returned, not run.
DEFER = "defer"


def _take_round(ctx, batch, round_index, *, source, n_nonfinite=None, timeline=None, counts=None, observe=None):
    """A committed round into the run's statistics and, for methods that read samples, into ``observe``.

    The one path of the live run and of a resume's replay: the method, its
    run state, the statistics and the NaN/Inf policy are the context's;
    ``source`` names the round's origin in warnings and errors.  ``observe`` sees
    the round after the run's NaN/Inf policy, exactly as the statistics did.
    ``n_nonfinite`` (rows with a NaN or Inf value) is given by the live run,
    whose reply :func:`validate_reply` has already checked (shapes, dtypes,
    positions on the film): the statistics then take the arrays without
    checking them again -- the same numbers as ``stats.add`` would ingest
    (``check_samples`` returns contiguous arrays of the given float dtype).
    ``observe`` says where and when the method's ``observe`` runs: None, here
    after the statistics; an idle one-thread executor (live runs only): the statistics
    ingest the round there while ``observe`` runs here -- they read the
    same arrays and write disjoint state, both compiled kernels that release
    the GIL -- and both are done when this returns.
    ``counts`` (H, W): the round's samples per pixel when the caller knows them (a live run: the
    request's, which the validation has matched pixel by pixel), so that they are not counted again
    from the positions (a bincount over every sample of the round); a resume's replay counts them.
    :data:`DEFER` (a live run's pipelined commit, for a method that plans before it observes:
    :func:`plans_before_observe`): the statistics take the round here, and ``observe`` is returned as a
    callable for the caller to run once it has planned (None when there is nothing to observe).
    """
    defer_observe = observe is DEFER
    helper = None if (observe is None or defer_observe) else observe
    method, stats, nonfinite = ctx.method, ctx.stats, ctx.nonfinite
    # every row the renderer delivered (NaN/Inf included) took an index of its pixel's sequence
    # (a context without the count, a test's stand-in, only ingests)
    rendered = getattr(ctx, "rendered", None)
    if rendered is not None:
        rendered += _pixel_counts_of(batch.positions, stats.width, stats.height) if counts is None else counts
    strata = getattr(ctx, "strata", None)
    if strata is not None:  # every row, NaN/Inf included, in its pixel's sequence order
        strata.add(batch.positions, batch.values)
    # A method that reads no pixel statistics (requires.statistics False) reads the features of its
    # rounds in observe only: the statistics keep none (nothing would read their sums), and the context
    # holds the layout that the rounds' features are checked against.
    own_layout = not method.requires.statistics and hasattr(ctx, "feature_layout")
    layout = ctx.feature_layout if own_layout else (layout_of(stats.features) if stats.features else None)
    if method.requires.features != "none" and batch.features and not layout and stats.n_samples == 0:
        # the renderer's first round says which features it sends; every later round sends the same
        layout = usable_layout(batch.features)
        if own_layout:
            ctx.feature_layout = layout
        else:
            stats.keep_features(layout)
    feats, n_fz = (check_features(batch.features, len(batch.positions), where=source, layout=layout)
                   if layout else ({}, 0))
    kept = feats if stats.features else {}  # what the statistics take
    if n_nonfinite is None:
        stats.add(batch.positions, batch.values, features=kept, nonfinite=nonfinite, source=source)
        if n_fz and not kept:  # counted as the statistics count them when they keep the features
            stats.n_feature_zeroed += int(n_fz)
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
                f2 = take_rows(kept, np.isfinite(val).all(axis=1)) if (kept and n_bad and nonfinite == "drop") \
                    else kept
                p2, v2 = apply_nonfinite(pos, val, n_bad, nonfinite, where=source)
                stats._ingest(p2, v2, n_bad, f2, n_fz, nonfinite=nonfinite, source=source)
            if timeline is not None:
                timeline.add("ingest", round_index, t, time.perf_counter(), time.thread_time() - c, **where)

        # In the helper only when the ingest cannot warn (no NaN/Inf row): the warnings
        # machinery is not thread-safe, and observe() may filter warnings meanwhile.
        if helper is not None and method.requires.samples and not n_bad:
            pending = helper.submit(ingest, helper=True)
            try:
                _observe(ctx, SampleBatch(pos, val, feats), n_bad, round_index, source=source, timeline=timeline)
            finally:
                pending.result()  # the statistics are complete before anything else happens
            return
        ingest()
    if method.requires.samples:
        if defer_observe:
            return lambda: _observe(ctx, SampleBatch(pos, val, feats), n_bad, round_index, source=source,
                                    timeline=timeline)
        _observe(ctx, SampleBatch(pos, val, feats), n_bad, round_index, source=source, timeline=timeline)
    return None


def plans_before_observe(method) -> bool:
    """Whether a pipelined run may plan the next round before the method observes the round it commits:
    the method reads samples (``requires.samples``) and declares ``plans_before_observe = True``, its plan
    with a round in flight reading only the committed counts and ``state.pending`` (splat's doubling
    rounds).  The plan is then the one made after ``observe`` (the same request), and the renderer
    renders it while the toolkit thread observes."""
    return bool(method.plans_before_observe) and bool(method.requires.samples)


def _observe(ctx, batch, n_bad, round_index, *, source, timeline):
    """``observe`` the round after the NaN/Inf policy; with the features the statistics keep (same rows)."""
    pos, val, feats, nonfinite = batch.positions, batch.values, batch.features or {}, ctx.nonfinite
    if feats and n_bad and nonfinite == "drop":
        feats = take_rows(feats, np.isfinite(val).all(axis=1))
    pos, val = apply_nonfinite(pos, val, n_bad, nonfinite, where=source)
    with (timeline.phase("observe", round_index) if timeline is not None else contextlib.nullcontext()):
        ctx.method.observe(ctx.run, SampleBatch(pos, val, feats), round_index)


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


class _Round:
    """What the toolkit does with one reply: validate, store, count (shared by both loops).

    ``first``: a new run's first commit (``adaptive.run._FirstCommit``): until a round is on disk the
    method may refuse a reply it cannot take (nfor without features) before anything is stored, and the
    first append publishes the new log.  A resumed run has none.
    """

    def __init__(self, ctx, first=None):
        self.ctx = ctx
        self.first = first
        self.name, self.c, self.log_path = ctx.name, len(ctx.stats.channels), ctx.log_path
        self.storage_dtype = ctx.storage_dtype  # ``auto``: resolved on the first reply
        self.warned = set()
        self.fresh_replies = bool(getattr(ctx.renderer, "fresh_replies", False))  # each reply's arrays are new

    @property
    def timeline(self):
        return self.ctx.clock.timeline

    def receive(self, req, reply, round_index):
        """The validated reply (stored precision) and its count of non-finite rows; nothing stored yet."""
        with self.timeline.phase("validate", round_index):
            batch, n_bad = self._receive(req, reply, round_index)
            decided = self.ctx.note_sampler(round_index)
            if decided is not None and self.log_path is not None:
                # the run's first reply, nothing appended yet: a resume plans with the same sampler
                set_run_settings(self.log_path, {**(read_log(self.log_path).run_settings or {}), "sampler": decided})
        if self.first is not None and not self.first.committed:
            # a refused run leaves no log, so its retry is not refused
            self.ctx.method.refuse_reply(batch)
        return batch, n_bad

    def _receive(self, req, reply, round_index):
        # the rows with a NaN or Inf value are counted in the validation's one pass; the cast to
        # the log's dtype keeps them (finite values beyond float32's range are refused there)
        # with a log, float32 positions go to its dtype once (in _to_storage), not through float64 first
        batch, n_bad = validate_reply_counted(req, reply, n_channels=self.c, renderer=self.name,
                                              keep_float32=self.log_path is not None, warned=self.warned)
        if self.storage_dtype == "auto":
            self.storage_dtype = _resolve_storage(self.log_path, np.asarray(batch.values).dtype)
        if self.log_path is not None:
            batch = self._to_storage(batch, round_index)
        val = np.ascontiguousarray(batch.values)
        if self.ctx.nonfinite == "raise" and n_bad:
            raise RendererError(self.name, "values", f"{n_bad} sample(s) with NaN or Inf in round "
                                f"{round_index} (policy nonfinite='raise'); nothing of this round was stored")
        return SampleBatch(np.ascontiguousarray(batch.positions), val, batch.features), n_bad

    def _to_storage(self, batch, round_index) -> SampleBatch:
        """Cast a validated reply to the log's dtype, refusing what float32 cannot hold."""
        val, dtype, name = np.asarray(batch.values), self.storage_dtype, self.name
        if dtype == "float32" and val.dtype != np.float32:
            big = np.isfinite(val) & (np.abs(val) > FLOAT32_MAX)
            if big.any():
                raise InputError(str(self.log_path), "storage_dtype", f"round {round_index} from {name} holds "
                                 f"{int(big.any(axis=1).sum())} sample(s) beyond float32's range (up to "
                                 f"{float(np.abs(val[big]).max()):.3g}); nothing of this round was stored, but "
                                 "this log stores float32: start the run again with a new log and "
                                 "storage_dtype='auto' or 'float64' (--storage-dtype auto)")
            if "spread" not in self.warned:
                stats = self.ctx.stats
                lost = float32_loses_spread(batch.positions, val, width=stats.width, height=stats.height)
                if lost:
                    self.warned.add("spread")
                    warnings.warn(f"{name}: round {round_index}: float32 storage loses the spread of the samples "
                                  f"in {lost} pixel(s) (e.g. 1e6 +- 1e-3 rounds to one value, variance 0); keep it "
                                  "with storage_dtype='auto' or 'float64' (--storage-dtype auto)", McreconWarning,
                                  stacklevel=4)
        return SampleBatch(cast_positions(batch.positions, dtype), val.astype(dtype, copy=False), batch.features)

    def commit(self, batch, n_bad, record, toolkit_s, *, writer=None, writer_copy=None, counts=None, observe=None):
        """Append to the log, then into the statistics (and ``observe``; with ``observe`` an idle
        one-thread executor, the two at once: see :func:`_take_round`).

        ``writer`` (a one-thread executor): the append is submitted there and its future returned;
        the statistics take the round meanwhile.  The round is committed when the future is done.
        ``writer_copy``: hand the writer a copy of the arrays (default: unless the renderer's replies
        are ``fresh_replies``); not needed when the caller waits for the write before the next render.
        ``counts``: the round's samples per pixel, known from its validated request (:func:`_take_round`).
        ``observe`` :data:`DEFER`: ``observe`` is not run but returned (:func:`_take_round`): (pending, observe).
        """
        pending = None
        if self.log_path is not None:
            rec = {**record, "toolkit_seconds": toolkit_s, "wall_seconds": self.ctx.clock.wall()}
            if writer is None:
                self._append(batch, record["round"], rec)
            else:
                # written while the renderer renders the next round: a renderer that may fill the same
                # buffers again (not ``fresh_replies``) hands the writer a copy
                copy = (not self.fresh_replies) if writer_copy is None else writer_copy
                kept = batch if not copy else SampleBatch(
                    np.array(batch.positions), np.array(batch.values),
                    {k: np.array(v) for k, v in batch.features.items()} if batch.features else batch.features)
                pending = writer.submit(self._append, kept, record["round"], rec, True)
        deferred = _take_round(self.ctx, batch, record["round"], source=self.name, n_nonfinite=n_bad,
                               timeline=self.timeline, counts=counts, observe=observe)
        return (pending, deferred) if observe is DEFER else pending

    def _append(self, batch, round_index, rec, on_writer=False):
        # on the writer thread: tagged as a helper's phase (its CPU counts in toolkit_cpu_seconds)
        with self.timeline.phase("append", round_index, **({"helper": True} if on_writer else {})):
            # checked: receive() validated the reply (validate_reply, then the log's dtype):
            # the commit does not scan it again
            append_log(self.log_path, batch.positions, batch.values, round_index=round_index,
                       features=batch.features if batch.features else None, checked=True, round_record=rec)
        if self.first is not None:
            self.first.appended(self.ctx, self)

    def evaluate(self, record, round_index):
        """The error of the image after the round (not part of the run's time)."""
        from ..core.metrics import relative_mse

        ctx = self.ctx
        if ctx.reference is None or not ctx.track_error:
            return 0.0
        te = time.perf_counter()
        rng, _ = round_seeds(0, 0)
        st = _adaptive_state(ctx.stats, ctx.schedule, round_index, _committed(ctx.stats), rng, committed=ctx.committed)
        with self.timeline.phase("evaluate", round_index):
            record["error"] = relative_mse(ctx.method.finish(ctx.run, st), ctx.reference, eps=ctx.eps)
        record["eval_seconds"] = time.perf_counter() - te
        return record["eval_seconds"]


def _render(ctx, req):
    """Call the renderer: (reply, seconds it reports as its own, seconds of the call beyond them)."""
    renderer = ctx.renderer
    # A round this machine cannot hold (box doubles its rounds up to 1/8 of the budget) is refused
    # before the renderer fills the memory with it.  A round's peak is about 4x its positions and
    # values as float64 (the reply, the renderer's and the validation's temporaries).
    check_memory("adapt", "spp", 32.0 * req.total * (2 + len(renderer.channels)),
                 f"round {req.round_index}'s {req.total} samples",
                 "lower the budget (--spp); the rounds committed before are in the log")
    ctx.bar.rendering(req.round_index, req.total)
    t1 = time.perf_counter()
    reply = renderer.render(req)
    t2 = time.perf_counter()
    render_s = getattr(renderer, "last_render_seconds", None)
    render_s = float(render_s) if render_s is not None else t2 - t1
    ctx.clock.timeline.add("render", req.round_index, t1, t2, 0.0, own=render_s)
    # Time in the renderer call beyond what the renderer reports as its own
    # (file exchange, conversions) belongs to the toolkit side of the run.
    ctx.clock.render_seconds += min(render_s, t2 - t1)
    return reply, render_s, max((t2 - t1) - render_s, 0.0)


def _finish_round(ctx, record, *, logged=False):
    """A committed round's full record: into the log, the run's records, ``on_round`` and the progress.

    ``logged``: the full record is in the log already (written by the toolkit thread that observed the
    round while this thread rendered: one thread writes the log at a time)."""
    if ctx.log_path is not None and not logged:
        # The commit stored the times known then; now the full round
        # (statistics, observe, error) is known: a resume reports these.
        update_round_record(ctx.log_path, record)
    ctx.rounds.append(record)
    ctx.clock.new_rounds += 1
    if ctx.on_round is not None:
        ctx.on_round(record)
    ctx.bar.update(_committed(ctx.stats), record["round"], record["wall_seconds"])


def _wait_out(fut):
    """``fut.result()``, waited for to the end even through Ctrl-C (raised after it): a log write is
    never abandoned half way while the run still holds the log's lock."""
    interrupted = None
    while True:
        try:
            out = fut.result()
            break
        except KeyboardInterrupt as exc:
            interrupted = exc
    if interrupted is not None:
        raise interrupted
    return out


class _LogWrites:
    """The log's writer thread and the round written behind the loop (at most one, in ``behind``).

    The sequential loop hands a round's append to :attr:`executor` and goes on
    planning and rendering; the pipelined loop waits for each append.  The run
    calls :meth:`drain` once its loop has ended (after the final image, which
    overlaps the last write, or on the way out of an error): the round written
    behind is then committed and the thread ends.  Without a log there is no
    thread, and each round is finished as soon as it is handed over.
    """

    def __init__(self, ctx):
        self.ctx = ctx
        self.executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mcrecon-log") \
            if ctx.log_path is not None else None
        self.behind = []  # (future or None, record)

    def hand_over(self, pending, record) -> None:
        """The round whose append is ``pending`` (None: none) is written behind; without a thread it is done."""
        self.behind.append((pending, record))
        if self.executor is None:
            self.written(wait=True)

    def written(self, *, wait) -> bool:
        """Finish the round written behind once it is on disk (``wait``: wait for it); True when none is left.

        A failed write raises here: the run stops with that round not committed (its samples were not
        lost silently: the error says which file and why).  Ctrl-C while waiting does not abandon the
        write (the log's lock is held until it is done): the wait goes on, and the interrupt is raised
        after it."""
        if not self.behind:
            return True
        fut, record = self.behind[0]
        if fut is not None and not (wait or fut.done()):
            return False
        self.behind.clear()
        try:
            if fut is not None:
                _wait_out(fut)
        except KeyboardInterrupt:  # raised once the write was done: the round is committed
            _finish_round(self.ctx, record)
            raise
        _finish_round(self.ctx, record)
        return True

    def drain(self) -> None:
        """Wait for the round written behind (it is committed before the run returns), then end the thread."""
        try:
            self.written(wait=True)
        finally:
            if self.executor is not None:
                self.executor.shutdown(wait=True)


def _loop_sequential(ctx, rnd, writes):
    """Plan, render, validate, commit, one round after the other; the log written behind.

    Each plan sees every round before it, as in a run without a log.  With a
    log, round j is written by ``writes``' thread while round j+1 is planned and
    rendered (the renderer waits for nothing but its plan); round j+1 is
    submitted only once round j is on disk, and ``on_round`` is called for a
    round once it is committed.  A run stopped meanwhile (Ctrl-C, a
    renderer's error) first waits for that write (:meth:`_LogWrites.drain`):
    nothing rendered and handed over is lost; a killed one resumes from the
    rounds on disk (the one being written is planned and rendered again, the
    same round: the plan and the seeds depend on the rounds before it only).
    The last round's write is left running behind: the run drains it after
    the final image (the two overlap).  Returns (why the run stopped, the
    next round's index).
    """
    # a method that reads samples observes a round while a helper thread ingests it
    helper = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mcrecon-ingest") \
        if ctx.method.requires.samples else None
    try:
        return _sequential_rounds(ctx, rnd, writes, helper)
    finally:
        if helper is not None:
            helper.shutdown(wait=True)


def _sequential_rounds(ctx, rnd, writes, helper):
    stats, schedule, clock = ctx.stats, ctx.schedule, ctx.clock
    round_index = ctx.round_index
    while True:
        if _committed(stats) >= schedule.budget:
            return "budget", round_index
        if round_index >= schedule.max_rounds:
            return "max_rounds", round_index
        if clock.past(schedule.time_limit):
            return "time_limit", round_index
        t0, c0 = time.perf_counter(), time.thread_time()
        with clock.timeline.phase("plan", round_index):
            req, why = ctx.plan(round_index)
        if req is None:
            return why, round_index
        writes.written(wait=False)  # done while planning, usually
        tp, cp = time.perf_counter(), time.thread_time()
        reply, render_s, extra_s = _render(ctx, req)
        t2, c2 = time.perf_counter(), time.thread_time()
        batch, n_bad = rnd.receive(req, reply, round_index)
        toolkit_s = (tp - t0) + (time.perf_counter() - t2) + extra_s
        record = {"round": round_index, "samples": len(batch),
                  "samples_total": _committed(stats) + len(batch), "renderer_seconds": render_s}
        t3 = time.perf_counter()
        writes.written(wait=True)  # one round on its way at a time
        pending = rnd.commit(batch, n_bad, record, toolkit_s, observe=helper, writer=writes.executor,
                             counts=_request_counts(req))
        toolkit_s += time.perf_counter() - t3
        clock.toolkit_cpu += (cp - c0) + (time.thread_time() - c2)
        record["toolkit_seconds"] = toolkit_s
        record["wall_seconds"] = clock.wall()
        clock.exclude(rnd.evaluate(record, round_index))  # evaluation is not part of the run's time
        writes.hand_over(pending, record)
        round_index += 1


def _loop_pipelined(ctx, rnd, writes):
    """Render round j in this thread while the toolkit thread commits round j-1 and plans round j+1.

    The plan of round j+1 sees the rounds <= j-1 and round j as ``pending``
    counts; the plan of round 1 waits for round 0 (there is nothing to plan
    from before) unless it is the second half of the driver's split initial
    pass: then it is made while round 0 renders, and round 0's commit
    overlaps round 1.  The renderer stays in the calling thread (renderers with
    thread affinity, signals, Ctrl-C); the toolkit's heavy parts release
    the GIL (the statistics' and the methods' compiled kernels run with
    ``nogil``, numpy's large-array loops, the filtering pool); h5py's
    writes hold it for their duration.  Each round's append goes to ``writes``' thread and is
    waited for.  Returns (why the run stopped, the next round's index).
    """
    stats, schedule, clock = ctx.stats, ctx.schedule, ctx.clock
    writer = writes.executor

    def commit(prev, carry, helper=None, defer_observe=False):
        """Validate and commit ``prev`` = (round, request, reply, renderer s, extra s): its finished record.

        ``helper``: the toolkit thread when it is idle (round 0 and the last round, committed by
        this thread while nothing renders), to ingest while ``observe`` runs.  ``defer_observe``:
        (record, observe), ``observe`` a callable that observes the round and completes the record's
        times (:func:`plans_before_observe`), or None.
        """
        t0, c0 = time.perf_counter(), time.thread_time()
        k, preq, reply, render_s, extra_s = prev
        batch, n_bad = rnd.receive(preq, reply, k)
        record = {"round": k, "samples": len(batch), "samples_total": _committed(stats) + len(batch),
                  "renderer_seconds": render_s}
        # committed by this thread while nothing renders (``helper``): the log's append runs beside the
        # statistics and observe, and is done before the round counts as committed
        pending = rnd.commit(batch, n_bad, record, carry + extra_s + (time.perf_counter() - t0),
                             writer=writer if helper is not None else None, writer_copy=False,
                             counts=_request_counts(preq), observe=DEFER if defer_observe else helper)
        observe = None
        if defer_observe:
            pending, observe = pending
        if pending is not None:
            _wait_out(pending)

        def times(t_extra=0.0):
            # a round's toolkit time: its validation and commit, the beyond-renderer part
            # of its render call, and the plan that made its request
            record["toolkit_seconds"] = carry + extra_s + (time.perf_counter() - t0) - t_extra
            record["wall_seconds"] = clock.wall()

        times()
        clock.toolkit_cpu += time.thread_time() - c0
        if not defer_observe:
            return record
        if observe is None:
            return record, None

        def observe_round():
            t1, c1 = time.perf_counter(), time.thread_time()
            observe()
            # the commit's time and the observe's, without the plan made between them
            record["toolkit_seconds"] += time.perf_counter() - t1
            record["wall_seconds"] = clock.wall()
            clock.toolkit_cpu += time.thread_time() - c1

        return record, observe_round

    def plan(j, req_j):
        """The plan of round j+1 from what is committed, round j (``req_j``) in flight: ((req, why), seconds)."""
        t0, c0 = time.perf_counter(), time.thread_time()
        with clock.timeline.phase("plan", j + 1):
            if j + 1 >= schedule.max_rounds:
                out = (None, "max_rounds")
            elif req_j is None:
                out = ctx.plan(j + 1)
            else:
                out = ctx.plan(j + 1, in_flight=req_j.total, pending=_request_counts(req_j))
        if out[0] is not None and prepare is not None:
            # the renderer's own preparation of the request (e.g. the Mitsuba bridge's jittered
            # positions), here while it still renders round j rather than inside its next call
            with clock.timeline.phase("prepare", j + 1):
                prepare(out[0])
        clock.toolkit_cpu += time.thread_time() - c0
        return out, time.perf_counter() - t0

    # optional: a renderer that computes part of its reply ahead (same reply with or without)
    prepare = getattr(ctx.renderer, "prepare", None)
    prepare = prepare if callable(prepare) else None

    def job(prev, carry, j, req_j, early=None, after=None):
        # the toolkit thread's work while round j renders.  ``early`` (a Future; a method that plans
        # before it observes): the plan is set there as soon as it is made, and the round's observe
        # (and its evaluation) follow while the renderer goes on with the planned round; ``after``: the
        # job before it (done, on this one thread), whose failure stops this one before it commits
        try:
            if after is not None and after.exception() is not None:
                raise after.exception()
            record = observe = None
            if prev is not None:
                if early is None:
                    record = commit(prev, carry)
                    record["_eval"] = rnd.evaluate(record, record["round"])
                else:
                    record, observe = commit(prev, carry, defer_observe=True)
            out, secs = plan(j, req_j)
            # round 1 planned blind (prev None): round 0's plan time goes with round 1's
            planned = (out, secs + (carry if prev is None else 0.0))
        except BaseException as exc:
            if early is not None:
                early.set_exception(exc)
            raise
        if early is not None:
            early.set_result(planned)
            if observe is not None:
                observe()
            if record is not None:
                record["_eval"] = rnd.evaluate(record, record["round"])
                if ctx.log_path is not None:
                    # the full record, from this thread: the next round's append follows it here, while
                    # the calling thread renders (it finishes the round without writing the log)
                    update_round_record(ctx.log_path, {k: v for k, v in record.items() if k != "_eval"})
                    record["_logged"] = True
        return record, planned

    def done(record):
        clock.exclude(record.pop("_eval", 0.0))  # evaluation is not part of the run's time
        _finish_round(ctx, record, logged=record.pop("_logged", False))

    blind = schedule.initial_rounds == 2  # round 1 is the second half of the driver's initial pass
    # plan, then observe (splat): the renderer goes on as soon as the next round is planned, and the
    # job that observes (``behind``) is finished once the round after it has rendered
    early_plans = plans_before_observe(ctx.method)
    behind = None

    def finish_behind():
        """The job still observing (early plans): wait for it and finish its round."""
        nonlocal behind
        if behind is not None:
            b, behind = behind, None
            record = b.result()[0]
            if record is not None:
                done(record)

    j = ctx.round_index
    planned = ctx.planned
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
            if j >= schedule.max_rounds:
                stopped = "max_rounds"
                break
            if clock.past(schedule.time_limit):
                stopped = "time_limit"
                break
            # round 1 is planned from round 0, after it (no toolkit work to overlap), unless
            # it is the driver's second half of a split initial pass
            first = j == 0 and not blind
            early = None
            if not first:
                early = Future() if early_plans else None
                fut = pool.submit(job, uncommitted, carry, j, req, early, behind)
                uncommitted = None
            try:
                reply, render_s, extra_s = _render(ctx, req)
                finish_behind()  # observed while this round rendered
            except BaseException:
                # the rounds before are committed first (nothing committed is lost);
                # a failure of such a commit is the run's first error
                for f in [b for b in (behind, fut) if b is not None]:
                    behind = fut = None
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
                if early is not None:
                    (req, why), carry = early.result()
                    behind = f  # still observing the round it committed
                else:
                    record, ((req, why), carry) = f.result()
                    if record is not None:
                        done(record)
                uncommitted = rendered
                if req is None:
                    finish_behind()  # nothing renders next: the round before is committed first
                if req is None and why == "wait":
                    # the method waits for the round just rendered (it asked for nothing):
                    # commit it here, then plan the next round from it, as round 1 after round 0
                    prev, uncommitted = uncommitted, None
                    record = commit(prev, carry, helper=pool)
                    record["_eval"] = rnd.evaluate(record, record["round"])
                    done(record)
                    (req, why), carry = plan(j, None)
            j += 1
        finish_behind()  # a run stopped with a round in flight (max_rounds, time_limit) commits it below
        if uncommitted is not None:
            # the last round: commit it (nothing is left to plan)
            prev, uncommitted = uncommitted, None
            record = commit(prev, carry, helper=pool)
            record["_eval"] = rnd.evaluate(record, record["round"])
            done(record)
        return stopped, j
    finally:
        for f in (behind, fut):
            if f is not None:
                with contextlib.suppress(BaseException):
                    f.result()
        pool.shutdown(wait=True)

"""One round of an adaptive run: render, validate, commit; the sequential and pipelined loops.
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
import warnings
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..errors import InputError, McreconWarning, RendererError
from ..io.logformat import cast_positions
from ..io.writer import append_log, set_run_settings, update_round_record, write_log
from ..io.reader import read_log
from ..core.requests import SampleBatch, _validate_reply
from ..core.features import check_features, layout_of, take_rows, usable_layout
from ..core.samples import (FLOAT32_MAX, apply_nonfinite, check_memory, float32_loses_spread)


from .schedule import _adaptive_state, _committed, _plan_round, _request_counts, round_seeds

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
    if method.requires.features != "none" and batch.features and not stats.features and stats.n_samples == 0:
        # the renderer's first round says which features it sends; every later round sends the same
        stats.keep_features(usable_layout(batch.features))
    feats, n_fz = (check_features(batch.features, len(batch.positions), where=source, layout=layout_of(stats.features))
                   if stats.features else ({}, 0))
    if n_nonfinite is None:
        stats.add(batch.positions, batch.values, features=feats, nonfinite=nonfinite, source=source)
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
                f2 = take_rows(feats, np.isfinite(val).all(axis=1)) if (feats and n_bad and nonfinite == "drop") \
                    else feats
                p2, v2 = apply_nonfinite(pos, val, n_bad, nonfinite, where=source)
                stats._ingest(p2, v2, n_bad, f2, n_fz, nonfinite=nonfinite, source=source)
            if timeline is not None:
                timeline.add("ingest", round_index, t, time.perf_counter(), time.thread_time() - c, **where)

        # In the helper only when the ingest cannot warn (no NaN/Inf row): the warnings
        # machinery is not thread-safe, and observe() may filter warnings meanwhile.
        if helper is not None and method.requires.samples and not n_bad:
            pending = helper.submit(ingest, helper=True)
            try:
                _observe(method, run, pos, val, n_bad, nonfinite, source, round_index, timeline, feats)
            finally:
                pending.result()  # the statistics are complete before anything else happens
            return
        ingest()
    if method.requires.samples:
        _observe(method, run, pos, val, n_bad, nonfinite, source, round_index, timeline, feats)


def _observe(method, run, pos, val, n_bad, nonfinite, source, round_index, timeline, feats=None):
    """``observe`` the round after the NaN/Inf policy; with the features the statistics keep (same rows)."""
    feats = feats or {}
    if feats and n_bad and nonfinite == "drop":
        feats = take_rows(feats, np.isfinite(val).all(axis=1))
    pos, val = apply_nonfinite(pos, val, n_bad, nonfinite, where=source)
    with (timeline.phase("observe", round_index) if timeline is not None else contextlib.nullcontext()):
        method.observe(run, SampleBatch(pos, val, feats), round_index)


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
                 storage_dtype, wall, timeline, fresh_replies=False):
        self.method, self.run, self.stats = method, run, stats
        self.timeline = timeline
        self.name, self.c, self.log_path, self.nonfinite = name, c, log_path, nonfinite
        self.ref, self.track_error, self.eps, self.budget = ref, track_error, eps, budget
        self.storage_dtype = storage_dtype
        self.warned = set()
        self.wall = wall  # () -> run wall seconds now
        self.fresh_replies = fresh_replies  # the renderer's: each reply's arrays are new (see commit)

    def receive(self, req, reply, round_index):
        """The validated reply (stored precision) and its count of non-finite rows; nothing stored yet."""
        with self.timeline.phase("validate", round_index):
            return self._receive(req, reply, round_index)

    def _receive(self, req, reply, round_index):
        # the rows with a NaN or Inf value are counted in the validation's one pass; the cast to
        # the log's dtype keeps them (finite values beyond float32's range are refused there)
        # with a log, float32 positions go to its dtype once (in _to_storage), not through float64 first
        batch, n_bad = _validate_reply(req, reply, n_channels=self.c, renderer=self.name,
                                       keep_float32=self.log_path is not None)
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

    def commit(self, batch, n_bad, record, toolkit_s, helper=None, writer=None, writer_copy=None):
        """Append to the log, then into the statistics (and ``observe``; with ``helper``, an idle
        one-thread executor, the two at once: see :func:`_take_round`).

        ``writer`` (a one-thread executor): the append is submitted there and its future returned;
        the statistics take the round meanwhile.  The round is committed when the future is done.
        ``writer_copy``: hand the writer a copy of the arrays (default: unless the renderer's replies
        are ``fresh_replies``); not needed when the caller waits for the write before the next render.
        """
        pending = None
        if self.log_path is not None:
            rec = {**record, "toolkit_seconds": toolkit_s, "wall_seconds": self.wall()}
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
        _take_round(self.method, self.run, self.stats, batch, record["round"], self.nonfinite, self.name,
                    n_nonfinite=n_bad, timeline=self.timeline, helper=helper)
        return pending

    def _append(self, batch, round_index, rec, on_writer=False):
        # on the writer thread: tagged as a helper's phase (its CPU counts in toolkit_cpu_seconds)
        with self.timeline.phase("append", round_index, **({"helper": True} if on_writer else {})):
            # checked: receive() validated the reply (validate_reply, then the log's dtype):
            # the commit does not scan it again
            append_log(self.log_path, batch.positions, batch.values, round_index=round_index,
                       features=batch.features if batch.features else None, checked=True, round_record=rec)

    def evaluate(self, record, round_index):
        """The error of the image after the round (not part of the run's time)."""
        from ..core.metrics import relative_mse

        if self.ref is None or not self.track_error:
            return 0.0
        te = time.perf_counter()
        rng, _ = round_seeds(0, 0)
        st = _adaptive_state(self.stats, round_index, self.budget, _committed(self.stats), rng, self.ref)
        with self.timeline.phase("evaluate", round_index):
            record["error"] = relative_mse(self.method.finish(self.run, st), self.ref, eps=self.eps)
        record["eval_seconds"] = time.perf_counter() - te
        return record["eval_seconds"]


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
    """Plan, render, validate, commit, one round after the other; the log written behind.

    Each plan sees every round before it, as in a run without a log.  With a
    log, round j is written by a writer thread while round j+1 is planned and
    rendered (the renderer waits for nothing but its plan); round j+1 is
    submitted only once round j is on disk, and ``on_round`` is called for a
    round once it is committed.  A run stopped meanwhile (Ctrl-C, a
    renderer's error) first waits for that write: nothing rendered and
    handed over is lost; a killed one resumes from the rounds on disk (the
    one being written is planned and rendered again, the same round: the
    plan and the seeds depend on the rounds before it only).  The last
    round's write is left to ``acct["drain"]``, which the caller runs after
    the final image (the two overlap).
    """
    # a method that reads samples observes a round while a helper thread ingests it
    helper = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mcrecon-ingest") \
        if method.requires.samples else None
    writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mcrecon-log") \
        if rnd.log_path is not None else None
    behind = []  # (future or None, record): the round being written and its record, at most one

    def drain():
        try:
            _written(behind, rounds, on_round, bar, stats, rnd, acct, wait=True)
        finally:
            if writer is not None:
                writer.shutdown(wait=True)

    try:
        out = _sequential_rounds(renderer, method, run, stats=stats, rounds=rounds, round_index=round_index,
                                 budget=budget, seed=seed, ref=ref, time_limit=time_limit, max_rounds=max_rounds,
                                 on_round=on_round, bar=bar, clock=clock, rnd=rnd, acct=acct, helper=helper,
                                 writer=writer, behind=behind)
    except BaseException:
        drain()
        raise
    else:
        # the last round's write overlaps the final image: the caller drains it (``acct["drain"]``)
        acct["drain"] = drain
    finally:
        if helper is not None:
            helper.shutdown(wait=True)
    return out


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


def _written(behind, rounds, on_round, bar, stats, rnd, acct, *, wait):
    """Finish the round written behind once it is on disk (``wait``: wait for it); True when none is left.

    A failed write raises here: the run stops with that round not committed (its samples were not lost
    silently: the error says which file and why).  Ctrl-C while waiting does not abandon the write (the
    log's lock is held until it is done): the wait goes on, and the interrupt is raised after it."""
    if not behind:
        return True
    fut, record = behind[0]
    if fut is not None and not (wait or fut.done()):
        return False
    behind.clear()
    try:
        if fut is not None:
            _wait_out(fut)
    except KeyboardInterrupt:  # raised once the write was done: the round is committed
        _finish_round(record, rounds, on_round, bar, stats, rnd.log_path, acct)
        raise
    _finish_round(record, rounds, on_round, bar, stats, rnd.log_path, acct)
    return True


def _sequential_rounds(renderer, method, run, *, stats, rounds, round_index, budget, seed, ref, time_limit,
                       max_rounds, on_round, bar, clock, rnd, acct, helper, writer, behind):
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
        _written(behind, rounds, on_round, bar, stats, rnd, acct, wait=False)  # done while planning, usually
        tp, cp = time.perf_counter(), time.thread_time()
        reply, render_s, extra_s = _render(renderer, req, acct)
        t2, c2 = time.perf_counter(), time.thread_time()
        batch, n_bad = rnd.receive(req, reply, round_index)
        toolkit_s = (tp - t0) + (time.perf_counter() - t2) + extra_s
        record = {"round": round_index, "samples": len(batch),
                  "samples_total": _committed(stats) + len(batch), "renderer_seconds": render_s}
        t3 = time.perf_counter()
        _written(behind, rounds, on_round, bar, stats, rnd, acct, wait=True)  # one round on its way at a time
        pending = rnd.commit(batch, n_bad, record, toolkit_s, helper=helper, writer=writer)
        toolkit_s += time.perf_counter() - t3
        acct["cpu"] += (cp - c0) + (time.thread_time() - c2)
        record["toolkit_seconds"] = toolkit_s
        record["wall_seconds"] = rnd.wall()
        clock["wall_start"] += rnd.evaluate(record, round_index)  # evaluation is not part of the run's time
        behind.append((pending, record))
        if writer is None:
            _written(behind, rounds, on_round, bar, stats, rnd, acct, wait=True)
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
        # committed by this thread while nothing renders (``helper``): the log's append runs beside the
        # statistics and observe, and is done before the round counts as committed
        pending = rnd.commit(batch, n_bad, record, carry + extra_s + (time.perf_counter() - t0), helper=helper,
                             writer=writer if helper is not None else None, writer_copy=False)
        if pending is not None:
            _wait_out(pending)
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
    writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mcrecon-log") if rnd.log_path is not None else None
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
        if writer is not None:
            writer.shutdown(wait=True)

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
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import sys
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from .errors import InputError, McreconWarning, RendererError
from .io.samplelog import (MAX_PIXELS, append_log, cast_positions, log_lock, read_log, set_run_settings,
                           update_round_record, write_log)
from .methods import Method, get_method
from .methods.base import AdaptiveState, RunState
from .renderers.protocol import SampleBatch, validate_reply
from .renderers.spec import renderer_from_spec
from .samples import FLOAT32_MAX, NONFINITE_POLICIES, apply_nonfinite, check_reference, float32_loses_spread
from .stats import PixelStats

__all__ = ["adapt", "resume", "AdaptiveResult", "round_seeds", "STORAGE_DTYPES"]

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
        (cumulative, renderer + toolkit), ``error`` (relative MSE of the
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
    def __init__(self, enabled: bool | None, budget: int):
        self.enabled = sys.stderr.isatty() if enabled is None else bool(enabled)
        self.budget = max(budget, 1)

    def update(self, n: int, rnd: int, wall: float):
        if not self.enabled:
            return
        frac = min(n / self.budget, 1.0)
        bar = "#" * int(30 * frac)
        sys.stderr.write(f"\r[{bar:<30}] {100 * frac:5.1f}%  round {rnd}  {n} samples  {wall:6.1f} s")
        sys.stderr.flush()

    def close(self):
        if self.enabled:
            sys.stderr.write("\n")
            sys.stderr.flush()


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
          on_round: Callable[[dict], Any] | None = None) -> AdaptiveResult:
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
    settings = {
        "method": method.name, "method_options": dict(method.params), "spp": float(spp), "seed": int(seed),
        "nonfinite": nonfinite, "time_limit": time_limit, "width": w, "height": h,
        "channels": list(channels), "renderer": _renderer_name(renderer),
        "renderer_spec": dict(renderer_spec or {}), "storage_dtype": storage_dtype,
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
                      track_error=track_error, eps=eps, on_round=on_round)


def _start(renderer, method, *, w, h, channels, ref, budget, settings, seed, log_path, overwrite, metadata,
           storage_dtype, time_limit, progress, nonfinite, max_rounds, track_error, eps, on_round):
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
                storage_dtype=storage_dtype)


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
    # Replay the committed rounds exactly as the live run took them: one batch
    # per round (the statistics merge runs of same-pixel samples within a batch,
    # so other batch boundaries would round differently for float64 values),
    # one round in memory at a time; observe() only for methods that read samples.
    stats = PixelStats(w, h, channels, subpixels=method.requires.subpixels)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", McreconWarning)  # the live run reported them
        for r in range(sl.n_rounds):
            chunk = sl.read_all(rounds=[r])
            _take_round(method, run, stats, SampleBatch(chunk.positions, chunk.values), r, s["nonfinite"],
                        str(log_path))
    records = list(sl.round_records)
    elapsed = float(records[-1]["wall_seconds"]) if records else 0.0
    budget = int(round(float(s["spp"]) * w * h))
    tl = time_limit if time_limit is not None else s.get("time_limit")
    return _run(renderer, method, run, stats=stats, rounds=records, round_index=sl.n_rounds, budget=budget,
                seed=int(s["seed"]), log_path=log_path, ref=ref, time_limit=tl, progress=progress,
                nonfinite=s["nonfinite"], max_rounds=10_000, track_error=track_error, eps=0.01,
                elapsed=elapsed, on_round=on_round,
                storage_dtype=s.get("storage_dtype", "float32") if sl.n_samples == 0 else str(sl.value_dtype))


def _take_round(method, run, stats, batch, round_index, nonfinite, source) -> None:
    """A committed round into the statistics and, for methods that read samples, into ``observe``.

    The one path of the live run and of a resume's replay.  ``observe`` sees
    the round after the run's NaN/Inf policy, exactly as the statistics did.
    """
    stats.add(batch.positions, batch.values, nonfinite=nonfinite, source=source)
    if method.requires.samples:
        pos, val = np.asarray(batch.positions), np.asarray(batch.values)
        if val.ndim == 1:
            val = val[:, None]
        n_bad = int((~np.isfinite(val)).any(axis=1).sum()) if val.size else 0
        pos, val = apply_nonfinite(pos, val, n_bad, nonfinite, where=source)
        method.observe(run, SampleBatch(pos, val), round_index)


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


def _run(renderer, method, run, *, stats, rounds, round_index, budget, seed, log_path, ref, time_limit,
         progress, nonfinite, max_rounds, track_error, eps, elapsed, on_round,
         storage_dtype) -> AdaptiveResult:
    from .metrics import relative_mse

    name = _renderer_name(renderer)
    c = len(stats.channels)
    bar = _Progress(progress, budget)
    stopped = "budget"
    wall_start = time.perf_counter() - elapsed
    state = None
    warned = set()

    def committed() -> int:
        # Samples dropped by the non-finite policy were rendered and committed: they
        # count against the budget, or a renderer that keeps returning NaN never ends.
        return stats.n_samples + stats.n_dropped

    try:
        while True:
            if committed() >= budget:
                stopped = "budget"
                break
            if round_index >= max_rounds:
                stopped = "max_rounds"
                break
            if time_limit is not None and time.perf_counter() - wall_start >= time_limit:
                stopped = "time_limit"
                break
            t0 = time.perf_counter()
            rng, rseed = round_seeds(seed, round_index)
            state = AdaptiveState(stats, round_index, budget, committed(), rng, ref)
            req = method.plan(run, state)
            if req is None or req.total == 0:
                stopped = "converged" if req is None or committed() < budget else "budget"
                break
            if req.total > state.remaining:
                raise RuntimeError(f"method {method.name} planned {req.total} samples with only "
                                   f"{state.remaining} left in the budget (a bug in the method)")
            req = dataclasses.replace(req, round_index=round_index, seed=rseed)
            t1 = time.perf_counter()
            reply = renderer.render(req)
            t2 = time.perf_counter()
            render_s = getattr(renderer, "last_render_seconds", None)
            render_s = float(render_s) if render_s is not None else t2 - t1
            batch = validate_reply(req, reply, n_channels=c, renderer=name)
            if storage_dtype == "auto":
                storage_dtype = _resolve_storage(log_path, np.asarray(batch.values).dtype)
            if log_path is not None:
                batch = _to_storage(batch, storage_dtype, stats, name, round_index, warned, log_path)
            if nonfinite == "raise":
                bad = ~np.isfinite(np.asarray(batch.values)).all(axis=1)
                if bad.any():
                    raise RendererError(name, "values", f"{int(bad.sum())} sample(s) with NaN or Inf in round "
                                        f"{round_index} (policy nonfinite='raise'); nothing of this round was stored")
            # Time in the renderer call beyond what the renderer reports as its own
            # (file exchange, conversions) belongs to the toolkit side of the run.
            toolkit_s = (t1 - t0) + (time.perf_counter() - t2) + max((t2 - t1) - render_s, 0.0)
            record = {"round": round_index, "samples": len(batch),
                      "samples_total": committed() + len(batch), "renderer_seconds": render_s}
            t3 = time.perf_counter()
            if log_path is not None:
                append_log(log_path, batch.positions, batch.values, round_index=round_index,
                           features=batch.features if batch.features else None,
                           round_record={**record, "toolkit_seconds": toolkit_s,
                                         "wall_seconds": time.perf_counter() - wall_start})
            _take_round(method, run, stats, batch, round_index, nonfinite, name)
            toolkit_s += time.perf_counter() - t3
            record["toolkit_seconds"] = toolkit_s
            record["wall_seconds"] = time.perf_counter() - wall_start
            if ref is not None and track_error:
                te = time.perf_counter()
                st = AdaptiveState(stats, round_index, budget, committed(), rng, ref)
                record["error"] = relative_mse(method.finish(run, st), ref, eps=eps)
                record["eval_seconds"] = time.perf_counter() - te
                wall_start += record["eval_seconds"]  # evaluation is not part of the run's time
            if log_path is not None:
                # The commit above stored the times known then; now the full round
                # (statistics, observe, error) is known: a resume reports these.
                update_round_record(log_path, record)
            rounds.append(record)
            if on_round is not None:
                on_round(record)
            bar.update(committed(), round_index, record["wall_seconds"])
            round_index += 1
    finally:
        bar.close()
    rng, _ = round_seeds(seed, round_index)
    final = AdaptiveState(stats, round_index, budget, committed(), rng, ref)
    image = method.finish(run, final)
    return AdaptiveResult(image=np.asarray(image, dtype=np.float64), stats=stats, rounds=rounds,
                          stopped=stopped, log=log_path, method=method, run=run)

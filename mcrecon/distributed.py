"""Scale-out on Dask (``dask.distributed``): many frames, huge logs, huge images.

Three entry points, each identical in result to the one-process path:

:func:`denoise_many`
    Many sample logs -> one EXR each (``mcrecon batch``): one task per
    frame, run with :func:`mcrecon.reconstruct` exactly as ``mcrecon
    denoise`` runs it, so the images are bit-identical.  Outputs are
    written atomically; a rerun skips frames whose output is newer than
    their log (and was made by the same method and options); a failing
    frame is reported with its one-line error and the others complete; a
    summary (frame, method, relative MSE against the log's reference,
    seconds, worker) is written as CSV and JSON.
:func:`ingest`
    One huge log -> :class:`~mcrecon.stats.PixelStats`: workers read
    disjoint row ranges (HDF5 hyperslabs of the log on a shared file
    system) into partial statistics merged pairwise in a tree by Chan et
    al.'s formulas (:meth:`PixelStats.merge`).  Counts, minima, maxima
    and subpixel counts are exact; means and ``m2`` agree to rounding
    (bound in ``docs/distributed.md``).
:func:`reconstruct_tiled`
    A huge film -> tiles with halos: each tile is reconstructed from the
    statistics of the tile grown by the method's declared
    :meth:`~mcrecon.methods.Method.halo`, then trimmed (what
    ``dask.array.map_overlap`` with ``boundary="none"`` does, tested bit
    for bit through :func:`map_tiles`, applied to the several arrays of a
    PixelStats, whose subpixel grid has another resolution, or to the
    samples that reach a tile for splat).  Whole-image methods (``halo``
    None: awr) are refused, and so are the cases where splat is not local
    (its paper variant; rounds whose density in a tile differs from the
    film's).

Without a ``client`` each function starts a :class:`distributed.LocalCluster`
of worker processes (or, for :func:`reconstruct_tiled` and :func:`ingest`,
runs in this process); with ``scheduler=ADDRESS`` it connects to a running
scheduler.  Workers need mcrecon installed and the logs and the output
directory on a file system they share with the client.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import json
import math
import os
import socket
import sys
import time
import warnings
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from .errors import InputError, McreconWarning

__all__ = ["denoise_many", "BatchResult", "ingest", "row_ranges", "tree_merge", "reconstruct_tiled", "map_tiles",
           "tile_boxes", "local_client", "denoise_frame", "SUMMARY_NAME"]

#: Base name of the batch summary files in ``out_dir`` (``.csv`` and ``.json``).
SUMMARY_NAME = "batch_summary"
SUMMARY_FIELDS = ("frame", "log", "output", "status", "method", "rel_mse", "seconds", "worker", "samples",
                  "error")


def _dask():
    try:
        import distributed
    except ImportError:
        raise InputError("mcrecon.distributed", "dask", "dask.distributed is not installed; "
                         "pip install 'mcrecon[dask]' (or pip install 'dask[distributed]')") from None
    return distributed


# ----------------------------------------------------------------------------
# Clusters
# ----------------------------------------------------------------------------

def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


#: Dask housekeeping switched off or slowed down for the clusters :func:`local_client` starts.
#: On a machine whose cores all run frames, every CPU-second the scheduler, the nannies and the
#: workers' event loops spend is taken from a frame.  Measured on the 16-frame gem batch with 2
#: workers on 2 cores (CPU time of the client process, which hosts the scheduler and the nannies,
#: plus the workers' event-loop threads, during the batch; docs/distributed.md): 1.45-2.6 CPU-s
#: with Dask's defaults, 0.9-1.0 without the profiler, 0.5-0.6 with the tick at 1 s too, against
#: ~15 CPU-s of frames.  The statistical profiler samples the running task's stack 100 times a
#: second on the worker's event loop (and a second thread watches each event loop); the tick
#: wakes every event loop 50 times a second to check that it is not blocked (it warns after 3 s,
#: which a 1 s tick still sees).  Only Dask's dashboard profile page loses anything.  A cluster
#: the user starts (``--scheduler``) keeps its own configuration (docs/distributed.md).
_QUIET = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "1s",
}


@contextlib.contextmanager
def local_client(workers: int | None = None, *, threads: int | None = None):
    """A :class:`distributed.Client` on a fresh LocalCluster of ``workers`` processes (default: the cores).

    Each worker runs one task at a time; ``threads`` (default: cores //
    workers, at least 1) is its ``MCRECON_THREADS``, the threads of
    mcrecon's own filters, so the workers together do not oversubscribe
    the machine.  Results do not depend on it.
    """
    distributed = _dask()
    n = int(workers) if workers is not None else _cores()
    if n < 1:
        raise InputError("mcrecon.distributed", "workers", f"{workers!r}, expected a positive integer")
    t = int(threads) if threads is not None else max(1, _cores() // n)
    import logging

    import dask

    # Dask's nanny starts workers with MALLOC_TRIM_THRESHOLD_=65536 (to hand freed memory back
    # to the OS).  Setting it also switches off glibc's adaptive mmap threshold, so every
    # image-sized temporary becomes a fresh mmap whose pages fault in on first touch: a 512^2,
    # 32-spp gem frame took 1.00-1.03 s instead of 0.79-0.88 s in the same process
    # (docs/distributed.md, "Measured scaling").  Our workers allocate as `mcrecon denoise`
    # does; an explicit MALLOC_TRIM_THRESHOLD_ in the environment is still inherited.
    with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None, **_QUIET}):
        cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                           dashboard_address=":0", silence_logs=logging.CRITICAL,
                                           env={"MCRECON_THREADS": str(t), "OMP_NUM_THREADS": "1"})
    try:
        # gathers and scatters go straight to the workers (on this machine, reachable): a result
        # crosses one TCP connection instead of two, through the scheduler, and big pickled
        # objects keep pickle protocol 5 (out-of-band arrays) instead of the scheduler's 4
        client = distributed.Client(cluster, direct_to_workers=True)
        try:
            yield client
        finally:
            client.close()
    finally:
        cluster.close()


def _local_workers(workers: int | None, frames: int) -> int:
    """Workers of a local cluster for ``frames`` frames: never more than the frames or the cores
    (each extra worker is an idle process of a few hundred MB; a million of them never start)."""
    cores = _cores()
    if workers is not None and (isinstance(workers, bool) or int(workers) != workers or workers < 1):
        raise InputError("batch", "workers", f"{workers!r}, expected a positive integer")
    n = min(cores if workers is None else int(workers), max(frames, 1), cores)
    if workers is not None and n < workers:
        warnings.warn(f"batch: {workers} workers capped at {n} ({frames} frame(s) to reconstruct, "
                      f"{cores} core(s))", McreconWarning, stacklevel=3)
    return n


@contextlib.contextmanager
def _client_for(client=None, scheduler: str | None = None, workers: int | None = None):
    if client is not None:
        yield client
    elif scheduler is not None:
        distributed = _dask()
        try:
            c = distributed.Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as exc:
            raise InputError(str(scheduler), "scheduler", f"cannot connect: {exc}") from None
        try:
            yield c
        finally:
            c.close()
    else:
        with local_client(workers) as c:
            yield c


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):
        return f"{socket.gethostname()}:{os.getpid()}"


def _one_line(exc: BaseException) -> str:
    text = str(exc) if isinstance(exc, InputError) else f"{type(exc).__name__}: {exc}"
    if isinstance(exc, OSError) and exc.filename:
        text = f"{exc.filename}: {exc.strerror or exc}"
    return " ".join(text.split())


# ----------------------------------------------------------------------------
# 1. Many logs -> many images
# ----------------------------------------------------------------------------

def denoise_frame(log_path, out_path, method: str, options: dict, *, nonfinite: str = "drop",
                  png: bool = False, exposure: float = 0.0) -> dict:
    """Reconstruct one frame exactly as ``mcrecon denoise`` does and write its EXR atomically.

    Runs on a worker; never raises: a failure comes back as
    ``status='failed'`` with the one-line error.
    """
    from .io import read_log, write_exr, write_png_preview
    from .metrics import relative_mse
    from .reconstruction import reconstruct

    log_path, out_path = Path(log_path), Path(out_path)
    rec = {"frame": log_path.stem, "log": str(log_path), "output": str(out_path), "method": method,
           "rel_mse": None, "seconds": None, "worker": _worker_name(), "samples": None, "error": None}
    t0 = time.perf_counter()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", McreconWarning)
            log = read_log(log_path)
            r = reconstruct(log, method=method, nonfinite=nonfinite, full=True, **options)
            if png:  # the preview first: the EXR (atomic) marks a complete frame
                write_png_preview(out_path.with_suffix(".png"), r.image, exposure=exposure)
            write_exr(out_path, r.image, channels=log.channels)
            ref = log.reference()
            if ref is not None:
                rec["rel_mse"] = relative_mse(r.image, ref)
            rec["samples"] = int(log.n_samples)
        rec["warnings"] = [" ".join(str(w.message).split()) for w in caught
                           if issubclass(w.category, McreconWarning)]
        rec["status"] = "done"
    except Exception as exc:  # noqa: BLE001 -- a bad frame must not stop the batch
        rec["status"] = "failed"
        rec["error"] = _one_line(exc)
    rec["seconds"] = time.perf_counter() - t0
    return rec


@dataclasses.dataclass
class BatchResult:
    """What :func:`denoise_many` did: one record per frame (in input order) and the summary files."""

    records: list
    summary_csv: Path | None
    summary_json: Path | None
    seconds: float

    @property
    def failed(self) -> list:
        return [r for r in self.records if r["status"] == "failed"]

    @property
    def ok(self) -> bool:
        return not self.failed


def _expand(paths) -> list[Path]:
    import glob

    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    out = []
    for p in paths:
        s = str(p)
        # a name that exists is that file, even if it holds glob characters ('shot[1].h5'):
        # globbing it could pick a neighbour ('shot1.h5') or nothing
        if any(ch in s for ch in "*?[") and not os.path.isfile(s):
            hits = sorted(glob.glob(s))
            if not hits:
                raise InputError(s, "logs", "the pattern matches no file")
            out.extend(Path(h) for h in hits)
        else:
            out.append(Path(s))
    if not out:
        raise InputError("batch", "logs", "no sample log given")
    return out


def _config(method, options: dict, nonfinite: str) -> dict:
    from .methods import Method, get_method

    if isinstance(method, Method):
        if options:
            raise InputError("batch", sorted(options)[0], "a method object already carries its options")
        m = method
    else:
        m = get_method(str(method), **options)   # validate once, here, before any work
    return {"method": m.name, "options": dict(m.params), "nonfinite": nonfinite}


def _previous(json_path: Path) -> dict:
    try:
        data = json.loads(json_path.read_text())
        return {r["frame"]: r for r in data.get("frames", []) if r.get("status") in ("done", "skipped")}
    except (OSError, ValueError, AttributeError, TypeError, KeyError):
        return {}


def _damaged_output(log: Path, out: Path) -> str | None:
    """Why an existing output EXR is not this log's image (None when its header fits the log).

    The EXR is published atomically, but a file can still be truncated or
    replaced afterwards (a full disk, a copy that stopped): its header is read
    (cheap, no pixels) and its size and channel count checked against the log's.
    """
    import OpenEXR

    from .io import read_log

    try:
        h = OpenEXR.File(str(out), header_only=True).header()
        (x0, y0), (x1, y1) = (tuple(int(v) for v in c) for c in h["dataWindow"])
        n_channels = len(h["channels"])
    except Exception as exc:  # noqa: BLE001 -- any failure to read the header is damage
        return f"not a readable EXR ({' '.join(str(exc).split()) or type(exc).__name__})"
    try:
        log = read_log(log)
    except InputError:
        return None   # the frame fails on its own, with the log's error
    got, want = (x1 - x0 + 1, y1 - y0 + 1, n_channels), (log.width, log.height, len(log.channels))
    if got != want:
        return f"{got[0]}x{got[1]} with {got[2]} channel(s), the log is {want[0]}x{want[1]} with {want[2]}"
    return None


def _up_to_date(log: Path, out: Path, prev: dict | None, config: dict) -> bool:
    try:
        if not out.is_file():
            return False
        if out.stat().st_mtime_ns < log.stat().st_mtime_ns:
            return False
    except OSError:
        return False
    # it must have been made by this method configuration (when a summary says so)
    if prev is not None and prev.get("config") not in (None, config):
        return False
    damage = _damaged_output(log, out)
    if damage is not None:
        warnings.warn(f"{out}: existing output is damaged ({damage}): reconstructing it again",
                      McreconWarning, stacklevel=3)
        return False
    return True


class _Progress:
    """A one-line progress bar on a terminal (stderr); silent otherwise."""

    def __init__(self, total: int, enabled: bool | None):
        self.total, self.done, self.failed = total, 0, 0
        self.on = sys.stderr.isatty() if enabled is None else bool(enabled)

    def step(self, failed: bool) -> None:
        self.done += 1
        self.failed += bool(failed)
        if self.on:
            width = 30
            fill = int(width * self.done / max(self.total, 1))
            sys.stderr.write(f"\r[{'#' * fill}{'.' * (width - fill)}] {self.done}/{self.total} frames"
                             + (f", {self.failed} failed" if self.failed else ""))
            sys.stderr.flush()

    def close(self) -> None:
        if self.on and self.total:
            sys.stderr.write("\n")


def _write_summary(out_dir: Path, records: list, config: dict, seconds: float) -> tuple[Path, Path]:
    from .io._atomic import atomic_path

    csv_path, json_path = out_dir / f"{SUMMARY_NAME}.csv", out_dir / f"{SUMMARY_NAME}.json"
    with atomic_path(csv_path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=SUMMARY_FIELDS, extrasaction="ignore")
        w.writeheader()
        for r in records:
            w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in SUMMARY_FIELDS})
    doc = {"config": config, "seconds": seconds,
           "frames": [{**{k: r.get(k) for k in SUMMARY_FIELDS}, "warnings": r.get("warnings", []),
                       "config": r.get("config")} for r in records]}
    with atomic_path(json_path) as tmp, open(tmp, "w") as f:
        json.dump(doc, f, indent=1)
    return csv_path, json_path


def denoise_many(paths, *, method="box", out_dir, client=None, scheduler: str | None = None,
                 workers: int | None = None, nonfinite: str = "drop", force: bool = False, png: bool = False,
                 exposure: float = 0.0, progress: bool | None = None, summary: bool = True,
                 **options) -> BatchResult:
    """Reconstruct every sample log in ``paths`` into ``out_dir/<log stem>.exr`` on a Dask cluster.

    Parameters
    ----------
    paths : path, glob pattern or sequence of them
        Sample logs (patterns like ``'frames/*.h5'`` are expanded here).
    method : str or Method
        A registered method with its ``options`` as keywords (validated
        here, before any work), or a method object.
    out_dir : path
        Output directory (created), shared with the workers.
    client : distributed.Client, optional
        An existing client; else ``scheduler`` (an address to connect to);
        else a LocalCluster of ``workers`` processes (default: the cores)
        is started and closed.
    nonfinite : {'drop', 'zero', 'raise'}
    force : bool
        Reconstruct frames whose output is already up to date too.
    png : bool
        Also write each frame's PNG preview (with ``exposure`` stops).
    progress : bool, optional
        A progress bar on stderr (default: when stderr is a terminal).
    summary : bool
        Write ``out_dir/batch_summary.csv`` and ``.json``.

    Returns
    -------
    BatchResult
        ``records`` in input order: ``status`` is ``done``, ``skipped``
        (up to date) or ``failed`` (with ``error``, one line).
    """
    from .samples import check_policy

    check_policy(nonfinite, "batch")
    logs = _expand(paths)
    stems = {}
    for p in logs:
        if p.stem in stems and stems[p.stem] != p:
            raise InputError(str(p), "frame", f"same name as {stems[p.stem]}: both would write {p.stem}.exr")
        stems[p.stem] = p
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    config = _config(method, options, nonfinite)
    prev = _previous(out_dir / f"{SUMMARY_NAME}.json")
    t0 = time.perf_counter()
    records: dict[int, dict] = {}
    todo = []
    for i, p in enumerate(logs):
        out = out_dir / f"{p.stem}.exr"
        if not force and _up_to_date(p, out, prev.get(p.stem), config):
            old = prev.get(p.stem) or {}
            records[i] = {**{k: old.get(k) for k in SUMMARY_FIELDS}, "frame": p.stem, "log": str(p),
                          "output": str(out), "status": "skipped", "method": config["method"], "error": None,
                          "config": config}
        else:
            todo.append((i, p, out))
    bar = _Progress(len(todo), progress)
    if todo:
        distributed = _dask()
        if client is None and scheduler is None:
            workers = _local_workers(workers, len(todo))
        with _client_for(client, scheduler, workers) as c:
            futures = {}
            for i, p, out in todo:
                f = c.submit(denoise_frame, str(p), str(out), config["method"], config["options"],
                             nonfinite=nonfinite, png=png, exposure=exposure, pure=False,
                             key=f"mcrecon-frame-{i}-{p.stem}-{os.urandom(4).hex()}")
                futures[f] = i
            for f in distributed.as_completed(futures):
                i = futures[f]
                try:
                    rec = f.result()
                except Exception as exc:  # noqa: BLE001 -- a lost worker, a pickling error
                    _, p, out = todo[[t[0] for t in todo].index(i)]
                    rec = {"frame": p.stem, "log": str(p), "output": str(out), "method": config["method"],
                           "status": "failed", "error": _one_line(exc)}
                rec["config"] = config
                records[i] = rec
                bar.step(rec["status"] == "failed")
    bar.close()
    ordered = [records[i] for i in range(len(logs))]
    seconds = time.perf_counter() - t0
    csv_path = json_path = None
    if summary:
        csv_path, json_path = _write_summary(out_dir, ordered, config, seconds)
    return BatchResult(ordered, csv_path, json_path, seconds)


# ----------------------------------------------------------------------------
# 2. Huge logs -> pixel statistics
# ----------------------------------------------------------------------------

def row_ranges(n: int, parts: int, *, align: int = 1) -> list[tuple[int, int]]:
    """``parts`` disjoint ``(start, stop)`` ranges covering ``[0, n)``, boundaries on multiples of ``align``."""
    n, parts, align = int(n), max(1, int(parts)), max(1, int(align))
    blocks = -(-n // align)
    parts = max(1, min(parts, blocks))
    edges = [min(n, (blocks * k // parts) * align) for k in range(parts + 1)]
    return [(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a] or [(0, 0)]


def _ingest_range(path: str, start: int, stop: int, subpixels: int, nonfinite: str, chunk_size: int):
    """Partial statistics of rows [start, stop) of a log, as a :class:`_Band` (runs on a worker).

    Streams the rows through two rotating buffers of ``chunk_size`` rows
    (as :meth:`PixelStats.from_log` does: no array per chunk), so the
    worker holds the image's statistics plus two chunks.
    """
    from .io import read_log
    from .stats import PixelStats

    log = read_log(path)
    stop = min(int(stop), log.n_samples)
    rows = max(1, min(int(chunk_size), stop - int(start)))
    bufs = [(np.empty((rows, 2), log.position_dtype), np.empty((rows, len(log.channels)), log.value_dtype))
            for _ in range(2)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", McreconWarning)  # counted in n_dropped / n_zeroed, warned once
        stats = PixelStats.from_batches(log.iter_into(bufs, start=int(start), stop=stop), width=log.width,
                                        height=log.height, channels=log.channels, subpixels=subpixels,
                                        nonfinite=nonfinite, source=str(log.path))
    return _Band.of(stats)


@dataclasses.dataclass
class _Band:
    """Statistics of image rows [y0, y0 + stats.height): the rows a partial touched.

    A part of a log written pixel by pixel touches a band of image rows;
    shipping and merging only that band moves a fraction of the image
    between processes.  Rows outside the band are empty (count 0), and
    merging an empty pixel is the identity bit for bit (``wb`` is 0 or 1,
    the other terms vanish exactly), so merging bands gives exactly what
    merging the full-image partials gives.
    """

    y0: int
    stats: object            # PixelStats of the band's rows
    height: int              # of the whole image

    @classmethod
    def of(cls, stats) -> "_Band":
        rows = np.flatnonzero(stats.count.any(axis=1))
        y0, y1 = (int(rows[0]), int(rows[-1]) + 1) if rows.size else (0, min(1, stats.height))
        if (y0, y1) == (0, stats.height):
            return cls(0, stats, stats.height)
        return cls(y0, _crop_stats(stats, y0, y1, 0, stats.width), stats.height)

    @property
    def y1(self) -> int:
        return self.y0 + self.stats.height

    def pack(self) -> tuple:
        """The band as a tuple of its arrays (first) and its small fields (last), to cross the network.

        Dask ships numpy arrays as raw frames, without a copy; any other
        object is pickled, and through the scheduler (how a client
        gathers by default) with pickle protocol 4, which copies every
        array into the pickle, scans it, and copies it again on arrival.
        Measured on this machine for the 104 MiB statistics of a 1024^2
        film: 0.47-0.54 s as a PixelStats, 0.11-0.13 s as its arrays.
        """
        d = self.stats.__dict__
        names = tuple(k for k, v in d.items() if isinstance(v, np.ndarray))
        small = {k: v for k, v in d.items() if k not in names}
        return (*(d[k] for k in names), (names, small, self.y0, self.height))

    @classmethod
    def unpack(cls, packed: tuple) -> "_Band":
        from .stats import PixelStats

        *arrays, (names, small, y0, height) = packed
        stats = PixelStats.__new__(PixelStats)
        stats.__dict__.update(small)
        stats.__dict__.update(zip(names, arrays))
        return cls(y0, stats, height)

    def full(self):
        """The statistics of the whole image (empty outside the band)."""
        if (self.y0, self.y1) == (0, self.height):
            return self.stats
        out = _empty_like(self.stats, self.height)
        _copy_rows(out, self.y0, self.stats)
        _carry_counters(out, self.stats)
        return out


def _empty_like(stats, height: int):
    from .stats import PixelStats

    out = PixelStats(stats.width, height, stats.channels, subpixels=stats.subpixels)
    out.has_range = stats.has_range
    return out


def _rows_view(stats, y0: int, y1: int):
    """A PixelStats whose arrays are views of rows [y0, y1) of ``stats``: merging into it writes ``stats``."""
    from .stats import PixelStats

    out = PixelStats.__new__(PixelStats)
    d = dict(stats.__dict__)
    for name in ("count", "mean", "m2", "min", "max"):
        d[name] = getattr(stats, name)[y0:y1]
    if stats.subpixels:
        s = stats.subpixels
        d["sub_sum"], d["sub_count"] = stats.sub_sum[y0 * s:y1 * s], stats.sub_count[y0 * s:y1 * s]
    d["height"] = y1 - y0
    d["n_dropped"] = d["n_zeroed"] = 0
    out.__dict__.update(d)
    return out


def _carry_counters(into, other) -> None:
    """What :meth:`PixelStats.merge` does besides the arrays (for merges done through row views)."""
    into.n_dropped += other.n_dropped
    into.n_zeroed += other.n_zeroed
    into.has_range = into.has_range and other.has_range
    if other._value_dtype is not None:
        into._note_dtype(other._value_dtype)


def _copy_rows(out, y0: int, stats) -> None:
    """Write ``stats`` into the empty rows [y0, y0 + stats.height) of ``out``.

    Equal to merging into them: with na = 0 the merge's weight is exactly
    1 and its other terms vanish, so it stores the band's own numbers.
    """
    y1 = y0 + stats.height
    for name in ("count", "mean", "m2", "min", "max"):
        getattr(out, name)[y0:y1] = getattr(stats, name)
    if out.subpixels:
        s = out.subpixels
        out.sub_sum[y0 * s:y1 * s] = stats.sub_sum
        out.sub_count[y0 * s:y1 * s] = stats.sub_count


def _merge_bands(a: _Band, b: _Band) -> _Band:
    """``a`` merged with ``b`` (a first, as :meth:`PixelStats.merge`), over the union of their rows.

    Rows only one band holds are copied (merging into empty rows is a
    copy, see :func:`_copy_rows`); only rows both hold are merged.
    """
    y0, y1 = min(a.y0, b.y0), max(a.y1, b.y1)
    if (y0, y1) == (a.y0, a.y1):
        out = a.stats                                   # b's rows lie inside a's band: merge in place
    else:
        out = _empty_like(a.stats, y1 - y0)
        _copy_rows(out, a.y0 - y0, a.stats)
        _carry_counters(out, a.stats)
    lo, hi = max(a.y0, b.y0), min(a.y1, b.y1)          # rows both bands hold
    if hi > lo:
        _rows_view(out, lo - y0, hi - y0).merge(_rows_view(b.stats, lo - b.y0, hi - b.y0))
    for r0, r1 in ((b.y0, min(b.y1, a.y0)), (max(b.y0, a.y1), b.y1)):   # b's rows outside a's band
        if r1 > r0:
            _copy_rows(out, r0 - y0, _rows_view(b.stats, r0 - b.y0, r1 - b.y0))
    _carry_counters(out, b.stats)
    return _Band(y0, out, a.height)


def _ingest_part(path: str, start: int, stop: int, subpixels: int, nonfinite: str, chunk_size: int) -> tuple:
    """:func:`_ingest_range` as a task: its band packed to cross the network (:meth:`_Band.pack`)."""
    return _ingest_range(path, start, stop, subpixels, nonfinite, chunk_size).pack()


def _merge_packed(a: tuple, b: tuple) -> tuple:
    """:func:`_merge_bands` as a task, on packed bands."""
    return _merge_bands(_Band.unpack(a), _Band.unpack(b)).pack()


def _merge_two(a, b):
    return a.merge(b)


def tree_merge(items: Sequence, merge=_merge_two, submit=None, *, until: int = 1):
    """Merge ``items`` pairwise, level by level (a balanced tree of depth ceil(log2 n)).

    ``submit(func, a, b)`` runs a merge (``client.submit``: the tree runs
    on the workers, futures in, futures out); default: in this process.
    With ``until`` > 1 it stops at that many items and returns them (the
    caller merges the last levels itself); else it returns the one result.
    """
    level = list(items)
    if not level:
        raise InputError("tree_merge", "items", "nothing to merge")
    while len(level) > max(1, int(until)):
        nxt = []
        for k in range(0, len(level) - 1, 2):
            nxt.append(submit(merge, level[k], level[k + 1]) if submit else merge(level[k], level[k + 1]))
        if len(level) % 2:
            nxt.append(level[-1])
        level = nxt
    return level[0] if until <= 1 else level


def ingest(log, *, client=None, scheduler: str | None = None, workers: int | None = None,
           parts: int | None = None, subpixels: int = 0, nonfinite: str = "drop",
           chunk_size: int | None = None):
    """Pixel statistics of one sample log, read by the workers in disjoint row ranges.

    Parameters
    ----------
    log : path or SampleLog
        On a file system the workers share.
    client, scheduler, workers : see :func:`denoise_many`
    parts : int, optional
        Row ranges (default: one per worker).  Each worker holds the
        image-sized partial statistics of its range plus two chunks; only
        the band of image rows a range touched is shipped and merged.
    subpixels, nonfinite : see :meth:`PixelStats.from_log`
    chunk_size : int, optional
        Rows per read (default the log reader's); range boundaries fall
        on multiples of it, so each range reads the chunks a one-process
        :meth:`~PixelStats.from_log` reads.

    Returns
    -------
    PixelStats
        Counts, min/max and subpixel counts exactly the one-process ones;
        mean and m2 equal to rounding (the merge order differs).
    """
    from .io import read_log
    from .io.samplelog import DEFAULT_READ_ROWS, SampleLog
    from .samples import check_policy, warn_nonfinite

    check_policy(nonfinite, "ingest")
    if not isinstance(log, SampleLog):
        log = read_log(log)
    path = str(Path(log.path).resolve())
    rows = int(chunk_size or DEFAULT_READ_ROWS)
    with _client_for(client, scheduler, workers) as c:
        nw = max(1, len(c.nthreads()))
        ranges = row_ranges(log.n_samples, parts or nw, align=rows)
        futs = [c.submit(_ingest_part, path, a, b, int(subpixels), nonfinite, rows, pure=False)
                for a, b in ranges]
        # the tree runs on the workers down to two bands; their merge happens here, where the
        # result has to come anyway: each band crosses the network once, in parallel, as arrays
        top = c.gather(tree_merge(futs, merge=_merge_packed, until=2,
                                  submit=lambda f, a, b: c.submit(f, a, b, pure=False)))
        stats = tree_merge([_Band.unpack(t) for t in top], merge=_merge_bands).full()
    n_bad = stats.n_dropped + stats.n_zeroed
    if n_bad:
        warn_nonfinite(str(log.path), n_bad, nonfinite, stacklevel=2)
    return stats


# ----------------------------------------------------------------------------
# 3. Huge images -> tiles with halos
# ----------------------------------------------------------------------------

def _crop_stats(stats, y0: int, y1: int, x0: int, x1: int):
    """The statistics of the pixels [y0:y1, x0:x1] (copies)."""
    from .stats import PixelStats

    out = PixelStats.__new__(PixelStats)
    d = dict(stats.__dict__)
    s = stats.subpixels
    for name in ("count", "mean", "m2", "min", "max"):
        d[name] = np.ascontiguousarray(getattr(stats, name)[y0:y1, x0:x1])
    if s:
        d["sub_sum"] = np.ascontiguousarray(stats.sub_sum[y0 * s:y1 * s, x0 * s:x1 * s])
        d["sub_count"] = np.ascontiguousarray(stats.sub_count[y0 * s:y1 * s, x0 * s:x1 * s])
    d["width"], d["height"] = x1 - x0, y1 - y0
    out.__dict__.update(d)
    return out


def _reconstruct_tile(method, stats, reference, inner):
    """Reconstruct one grown tile and trim it to its inner part (runs on a worker)."""
    from .methods.base import MethodInputs

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", McreconWarning)
        img = method.reconstruct(MethodInputs(stats, None, reference))
    (a, b), (c, d) = inner
    return np.asarray(img[a:b, c:d], dtype=np.float64)


def tile_boxes(width: int, height: int, tile: int, halo: int):
    """``(outer, tile, inner)`` boxes of each tile, each box ((y0, y1), (x0, x1)).

    outer = the tile grown by ``halo`` on every side and clipped to the
    film (``dask.array.map_overlap`` with ``boundary="none"``); tile = the
    tile in film coordinates; inner = the tile inside the outer box.
    """
    for ty in range(0, height, tile):
        for tx in range(0, width, tile):
            y0, y1, x0, x1 = ty, min(height, ty + tile), tx, min(width, tx + tile)
            oy0, oy1, ox0, ox1 = max(0, y0 - halo), min(height, y1 + halo), max(0, x0 - halo), min(width, x1 + halo)
            yield ((oy0, oy1), (ox0, ox1)), ((y0, y1), (x0, x1)), ((y0 - oy0, y1 - oy0), (x0 - ox0, x1 - ox0))


def _run_tiles(func, tasks, shape, client=None) -> np.ndarray:
    """Assemble ``out[tile] = func(*args)`` for each ``(tile, args)`` of ``tasks``.

    Without a client the tiles run here one after another; with one, as
    Dask futures (arguments that are futures stay on the workers), placed
    into the output as they complete.
    """
    out = np.empty(shape, np.float64)
    if client is None:
        for (iy, ix), args in tasks:
            out[iy[0]:iy[1], ix[0]:ix[1]] = func(*args)
        return out
    distributed = _dask()
    futs = {client.submit(func, *args, pure=False): box for box, args in tasks}
    for f in distributed.as_completed(futs):
        iy, ix = futs[f]
        out[iy[0]:iy[1], ix[0]:ix[1]] = f.result()
        f.release()
    return out


def _trim_apply(func, block, inner):
    (a, b), (c, d) = inner
    return np.asarray(func(block))[a:b, c:d]


def map_tiles(func, image, *, tile: int, halo: int, client=None) -> np.ndarray:
    """``func`` applied to tiles of ``image`` grown by ``halo`` (clipped at the edges), each trimmed back.

    The tiling of :func:`reconstruct_tiled`, on a plain array: for a
    ``func`` whose result at a pixel depends on pixels at most ``halo``
    away it equals ``func(image)``, and it equals
    ``dask.array.map_overlap(func, image, depth=halo, boundary="none")``
    (``tests/test_distributed.py`` checks both bit for bit).  The output
    is float64 with the image's first two dimensions.
    """
    image = np.asarray(image)
    h, w = image.shape[:2]
    tasks = [(box, (func, np.ascontiguousarray(image[oy[0]:oy[1], ox[0]:ox[1]]), inner))
             for (oy, ox), box, inner in tile_boxes(w, h, int(tile), int(halo))]
    probe = np.asarray(func(image[:1, :1]))
    return _run_tiles(_trim_apply, tasks, (h, w) + probe.shape[2:], client)


# ---------------------------------------------------------------- sample tiles (splat)
class _TileSamples:
    """The samples of one grown tile, shifted to its origin, as a sample source for a method.

    Chunks are kept as the method reads the film's source (the same
    chunk boundaries, each chunk reduced to the tile's samples), so the
    method accumulates every pixel's contributions in the same order as
    on the whole film.
    """

    def __init__(self, width, height, channels, name, rounds):
        self.width, self.height, self.channels, self.name = width, height, tuple(channels), name
        self._rounds = rounds        # [(round index or None, [(positions, values), ...]), ...]
        ends = np.cumsum([sum(p.shape[0] for p, _ in chunks) for _, chunks in rounds])
        self._slices = list(zip([0, *ends[:-1].tolist()], ends.tolist()))

    @property
    def n_samples(self) -> int:
        return int(self._slices[-1][1]) if self._slices else 0

    def round_slices(self):
        return self._slices

    def iter_chunks(self, *, rounds=None, with_round: bool = False, chunk_size=None):
        from .samples import SampleChunk

        groups = range(len(self._rounds)) if rounds is None else [int(r) for r in rounds]
        for g in groups:
            for pos, val in self._rounds[g][1]:
                yield SampleChunk(pos, val, None, 0)


def _film_rounds(source) -> list:
    """How a sample-filtering method groups the source's chunks: per round (two or more), else all at once."""
    nonempty = [r for r, (a, b) in enumerate(source.round_slices()) if b > a]
    return [[r] for r in nonempty] if len(nonempty) >= 2 else [None]


def _tile_samples(source, outer, where: str):
    """The samples of ``source`` in the pixels of ``outer``, shifted by its origin; and the per-round counts.

    Returns (_TileSamples, film counts per round, tile counts per round).
    Positions are checked as the method checks them (an off-film or
    non-finite position is the same one-line error).  Shifting a float
    x >= x0 by an integer x0 is exact (x0 is a multiple of x's spacing),
    so the method computes the same offsets to every pixel centre.
    """
    from .samples import check_samples

    (oy0, oy1), (ox0, ox1) = outer
    groups, film_n, tile_n = [], [], []
    for g in _film_rounds(source):
        chunks, nf, nt = [], 0, 0
        for ch in source.iter_chunks(rounds=g, with_round=False):
            pos, val, _ = check_samples(ch.positions, ch.values, width=source.width, height=source.height,
                                        n_channels=len(source.channels), where=where)
            nf += pos.shape[0]
            ix, iy = np.floor(pos[:, 0]), np.floor(pos[:, 1])
            keep = (ix >= ox0) & (ix < ox1) & (iy >= oy0) & (iy < oy1)
            if keep.any():
                p = pos[keep]
                p[:, 0] -= ox0
                p[:, 1] -= oy0
                chunks.append((p, val[keep]))
                nt += p.shape[0]
        groups.append((None if g is None else g[0], chunks))
        film_n.append(nf)
        tile_n.append(nt)
    sub = _TileSamples(ox1 - ox0, oy1 - oy0, source.channels, source_name_of(source), groups)
    return sub, film_n, tile_n


def source_name_of(source) -> str:
    from .samples import source_name

    return source_name(source)


def _splat_tile(method, source, outer, inner, film_pixels: int, nonfinite: str, reference=None):
    """Reconstruct one grown tile of a sample-filtering method from the samples that reach it (on a worker).

    ``source`` is a log path (the worker streams the whole log and keeps
    the tile's samples: memory is the grown tile's samples) or a
    :class:`_TileSamples` already cut on the client.
    """
    from .methods.base import MethodInputs

    where = f"{method.where} (tiled)"
    if isinstance(source, _TileSamples):
        sub, film_n, tile_n = source, None, None
    else:
        from .io import read_log

        sub, film_n, tile_n = _tile_samples(read_log(source), outer, where)
    if film_n is not None:
        _check_round_densities(where, film_n, tile_n, film_pixels, sub.width * sub.height)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", McreconWarning)
        img = method.reconstruct(MethodInputs(None, sub, reference, nonfinite=nonfinite))
    (a, b), (c, d) = inner
    return np.asarray(img[a:b, c:d], dtype=np.float64)


def _check_round_densities(where, film_n, tile_n, film_pixels, tile_pixels):
    """Refuse a tile whose rounds are not as dense as the film's.

    Splatting weighs round j by its mean samples per pixel over the
    *film*, N_j = n_j / pixels (Suykens and Willems' scale-down); a tile
    reproduces it exactly only if its own rounds have the same densities
    (equal fractions give the same correctly rounded quotient), as rounds
    that sample every pixel alike do.  One round is weighed 1 whatever
    its density.
    """
    if len(film_n) < 2:
        return
    for r, (nf, nt) in enumerate(zip(film_n, tile_n)):
        if nt * film_pixels != nf * tile_pixels:
            raise InputError(where, "rounds", f"round {r} has {nt / tile_pixels:.6g} samples per pixel in a tile "
                             f"but {nf / film_pixels:.6g} over the film: splatting weighs rounds by their "
                             "film-wide density, so tiles of an adaptively sampled log are not local; "
                             "reconstruct it untiled (mcrecon.reconstruct)")


def reconstruct_tiled(source, *, method="box", tile: int = 1024, client=None, reference=None,
                      nonfinite: str = "drop", **options) -> np.ndarray:
    """Reconstruct in tiles with halos: the untiled image of a local method, tile by tile.

    Parameters
    ----------
    source : PixelStats, a sample log (path or SampleLog) or a SampleSet
        Methods of pixel statistics take statistics (a log is ingested
        with :func:`ingest` when a ``client`` is given, else
        :meth:`PixelStats.from_log`).  Sample-filtering methods (splat)
        take a log or a SampleSet: each tile gets the samples whose pixel
        lies in the tile grown by the halo.
    method : str or Method
        A method declaring a finite :meth:`~mcrecon.methods.Method.halo`;
        whole-image methods (awr) are refused.
    tile : int
        Tile side in pixels (the halo comes on top of it).
    client : distributed.Client, optional
        Tiles run as tasks on it; without one, in this process one after
        the other (memory: one grown tile at a time besides the input).
        For a log and a sample-filtering method each task streams the log
        itself (the log must be on a file system the workers share).
    reference : ndarray (H, W, C), optional
        For oracle modes (cropped with each tile).

    Raises
    ------
    InputError
        A whole-image method; statistics with a pixel of fewer than two
        samples (the fill-in policies for such pixels can borrow from
        anywhere in the image, so no finite halo makes the result local);
        for splat, the paper variant (``spread='all'``: its pseudo-rounds
        and scatter depend on the whole film) or rounds whose density in a
        tile differs from the film's (adaptive logs).
    """
    from .methods import Method, get_method
    from .stats import PixelStats

    m = method if isinstance(method, Method) else get_method(str(method), **options)
    if isinstance(method, Method) and options:
        raise InputError("reconstruct_tiled", sorted(options)[0], "a method object already carries its options")
    where = f"{m.where} (tiled)"
    tile = int(tile)
    if tile < 1:
        raise InputError(where, "tile", f"{tile}, expected a positive number of pixels")
    if m.requires.samples:
        return _reconstruct_tiled_samples(m, source, tile, client, reference, nonfinite, where)
    if not m.requires.statistics:
        raise InputError(where, "method", f"{m.name} reads neither pixel statistics nor samples")
    if isinstance(source, PixelStats):
        stats = source
    else:
        stats = ingest(source, client=client, subpixels=m.requires.subpixels, nonfinite=nonfinite) \
            if client is not None else PixelStats.from_log(source, subpixels=m.requires.subpixels,
                                                           nonfinite=nonfinite)
    h, w, c = stats.shape
    halo = _halo_or_refuse(m, w, h, where)
    few = int((stats.count < 2).sum())
    if few:
        raise InputError(where, "statistics", f"{few} pixel(s) with fewer than 2 samples: their fill-in may "
                         "borrow from the whole image, so tiles would not reproduce the untiled result; "
                         "reconstruct untiled, or give every pixel at least 2 samples")
    if m.requires.subpixels and stats.subpixels != m.requires.subpixels:
        raise InputError(where, "statistics", f"need a {m.requires.subpixels}x{m.requires.subpixels} subpixel "
                         f"grid, got subpixels={stats.subpixels}")
    ref = None if reference is None else np.asarray(reference, dtype=np.float64)
    mf = m if client is None else client.scatter(m, broadcast=True)
    tasks = []
    for (oy, ox), box, inner in tile_boxes(w, h, tile, halo):
        sub = _crop_stats(stats, oy[0], oy[1], ox[0], ox[1])
        r = None if ref is None else ref[oy[0]:oy[1], ox[0]:ox[1]]
        if client is not None:   # each grown tile goes to one worker, the film stays here
            sub = client.scatter(sub)
            r = None if r is None else client.scatter(r)
        tasks.append((box, (mf, sub, r, inner)))
    return _run_tiles(_reconstruct_tile, tasks, (h, w, c), client)


def _halo_or_refuse(m, w, h, where) -> int:
    halo = m.halo(w, h)
    if halo is None:
        raise InputError(where, "halo", f"{m.name} is a whole-image method (its result at a pixel depends on the "
                         "whole film); it cannot be tiled: reconstruct it untiled on one worker with the memory "
                         "for the film (mcrecon.reconstruct)")
    return int(halo)


def _reconstruct_tiled_samples(m, source, tile, client, reference, nonfinite, where):
    from .io import read_log
    from .io.samplelog import SampleLog
    from .samples import SampleSet, check_policy
    from .stats import PixelStats

    check_policy(nonfinite, where)
    if m.name == "splat" and m.params.get("spread") == "all":
        raise InputError(where, "spread", "splat's paper variant (spread='all') is not local: it splits a "
                         "single-round source into pseudo-rounds scheduled by the film's smallest pixel count, "
                         "and sums large batches in two blocks whose split moves with the batch; tile the robust "
                         "variant (the default), or reconstruct untiled")
    if isinstance(source, PixelStats):
        raise InputError(where, "source", f"{m.name} filters individual samples: give it a sample log or a "
                         "SampleSet, not pixel statistics")
    if isinstance(source, (str, os.PathLike)):
        source = read_log(source)
    if not isinstance(source, (SampleLog, SampleSet)):
        raise InputError(where, "source", f"got {type(source).__name__}, expected a sample log or a SampleSet")
    w, h, c = source.width, source.height, len(source.channels)
    halo = _halo_or_refuse(m, w, h, where)
    ref = None if reference is None else np.asarray(reference, dtype=np.float64)
    mf = m if client is None else client.scatter(m, broadcast=True)
    tasks = []
    for outer, box, inner in tile_boxes(w, h, tile, halo):
        (oy, ox) = outer
        r = None if ref is None else ref[oy[0]:oy[1], ox[0]:ox[1]]
        if isinstance(source, SampleLog):
            src = str(Path(source.path).resolve())       # the task streams the log itself
        else:
            src, film_n, tile_n = _tile_samples(source, outer, where)
            _check_round_densities(where, film_n, tile_n, w * h, src.width * src.height)
            if client is not None:
                src = client.scatter(src)
        if client is not None and r is not None:
            r = client.scatter(r)
        tasks.append((box, (mf, src, outer, inner, w * h, nonfinite, r)))
    return _run_tiles(_splat_tile, tasks, (h, w, c), client)


from ._lazy import public_dir as _public_dir  # noqa: E402

__dir__ = _public_dir(__name__)

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
    ``dask.array.map_overlap`` does, applied to the several arrays of a
    PixelStats, whose subpixel grid has another resolution).  Whole-image
    methods (``halo`` None: awr) are refused.

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

__all__ = ["denoise_many", "BatchResult", "ingest", "row_ranges", "tree_merge", "reconstruct_tiled",
           "local_client", "denoise_frame", "SUMMARY_NAME"]

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

    cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                       dashboard_address=":0", silence_logs=logging.CRITICAL,
                                       env={"MCRECON_THREADS": str(t), "OMP_NUM_THREADS": "1"})
    try:
        client = distributed.Client(cluster)
        try:
            yield client
        finally:
            client.close()
    finally:
        cluster.close()


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
        if any(ch in s for ch in "*?["):
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


def _up_to_date(log: Path, out: Path, prev: dict | None, config: dict) -> bool:
    try:
        if not out.is_file() or out.stat().st_size == 0:
            return False
        if out.stat().st_mtime_ns < log.stat().st_mtime_ns:
            return False
    except OSError:
        return False
    # the EXR is published atomically: it exists only complete; it must also
    # have been made by this method configuration (when a summary says so)
    return prev is None or prev.get("config") in (None, config)


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
    """Partial statistics of rows [start, stop) of a log (runs on a worker)."""
    from .io import read_log
    from .stats import PixelStats

    log = read_log(path)
    batches = ((c.positions, c.values) for c in log.iter_chunks(start=start, stop=stop, chunk_size=chunk_size,
                                                                 with_round=False))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", McreconWarning)  # counted in n_dropped / n_zeroed, warned once
        return PixelStats.from_batches(batches, width=log.width, height=log.height, channels=log.channels,
                                       subpixels=subpixels, nonfinite=nonfinite, source=str(log.path))


def _merge_two(a, b):
    return a.merge(b)


def tree_merge(items: Sequence, merge=_merge_two, submit=None):
    """Merge ``items`` pairwise, level by level (a balanced tree of depth ceil(log2 n)).

    ``submit(func, a, b)`` runs a merge (``client.submit``: the tree runs
    on the workers, futures in, futures out); default: in this process.
    """
    level = list(items)
    if not level:
        raise InputError("tree_merge", "items", "nothing to merge")
    while len(level) > 1:
        nxt = []
        for k in range(0, len(level) - 1, 2):
            nxt.append(submit(merge, level[k], level[k + 1]) if submit else merge(level[k], level[k + 1]))
        if len(level) % 2:
            nxt.append(level[-1])
        level = nxt
    return level[0]


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
        Row ranges (default: twice the workers).  Each worker holds the
        image-sized partial statistics of its range plus one chunk.
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
    from .samples import check_policy

    check_policy(nonfinite, "ingest")
    if not isinstance(log, SampleLog):
        log = read_log(log)
    path = str(Path(log.path).resolve())
    rows = int(chunk_size or DEFAULT_READ_ROWS)
    with _client_for(client, scheduler, workers) as c:
        nw = max(1, len(c.nthreads()))
        ranges = row_ranges(log.n_samples, parts or 2 * nw, align=rows)
        futs = [c.submit(_ingest_range, path, a, b, int(subpixels), nonfinite, rows, pure=False)
                for a, b in ranges]
        stats = tree_merge(futs, submit=lambda f, a, b: c.submit(f, a, b, pure=False)).result()
    n_bad = stats.n_dropped + stats.n_zeroed
    if n_bad:
        verb = "dropped" if nonfinite == "drop" else "set to 0"
        warnings.warn(f"{log.path}: values: {n_bad} sample(s) with NaN or Inf {verb} "
                      f"(policy nonfinite={nonfinite!r})", McreconWarning, stacklevel=2)
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
    """``(outer, inner)`` boxes of each tile: outer = the tile grown by ``halo`` and clipped,
    inner = the tile inside the outer box; boxes are ((y0, y1), (x0, x1))."""
    for ty in range(0, height, tile):
        for tx in range(0, width, tile):
            y0, y1, x0, x1 = ty, min(height, ty + tile), tx, min(width, tx + tile)
            oy0, oy1, ox0, ox1 = max(0, y0 - halo), min(height, y1 + halo), max(0, x0 - halo), min(width, x1 + halo)
            yield ((oy0, oy1), (ox0, ox1)), ((y0, y1), (x0, x1)), ((y0 - oy0, y1 - oy0), (x0 - ox0, x1 - ox0))


def reconstruct_tiled(source, *, method="box", tile: int = 1024, client=None, reference=None,
                      nonfinite: str = "drop", **options) -> np.ndarray:
    """Reconstruct in tiles with halos: the untiled image of a local method, tile by tile.

    Parameters
    ----------
    source : PixelStats, or a sample log path (ingested with :func:`ingest`
        when a ``client`` is given, else :meth:`PixelStats.from_log`)
    method : str or Method
        A method declaring a finite :meth:`~mcrecon.methods.Method.halo`;
        whole-image methods (awr) and methods that filter individual
        samples (splat) are refused.
    tile : int
        Tile side in pixels (the halo comes on top of it).
    client : distributed.Client, optional
        Tiles run as tasks on it; without one, in this process one after
        the other (memory: one grown tile at a time besides the input).
    reference : ndarray (H, W, C), optional
        For oracle modes (cropped with each tile).

    Raises
    ------
    InputError
        A whole-image method, a sample-filtering method, or statistics with
        a pixel of fewer than two samples (the fill-in policies for such
        pixels can borrow from anywhere in the image, so no finite halo
        makes the result local).
    """
    from .methods import Method, get_method
    from .stats import PixelStats

    m = method if isinstance(method, Method) else get_method(str(method), **options)
    if isinstance(method, Method) and options:
        raise InputError("reconstruct_tiled", sorted(options)[0], "a method object already carries its options")
    where = f"{m.where} (tiled)"
    if m.requires.samples or not m.requires.statistics:
        raise InputError(where, "method", f"{m.name} filters individual samples; tiling splits pixel statistics "
                         "only: reconstruct it untiled (mcrecon.reconstruct / mcrecon batch)")
    if isinstance(source, PixelStats):
        stats = source
    else:
        stats = ingest(source, client=client, subpixels=m.requires.subpixels, nonfinite=nonfinite) \
            if client is not None else PixelStats.from_log(source, subpixels=m.requires.subpixels,
                                                           nonfinite=nonfinite)
    h, w, c = stats.shape
    halo = m.halo(w, h)
    if halo is None:
        raise InputError(where, "halo", f"{m.name} is a whole-image method (its result at a pixel depends on the "
                         "whole film); it cannot be tiled: reconstruct it untiled on one worker with the memory "
                         "for the film (mcrecon.reconstruct)")
    tile = int(tile)
    if tile < 1:
        raise InputError(where, "tile", f"{tile}, expected a positive number of pixels")
    few = int((stats.count < 2).sum())
    if few:
        raise InputError(where, "statistics", f"{few} pixel(s) with fewer than 2 samples: their fill-in may "
                         "borrow from the whole image, so tiles would not reproduce the untiled result; "
                         "reconstruct untiled, or give every pixel at least 2 samples")
    if m.requires.subpixels and stats.subpixels != m.requires.subpixels:
        raise InputError(where, "statistics", f"need a {m.requires.subpixels}x{m.requires.subpixels} subpixel "
                         f"grid, got subpixels={stats.subpixels}")
    ref = None if reference is None else np.asarray(reference, dtype=np.float64)
    out = np.empty((h, w, c), np.float64)
    boxes = list(tile_boxes(w, h, tile, halo))
    if client is None:
        for (oy, ox), (iy, ix), inner in boxes:
            sub = _crop_stats(stats, oy[0], oy[1], ox[0], ox[1])
            r = None if ref is None else ref[oy[0]:oy[1], ox[0]:ox[1]]
            out[iy[0]:iy[1], ix[0]:ix[1]] = _reconstruct_tile(m, sub, r, inner)
        return out
    distributed = _dask()
    mf = client.scatter(m, broadcast=True)
    futs = {}
    for (oy, ox), (iy, ix), inner in boxes:
        sub = client.scatter(_crop_stats(stats, oy[0], oy[1], ox[0], ox[1]))
        r = None if ref is None else client.scatter(ref[oy[0]:oy[1], ox[0]:ox[1]])
        futs[client.submit(_reconstruct_tile, mf, sub, r, inner, pure=False)] = (iy, ix)
    for f in distributed.as_completed(futs):
        iy, ix = futs[f]
        out[iy[0]:iy[1], ix[0]:ix[1]] = f.result()
    return out

"""Scale-out on Dask (``dask.distributed``): many frames, huge logs, huge images.

Three entry points, each identical in result to the one-process path:

:func:`reconstruct_many`
    Many sample logs or pixel-statistics EXRs -> one EXR each (``mcrecon
    batch``): one task per frame, run with :func:`mcrecon.reconstruct`
    exactly as ``mcrecon denoise`` runs it, so the images are bit-identical.  Outputs are
    written atomically; a rerun skips frames whose output is newer than
    their log (and was made by the same method and options); a failing
    frame is reported with its one-line error and the others complete; a
    summary (frame, method, relative MSE against the log's reference,
    seconds, worker) is written as CSV and JSON.
:func:`ingest`
    One huge log -> :class:`~mcrecon.core.stats.PixelStats`: workers read
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

import csv
import dataclasses
import json
import os
import sys
import time
import warnings
from pathlib import Path


from ..errors import InputError, McreconWarning


from .._lazy import public_dir as _public_dir
from .cluster import _client_for, _dask, _local_workers, _one_line, _worker_name

__all__ = ['reconstruct_many', 'BatchResult', 'reconstruct_frame', 'SUMMARY_NAME']

#: Base name of the batch summary files in ``out_dir`` (``.csv`` and ``.json``).
SUMMARY_NAME = "batch_summary"
SUMMARY_FIELDS = ("frame", "log", "output", "status", "method", "rel_mse", "seconds", "worker", "samples",
                  "error")


# ----------------------------------------------------------------------------
# 1. Many logs -> many images
# ----------------------------------------------------------------------------

def reconstruct_frame(log_path, out_path, method: str, options: dict, *, nonfinite: str = "drop",
                      png: bool = False, exposure: float = 0.0, exr_options: dict | None = None,
                      frame: str | None = None) -> dict:
    """Reconstruct one frame exactly as ``mcrecon reconstruct`` does and write its EXR atomically.

    ``log_path``: a sample log, or a pixel-statistics EXR (read with
    ``exr_options``, :func:`mcrecon.io.read_pixel_stats_exr`'s keywords;
    by default with the layout its channel names say; written in its
    output colours), or the glob of a seed set's renders (``frame``: its
    name).  ``options``: the method options the caller gave.
    Runs on a worker; never raises: a failure comes back as
    ``status='failed'`` with the one-line error.
    """
    from ..io import read_log, write_exr, write_png_preview
    from ..core.metrics import relative_mse
    from ..offline.pixel_files import is_pixel_file_source
    from ..offline.reconstruction import reconstruct

    log_path, out_path = Path(log_path), Path(out_path)
    exr = is_pixel_file_source(log_path)
    rec = {"frame": frame or log_path.stem, "log": str(log_path), "output": str(out_path), "method": method,
           "rel_mse": None, "seconds": None, "worker": _worker_name(), "samples": None, "error": None}
    t0 = time.perf_counter()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", McreconWarning)
            log = None if exr else read_log(log_path)
            r = reconstruct(log_path if exr else log, method=method, nonfinite=nonfinite, full=True,
                            **({"exr_options": exr_options} if exr and exr_options else {}), **options)
            if png:  # the preview first: the EXR (atomic) marks a complete frame
                write_png_preview(out_path.with_suffix(".png"), r.image, exposure=exposure)
            write_exr(out_path, r.image, channels=r.channels)
            ref = log.reference() if log is not None else None
            if ref is not None:
                rec["rel_mse"] = relative_mse(r.image, ref)
            rec["samples"] = int(log.n_samples) if log is not None else int(r.inputs.stats.count.sum())
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
    """What :func:`reconstruct_many` did: one record per frame (in input order) and the summary files."""

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


def _config(method, options: dict, nonfinite: str, exr_options: dict) -> tuple[dict, dict]:
    """(the configuration a frame's output is made by, as the summary records it; the options the caller
    gave, which the workers build the method from: an option not given keeps the freedom
    ``statistics_fallback`` has on an EXR frame)."""
    from ..methods.base import Method
    from ..methods import get_method

    if isinstance(method, Method):
        if options:
            raise InputError("batch", sorted(options)[0], "a method object already carries its options")
        m = method
    else:
        m = get_method(str(method), **options)   # validate once, here, before any work
    config = {"method": m.name, "options": dict(m.params), "nonfinite": nonfinite}
    if exr_options:  # only then: summaries written without EXR read options still match
        config["exr_options"] = {k: exr_options[k] for k in sorted(exr_options)}
    return config, {k: m.params[k] for k in sorted(m.given_options)}


def _previous(json_path: Path) -> dict:
    try:
        data = json.loads(json_path.read_text())
        return {r["frame"]: r for r in data.get("frames", []) if r.get("status") in ("done", "skipped")}
    except (OSError, ValueError, AttributeError, TypeError, KeyError):
        return {}


def _damaged_output(log: Path, out: Path) -> str | None:
    """Why an existing output EXR is not this log's image (None when it reads whole and fits the log).

    The EXR is published atomically, but a file can still be truncated or
    replaced afterwards (a full disk, a copy that stopped): it is read whole
    (an image: cheap beside its reconstruction; a file cut after its header
    reads no pixels) and its size and channel count checked against the log's.
    """
    from ..io import read_exr, read_log
    from ..offline.pixel_files import is_pixel_file_source

    try:
        image, channels = read_exr(out)
    except InputError as exc:
        return f"not a readable EXR ({exc.problem})"
    if is_pixel_file_source(log):  # a pixel-statistics EXR: its output colours are not its channels; the size must fit
        try:
            src = read_exr(log)[0]
        except InputError:
            return None   # the frame fails on its own, with the file's error
        if src.shape[:2] != image.shape[:2]:
            return f"{image.shape[1]}x{image.shape[0]}, the input is {src.shape[1]}x{src.shape[0]}"
        return None
    try:
        log = read_log(log)
    except InputError:
        return None   # the frame fails on its own, with the log's error
    got, want = (image.shape[1], image.shape[0], len(channels)), (log.width, log.height, len(log.channels))
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
    from ..io._atomic import atomic_path

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


def reconstruct_many(paths, *, method="box", out_dir, client=None, scheduler: str | None = None,
                 workers: int | None = None, nonfinite: str = "drop", force: bool = False, png: bool = False,
                 exposure: float = 0.0, progress: bool | None = None, summary: bool = True,
                 exr_options: dict | None = None, seed_sets=None, **options) -> BatchResult:
    """Reconstruct every frame in ``paths`` into ``out_dir/<frame stem>.exr`` on a Dask cluster.

    Parameters
    ----------
    paths : path, glob pattern or sequence of them
        Sample logs or pixel-statistics EXRs (patterns like ``'frames/*.h5'``
        or ``'frames/*.exr'`` are expanded here).
    seed_sets : str, optional
        Frames that are seed sets (:func:`mcrecon.io.seed_sets.seed_set_frames`):
        ``'shot.####.seed*.exr'`` makes one frame per frame number, written
        as ``out_dir/shot.0001.exr``; ``paths`` may then be empty.
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
    exr_options : dict, optional
        How every pixel-statistics EXR frame is read (the keywords of
        :func:`mcrecon.io.read_pixel_stats_exr`, as
        :func:`mcrecon.reconstruct` takes them): a Mitsuba moment EXR, which
        carries no sample count, needs ``{"spp": N}``.  Refused when a frame
        is a sample log.

    Returns
    -------
    BatchResult
        ``records`` in input order: ``status`` is ``done``, ``skipped``
        (up to date) or ``failed`` (with ``error``, one line).
    """
    from ..core.samples import check_policy
    from ..offline.pixel_files import check_exr_options, is_pixel_file_source

    check_policy(nonfinite, "batch")
    exr_options = check_exr_options(exr_options, "batch")
    logs = _expand(paths) if paths or seed_sets is None else []
    if seed_sets is not None:
        from ..io.seed_sets import seed_set_frames
        logs += seed_set_frames(seed_sets)
    if exr_options:
        for p in logs:
            if not is_pixel_file_source(p):
                raise InputError(str(p), "exr_options", f"{', '.join(sorted(exr_options))}: read options of "
                                 "pixel-statistics EXR frames (paths ending in .exr), and this frame is a sample "
                                 "log; give the logs and the EXRs in separate batches")
    stems = {}
    for p in logs:
        if p.stem in stems and stems[p.stem] != p:
            raise InputError(str(p), "frame", f"same name as {stems[p.stem]}: both would write {p.stem}.exr")
        stems[p.stem] = p
    out_dir = Path(out_dir)
    for p in logs:  # an EXR frame in the output directory would be replaced by its own image
        if os.path.abspath(out_dir / f"{p.stem}.exr") == os.path.abspath(p):
            raise InputError(str(p), "out_dir", "the frame's output would replace the frame itself; give "
                             "another output directory")
    out_dir.mkdir(parents=True, exist_ok=True)
    config, given = _config(method, options, nonfinite, exr_options)
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
                f = c.submit(reconstruct_frame, str(p), str(out), config["method"], given,
                             nonfinite=nonfinite, png=png, exposure=exposure, exr_options=exr_options,
                             frame=p.stem, pure=False,
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

__dir__ = _public_dir(__name__)

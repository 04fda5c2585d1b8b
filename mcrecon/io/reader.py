"""HDF5 sample logs, format version 1 (specified in ``docs/sample-log-format.md``).

This module is the only place that touches h5py for sample logs.  A log
is read lazily: :func:`read_log` validates the layout and returns a
:class:`SampleLog` that streams samples in chunks and never modifies the
file.  :func:`write_log` writes a whole log atomically (temporary file,
then rename); :func:`append_log` appends one round and commits it by
updating ``n_committed`` last, so a crash during an append leaves the
committed rounds readable and the partial round ignored.

Appending costs time and space proportional to the round, not to the
file: the per-round datasets (``/rounds/end``, ``/run/round_records``) are
chunked and resizable and grow by one row per round, and an append opens
the file once and reads only the attributes, shapes and last rows it needs.

Round records (the adaptive driver's times and errors) are stored as rows
of a compound dataset, one column per known key, with a bit mask of the
keys present (format_minor 2); keys outside the columns go to a JSON
dataset beside it, written only for the rounds that have such keys.  Logs
written before keep their JSON ``/run/records`` and are appended to in
that layout.
"""

from __future__ import annotations

import contextlib
import time
from pathlib import Path
from typing import Iterator

import h5py
import numpy as np

from ..errors import InputError
from ..core.requests import check_sampler
from ..core.samples import check_reference, positions_on_film, round_slices, touches_window
from ..core.samples import DEFAULT_READ_ROWS
from .lock import _err, live_writer
from .logformat import (LogChunk, _H5_ERRORS, _HAS_RECORD, _LIVE_RETRIES, _LIVE_RETRY_SECONDS, _committed_rows,
                        _detail, _json_attr, _open, _read_header, _read_slice, _record_columns, _strings,
                        _tail_info, _tail_rows)

__all__ = ['SampleLog', 'read_log']

def _bad_rows(d, s: int, e: int) -> tuple[int, int]:
    """The first chunk-aligned row range of [s, e) of ``d`` that fails to read (else (s, e)), cut to [s, e).

    Cut: rows past ``e`` (past the committed ones, those an interrupted
    append left) are not named.
    """
    c = d.chunks[0] if d.chunks else max(e - s, 1)
    for a in range(s - s % c, e, c):
        b = min(a + c, d.shape[0], e)
        try:
            d[a:b]
        except _H5_ERRORS:
            return max(a, s), b
    return s, e


def _member(path, group, name: str, shown: str):
    """``group[name]``, or a one-line error naming ``shown`` when it cannot be opened: a soft link to
    nothing or to itself, an external link to a missing file (HDF5 says only "component not found")."""
    try:
        return group[name]
    except _H5_ERRORS as exc:
        link = None
        with contextlib.suppress(*_H5_ERRORS):
            link = group.get(name, getlink=True)
        if isinstance(link, h5py.SoftLink):
            what = f"a soft link to {link.path}, which does not lead to an object (missing, or a loop of links)"
        elif isinstance(link, h5py.ExternalLink):
            what = f"an external link to {link.path} in {link.filename}, which cannot be opened"
        else:
            what = f"cannot be opened ({_detail(exc)})"
        raise _err(path, shown, f"{what}: store the data itself there, or delete it") from None


def _read_error(path, name: str, d, s: int, e: int, exc) -> InputError:
    """A one-line error of a failed read of rows [s, e) of dataset ``name``."""
    if isinstance(exc, InputError):
        return exc
    detail = _detail(exc)
    pid = live_writer(path)
    if pid is not None:
        return _err(path, f"dataset /{name}", f"rows {s}-{e - 1} could not be read while process {pid} is "
                    f"writing the log ({detail}); try again")
    if "filter" in detail or "checksum" in detail.lower():
        if d is not None:
            with contextlib.suppress(*_H5_ERRORS):
                s, e = _bad_rows(d, s, e)
        return _err(path, f"dataset /{name}", f"rows {s}-{e - 1}: checksum mismatch (Fletcher-32), the stored "
                    "data is damaged; regenerate the log or restore it from a copy")
    return _err(path, f"dataset /{name}", f"rows {s}-{e - 1} could not be read ({detail}); the file is damaged")


class _Reader:
    """A log opened for reading that survives a concurrent append.

    A read that fails while a live run holds the writer lock is retried on
    a fresh open (the run may have been half-way through an append); any
    other failure, or one that persists, becomes a one-line InputError
    naming the dataset and rows.
    """

    def __init__(self, path):
        self.path = path
        self.f = _open(path)

    def read(self, name: str, s: int, e: int, out=None):
        for attempt in range(_LIVE_RETRIES + 1):
            d = None
            try:
                d = self.f[name]
                if out is None:
                    return d[s:e]
                d.read_direct(out, np.s_[s:e], np.s_[0:e - s])
                return out[:e - s]
            except _H5_ERRORS as exc:
                if isinstance(exc, InputError):
                    raise
                # A kill during an append's rewrite of the last, partly filled chunk: its
                # committed rows are intact, /_tail tells (genuine damage still fails).
                rows = None if d is None else _tail_rows(self.f, name, d, s, e)
                if rows is not None:
                    if out is None:
                        return rows
                    out[:e - s] = rows
                    return out[:e - s]
                if attempt == _LIVE_RETRIES or live_writer(self.path) is None:
                    raise _read_error(self.path, name, d, s, e, exc) from None
                self.f.close()
                time.sleep(_LIVE_RETRY_SECONDS)
                self.f = _open(self.path)

    def close(self):
        self.f.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _read_ds(path, d, name: str, s: int = 0, e: int | None = None, *, short: bool = False):
    """Rows [s, e) of dataset ``d`` (``/name``); a failed read is a one-line InputError.

    A torn last chunk (a kill during an append) reads its committed rows
    from /_tail; with ``short`` (a per-round dataset read whole, of which
    the caller keeps the committed rows) the rows then end with them.
    """
    e = d.shape[0] if e is None else e
    try:
        return _read_slice(d.file, name, d, s, e, short=short)
    except _H5_ERRORS as exc:
        raise _read_error(path, name, d, s, e, exc) from None


def _read_round_records(path, run, n_rounds: int) -> list[dict]:
    """The records of the first ``n_rounds`` rounds that have one, in round order."""
    old = None
    if "records" in run:  # format_minor 0 and 1: one JSON string per record
        d = run["records"]
        if not isinstance(d, h5py.Dataset) or d.ndim != 1:
            raise _err(path, "dataset /run/records", f"shape {getattr(d, 'shape', None)}, expected (R,) strings")
        # Row i is round i's record; a round without one holds null (format_minor 1).
        old = [_json_attr(path, "dataset run/records", x) for x in _strings(_read_ds(path, d, "run/records", 0,
                                                                                       min(n_rounds, d.shape[0])))]
    if "round_records" not in run:
        return [r for r in old or () if r is not None]
    # format_minor 2: compound rows + JSON of the keys outside the columns
    d = run["round_records"]
    _, cols = _record_columns(path, d)
    rows = _read_ds(path, d, "run/round_records", 0, min(n_rounds, d.shape[0]), short=True)
    present = rows["present"].astype(np.int64).tolist()
    values = [rows[c].tolist() for c in cols]  # Python ints and floats, exactly as stored
    extra = run.get("round_records_extra")
    if extra is not None and (not isinstance(extra, h5py.Dataset) or extra.ndim != 1):
        raise _err(path, "dataset /run/round_records_extra",
                   f"shape {getattr(extra, 'shape', None)}, expected (R,) strings")
    extra = _strings(_read_ds(path, extra, "run/round_records_extra", 0, min(n_rounds, extra.shape[0]))) \
        if extra is not None else []
    out = []
    for i in range(n_rounds):
        p = present[i] if i < len(present) else 0
        if not p & _HAS_RECORD:
            # A round an mcrecon before format_minor 2 appended to this log keeps its JSON record.
            if old is not None and i < len(old) and old[i] is not None:
                out.append(old[i])
            continue
        rec = {c: values[k][i] for k, c in enumerate(cols) if p >> (k + 1) & 1}
        if i < len(extra) and extra[i]:
            more = _json_attr(path, "dataset run/round_records_extra", extra[i])
            if not isinstance(more, dict):
                raise _err(path, "dataset /run/round_records_extra", f"row {i}: expected a JSON object")
            rec.update(more)
        out.append(dict(sorted(rec.items())))  # key order of the JSON records (sorted)
    return out


def _check_round_labels(path, rds, ends: np.ndarray) -> None:
    """Refuse a /round that contradicts the committed rounds of /rounds/end, in one line.

    /rounds/end gives the rounds; /round must agree: one label throughout
    each committed round, a larger one in each later round.  Since /round
    is non-decreasing, reading the first and last row of every non-empty
    round is enough (2 rows per round, not the whole dataset).  Rows past
    the committed ones were cut from ``ends`` before: they are not a
    contradiction.
    """
    ends = np.asarray(ends, np.int64)
    starts = np.concatenate([[0], ends[:-1]])
    full = ends > starts
    if not full.any():
        return
    idx = np.unique(np.concatenate([starts[full], ends[full] - 1]))
    labels = dict(zip(idx.tolist(), _read_rows(path, rds, "round", idx).tolist()))
    prev = None
    for k in np.flatnonzero(full).tolist():
        s, e = int(starts[k]), int(ends[k])
        first, last = labels[s], labels[e - 1]
        if first != last or (prev is not None and first <= prev[1]):
            what = (f"{first} at row {s} and {last} at row {e - 1}" if first != last else
                    f"{first} at row {s}, its first row, after {prev[1]} at row {prev[0]}, the last of the round "
                    "before")
            raise _err(path, "dataset /rounds/end",
                       f"round {k} (rows {s}-{e - 1} by /rounds/end) contradicts /round, which holds {what}; "
                       "/round must hold one label per round, larger in each later round: "
                       "rewrite /rounds/end as the cumulative sample count at the end of each round of /round, "
                       "or delete it (mcrecon then derives the rounds from /round)")
        prev = (e - 1, last)


def _read_rows(path, d, name: str, idx: np.ndarray) -> np.ndarray:
    """Rows ``idx`` (sorted, distinct) of the 1-D dataset ``d``, as int64, in one point selection."""
    if idx.size == 0:
        return np.zeros(0, np.int64)
    try:
        return _point_rows(d, idx)
    except _H5_ERRORS as exc:
        out = _torn_point_rows(d, name, np.asarray(idx, np.int64))  # a torn last chunk: see _read_ds
        if out is None:
            raise _read_error(path, name, d, int(idx[0]), int(idx[-1]) + 1, exc) from None
        return out


def _point_rows(d, idx) -> np.ndarray:
    out = np.empty(idx.size, np.int64)
    if idx.size:
        fspace = d.id.get_space()
        fspace.select_elements(np.asarray(idx, np.uint64).reshape(-1, 1))
        d.id.read(h5py.h5s.create_simple((idx.size,)), fspace, out, mtype=h5py.h5t.NATIVE_INT64)
    return out


def _torn_point_rows(d, name: str, idx: np.ndarray):
    """Rows ``idx`` of ``d`` with those in a torn last chunk from /_tail (see _tail_rows), or None."""
    f = d.file
    info = _tail_info(f, name, d)
    if info is None:
        return None
    a, b = info[:2]
    inside = (idx >= a) & (idx < b)
    if not inside.any():
        return None
    lo, hi = int(idx[inside][0]), int(idx[inside][-1]) + 1
    rows = _tail_rows(f, name, d, lo, hi)
    if rows is None:
        return None
    out = np.empty(idx.size, np.int64)
    out[inside] = np.asarray(rows, np.int64)[idx[inside] - lo]
    try:
        out[~inside] = _point_rows(d, idx[~inside])
    except _H5_ERRORS:
        return None
    return out


class SampleLog:
    """A validated, lazily read sample log.  Obtain one with :func:`read_log`.

    Attributes
    ----------
    path : Path
    width, height : int
    channels : tuple of str
    n_samples : int
        Committed samples (rows past it belong to an interrupted append).
    round_ends : ndarray of int64
        Cumulative sample count at the end of each committed round.
    metadata : dict
        Renderer, scene, seed and settings as written.
    feature_names : tuple of str
    value_dtype : numpy dtype
    has_reference : bool
    run_settings : dict or None
        Driver settings of an adaptive run (for ``--resume``).
    round_records : list of dict
        Per-round records of an adaptive run (times, errors): those of the
        committed rounds that have one, in round order, as they were written
        (JSON types: ints stay ints, floats are exact float64).
    format_minor : int
        Compatible revision of format version 1 (0 when not recorded).
    sampler : str
        What each pixel's samples are (:data:`~mcrecon.core.requests.SAMPLERS`): the root attribute
        ``sampler``, else an adaptive run's recorded ``sampler`` setting, else ``independent``.
    """

    def __init__(self, path):
        self.path = Path(path)
        for attempt in range(_LIVE_RETRIES + 1):
            try:
                with _open(self.path) as f:
                    self._validate(f)
                return
            except _H5_ERRORS as exc:
                # A live run may be half-way through an append: read again (the committed
                # part never changes).  A log at rest fails at once, in one line.
                pid = live_writer(self.path)
                if pid is None or attempt == _LIVE_RETRIES:
                    if isinstance(exc, InputError):
                        raise
                    where = "while process %s is writing it" % pid if pid is not None else "(the file is damaged)"
                    raise _err(self.path, "file", f"could not be read {where}: {_detail(exc)}") from None
                time.sleep(_LIVE_RETRY_SECONDS)

    def _validate(self, f):
        path = self.path
        h = _read_header(path, f)
        self.width, self.height, self.channels = h.width, h.height, h.channels
        self.format_minor = h.format_minor
        n = h.n
        self.n_samples = n
        self.value_dtype = h.value_dtype
        self.position_dtype = h.position_dtype
        a = f.attrs
        self._has_round = "round" in f
        if self._has_round:
            r = f["round"]
            if r.ndim != 1 or r.shape[0] < n or r.dtype.kind not in "iu":
                raise _err(path, "dataset /round", f"shape {r.shape} dtype {r.dtype}, expected ({n},) integers")
        if n == 0:
            ends = np.zeros(0, np.int64)
        elif "rounds/end" in f:
            d = f["rounds/end"]
            if not isinstance(d, h5py.Dataset) or d.ndim != 1 or d.dtype.kind not in "iu":
                raise _err(path, "dataset /rounds/end", f"shape {getattr(d, 'shape', None)}, expected (R,) integers")
            ends = np.asarray(_read_ds(path, d, "rounds/end", short=True), dtype=np.int64)
            ends = ends[:_committed_rows(ends, n)]
            ends = ends[ends <= n]
            if ends.size and ends[0] < 0:
                raise _err(path, "dataset /rounds/end", f"row 0 is {ends[0]}, expected cumulative sample counts "
                           ">= 0: rewrite it, or delete it (mcrecon then derives the rounds from /round)")
            if ends.size and (np.any(np.diff(ends) < 0)):
                raise _err(path, "dataset /rounds/end", "must be non-decreasing")
            if not ends.size or ends[-1] != n:
                ends = np.append(ends, n)
            if self._has_round:
                _check_round_labels(path, f["round"], ends)
        elif self._has_round:
            ends = self._scan_round_ends(f["round"], n)
        else:
            ends = np.array([n], np.int64)
        self.round_ends = ends
        if "features" in f and not isinstance(f["features"], h5py.Group):
            raise _err(path, "/features", "a dataset, expected a group of /features/NAME datasets (one per "
                       "feature, one row per sample)")
        self.feature_names = tuple(sorted(f["features"].keys())) if "features" in f else ()
        self.feature_shapes = {}
        self.feature_dtypes = {}  # the stored dtypes, from the metadata (a row of a wide feature is no read)
        for name in self.feature_names:
            d = _member(path, f["features"], name, f"/features/{name}")
            if not isinstance(d, h5py.Dataset) or d.shape[:1] < (n,):
                raise _err(path, f"dataset /features/{name}", f"shape {getattr(d, 'shape', None)}, expected ({n}, ...)")
            if d.dtype.kind not in "fiub":
                raise _err(path, f"dataset /features/{name}", f"dtype {d.dtype}, expected a numeric dtype "
                           "(integer, float or bool)")
            self.feature_shapes[name] = tuple(d.shape[1:])
            self.feature_dtypes[name] = d.dtype
        self.has_reference = "reference" in f
        if self.has_reference:
            ref = _member(path, f, "reference", "/reference")
            expect = (self.height, self.width, len(self.channels))
            if not isinstance(ref, h5py.Dataset):
                raise _err(path, "dataset /reference", f"a {type(ref).__name__.lower()}, expected a dataset of shape "
                           f"(height, width, channels) = {expect}: write the reference image there, or delete it")
            if ref.shape != expect:
                raise _err(path, "dataset /reference", f"shape {ref.shape}, expected (height, width, channels) = {expect}")
        meta = a.get("metadata_json", "{}")
        self.metadata = _json_attr(path, "attribute metadata_json", meta)
        if not isinstance(self.metadata, dict):
            raise _err(path, "attribute metadata_json", "expected a JSON object")
        run = f.get("run")
        self.run_settings = None
        self.round_records = []
        if run is not None:
            s = run.attrs.get("settings_json")
            if s is not None:
                self.run_settings = _json_attr(path, "attribute run/settings_json", s)
            self.round_records = _read_round_records(path, run, len(self.round_ends))
        if "sampler" in a:
            self.sampler = check_sampler(a["sampler"], where=str(path), field="attribute sampler")
        else:  # an adaptive run records its renderer's sampler in its settings
            recorded = self.run_settings.get("sampler") if isinstance(self.run_settings, dict) else None
            self.sampler = check_sampler(recorded, where=str(path), field="run settings sampler")

    @staticmethod
    def _scan_round_ends(rds, n):
        ends = []
        prev = None
        for start in range(0, n, DEFAULT_READ_ROWS):
            r = np.asarray(_read_ds(getattr(rds.file, "filename", "log"), rds, "round", start,
                                    min(n, start + DEFAULT_READ_ROWS)), dtype=np.int64)
            if prev is not None and r.size and r[0] != prev:
                ends.append(start)
            change = np.flatnonzero(np.diff(r)) + 1 + start
            ends.extend(change.tolist())
            if r.size:
                prev = r[-1]
        ends.append(n)
        return np.asarray(ends, np.int64)

    # ----------------------------------------------------------- reading
    @property
    def n_rounds(self) -> int:
        return int(self.round_ends.size)

    def round_slices(self) -> list[tuple[int, int]]:
        """(start, stop) sample ranges of each committed round."""
        return round_slices(self.round_ends)

    def iter_chunks(self, *, chunk_size: int = DEFAULT_READ_ROWS, rounds=None,
                    start: int = 0, stop: int | None = None, with_round: bool = True,
                    features=(), window=None) -> Iterator[LogChunk]:
        """Stream committed samples in chunks of at most ``chunk_size`` rows.

        Parameters
        ----------
        rounds : iterable of int, optional
            Only these rounds (indices into :meth:`round_slices`).
        start, stop : int
            Sample range when ``rounds`` is None.
        with_round : bool
            Read the per-sample round index (``chunk.round``; else None).
        features : sequence of str
            Per-sample features to read with the samples (``chunk.features``).
        window : (y0, y1, x0, x1), optional
            Read the values and features only of chunks with a sample in
            those pixels (``chunk.values`` and ``chunk.features`` None for
            the others, whose positions are all on the film): a reader of a
            window's statistics needs every chunk's positions (each pixel's
            turn in the half split), but adds the window's samples only.
        """
        for name in features:
            if name not in self.feature_names:
                raise _err(self.path, f"dataset /features/{name}",
                           f"no such feature; valid: {', '.join(self.feature_names) or '(none)'}")
        chunk_size = max(int(chunk_size), 1)
        if rounds is None:
            stop = self.n_samples if stop is None else min(int(stop), self.n_samples)
            ranges = [(int(start), stop)]
        else:
            sl = self.round_slices()
            ranges = [sl[int(r)] for r in rounds]
        with _Reader(self.path) as f:
            for a, b in ranges:
                for s in range(a, b, chunk_size):
                    e = min(b, s + chunk_size)
                    pos = f.read("positions", s, e)
                    inside = window is None or touches_window(pos, window)
                    # a chunk without a sample in the window: its positions alone (valid ones; else the values
                    # too, for the statistics to refuse them as they refuse them in a pass over the film)
                    val = None if not inside and positions_on_film(pos, self.width, self.height) else \
                        f.read("values", s, e)
                    if not with_round:
                        rnd = None
                    elif self._has_round:
                        rnd = f.read("round", s, e).astype(np.int64, copy=False)
                    else:
                        rnd = (np.searchsorted(self.round_ends, np.arange(s, e), side="right")).astype(np.int64)
                    feats = {name: f.read(f"features/{name}", s, e) for name in features} if inside else None
                    yield LogChunk(pos, val, rnd, s, feats)

    def iter_into(self, buffers, *, start: int = 0, stop: int | None = None):
        """Stream committed samples into caller-owned buffers, rotating through them.

        ``buffers`` is a sequence of ``(positions, values)`` array pairs of
        equal row count (the chunk size) and the log's dtypes.  Yields
        ``(positions_view, values_view)`` of the filled rows; a buffer is
        reused ``len(buffers)`` chunks later, so a consumer that overlaps
        work with reading must be done with a chunk by then.  Avoids
        allocating a fresh array per chunk (the hot path of
        :meth:`mcrecon.core.stats.PixelStats.from_log`).
        """
        rows = buffers[0][0].shape[0]
        stop = self.n_samples if stop is None else min(int(stop), self.n_samples)
        with _Reader(self.path) as f:
            for i, s in enumerate(range(int(start), stop, rows)):
                e = min(stop, s + rows)
                pb, vb = buffers[i % len(buffers)]
                yield f.read("positions", s, e, out=pb), f.read("values", s, e, out=vb)

    def read_all(self, *, rounds=None, features=()) -> LogChunk:
        """All committed samples (or those of some rounds) in memory, with the ``features`` named."""
        chunks = list(self.iter_chunks(rounds=rounds, features=features))
        if not chunks:
            c = len(self.channels)
            return LogChunk(np.zeros((0, 2), self.position_dtype), np.zeros((0, c), self.value_dtype),
                            np.zeros(0, np.int64), 0, {})
        return LogChunk(np.concatenate([c.positions for c in chunks]),
                        np.concatenate([c.values for c in chunks]),
                        np.concatenate([c.round for c in chunks]), chunks[0].start,
                        {name: np.concatenate([c.features[name] for c in chunks]) for name in features})

    def read_feature(self, name: str, *, start: int = 0, stop: int | None = None) -> np.ndarray:
        if name not in self.feature_names:
            raise _err(self.path, f"dataset /features/{name}",
                       f"no such feature; valid: {', '.join(self.feature_names) or '(none)'}")
        stop = self.n_samples if stop is None else min(stop, self.n_samples)
        with _Reader(self.path) as f:
            return f.read(f"features/{name}", start, stop)

    def reference(self) -> np.ndarray | None:
        """The reference image (H, W, C) float64, or None."""
        if not self.has_reference:
            return None
        with _Reader(self.path) as f:
            ref = np.asarray(f.read("reference", 0, self.height), dtype=np.float64)
        return check_reference(ref, (self.height, self.width, len(self.channels)),
                               where=f"{self.path}: dataset /reference")

    def __repr__(self) -> str:
        return (f"SampleLog({str(self.path)!r}, {self.width}x{self.height}, channels={','.join(self.channels)}, "
                f"samples={self.n_samples}, rounds={self.n_rounds})")


def read_log(path) -> SampleLog:
    """Open and validate a sample log without loading its samples.

    Raises
    ------
    InputError
        The file is missing, not HDF5, truncated, or lacks or mis-shapes
        a required dataset or attribute.  The message names the file and
        the field.
    """
    return SampleLog(path)

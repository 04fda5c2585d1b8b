"""HDF5 sample logs, format version 1 (specified in ``docs/sample-log-format.md``).

This module is the only place that touches h5py for sample logs.  A log
is read lazily: :func:`read_log` validates the layout and returns a
:class:`SampleLog` that streams samples in chunks and never modifies the
file.  :func:`write_log` writes a whole log atomically (temporary file,
then rename); :func:`append_log` appends one round and commits it by
updating ``n_committed`` last, so a crash during an append leaves the
committed rounds readable and the partial round ignored.
"""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
from pathlib import Path
from typing import Iterator, Mapping, Sequence

import h5py
import numba
import numpy as np

from ..errors import InputError
from ._atomic import publish

__all__ = ["cast_positions", "FORMAT_NAME", "FORMAT_VERSION", "SampleLog", "LogChunk", "read_log", "write_log",
           "append_log", "set_run_settings", "DEFAULT_CHUNK_ROWS"]

FORMAT_NAME = "mcrecon-sample-log"
FORMAT_VERSION = 1
#: Rows per HDF5 chunk: 65536 samples = 512 KiB of float32 positions.
DEFAULT_CHUNK_ROWS = 1 << 16
#: Rows per read when streaming (a multiple of the chunk rows).
DEFAULT_READ_ROWS = 1 << 20
_VALID_FLOATS = (np.float32, np.float64)


@dataclasses.dataclass(eq=False)
class LogChunk:
    """A contiguous run of samples read from a log."""

    positions: np.ndarray  # (n, 2)
    values: np.ndarray  # (n, C)
    round: np.ndarray  # (n,) int
    start: int  # index of the first sample in the log

    def __len__(self) -> int:
        return int(self.positions.shape[0])

    def __getitem__(self, i):  # (positions, values) unpacking
        return (self.positions, self.values)[i]


@numba.njit(cache=True, nogil=True)
def _cast_positions_f32(pos, out):
    for k in range(pos.shape[0]):
        for a in range(2):
            x = pos[k, a]
            y = np.float32(x)
            # float32 rounding can carry x = 127.99999999 up to 128.0: keep the pixel.
            if np.floor(y) != np.floor(x):
                y = np.nextafter(np.float32(np.floor(x) + 1.0), np.float32(0.0))
            out[k, a] = y
    return out


def cast_positions(positions, dtype) -> np.ndarray:
    """Cast film positions to ``dtype`` without moving any into the next pixel.

    float32 rounding can turn x = 127.99999999 into 128.0; such positions
    are set to the largest value of that dtype inside their pixel.
    """
    pos = np.asarray(positions)
    dtype = np.dtype(dtype)
    if pos.dtype == dtype:
        return pos
    if dtype == np.float32 and pos.dtype == np.float64 and pos.ndim == 2 and pos.shape[1] == 2:
        return _cast_positions_f32(np.ascontiguousarray(pos), np.empty(pos.shape, np.float32))
    out = pos.astype(dtype)
    moved = np.floor(out) != np.floor(pos)
    if moved.any():
        cell = np.floor(pos[moved])
        out[moved] = np.nextafter((cell + 1).astype(dtype), dtype.type(0))
    return out


def _err(path, field, problem):
    return InputError(str(path), field, problem)


def _open(path, mode="r"):
    path = Path(path)
    if not path.exists():
        raise _err(path, "file", "does not exist")
    if path.is_dir():
        raise _err(path, "file", "is a directory; expected an HDF5 sample log")
    try:
        return h5py.File(path, mode)
    except OSError as exc:
        detail = " ".join(str(exc).split())  # one line: h5py's messages carry newlines
        raise _err(path, "file", f"not a readable HDF5 file (truncated or another format: {detail}); "
                   "regenerate it, or check the path") from None


def _json_attr(path, field, raw):
    try:
        return json.loads(raw.decode() if isinstance(raw, bytes) else str(raw))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise _err(path, field, f"not valid JSON ({exc})") from None


def _str_list(v) -> tuple[str, ...]:
    arr = np.atleast_1d(v)
    return tuple(x.decode() if isinstance(x, bytes) else str(x) for x in arr.tolist())


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
        Per-round records of an adaptive run (times, errors).
    """

    def __init__(self, path):
        self.path = Path(path)
        with _open(self.path) as f:
            self._validate(f)

    def _validate(self, f):
        path = self.path
        a = f.attrs
        fmt = a.get("format")
        if fmt is not None and (fmt.decode() if isinstance(fmt, bytes) else str(fmt)) != FORMAT_NAME:
            raise _err(path, "attribute format", f"is {fmt!r}, expected {FORMAT_NAME!r}")
        ver = a.get("format_version")
        if ver is None:
            raise _err(path, "attribute format_version", f"missing; expected {FORMAT_VERSION} "
                       "(is this an mcrecon sample log? see docs/sample-log-format.md)")
        try:
            ver = int(ver)
        except (TypeError, ValueError):
            raise _err(path, "attribute format_version", f"is {ver!r}, expected the integer {FORMAT_VERSION}") from None
        if ver != FORMAT_VERSION:
            raise _err(path, "attribute format_version", f"is {ver}, this mcrecon reads version {FORMAT_VERSION}")
        for key in ("width", "height", "channels"):
            if key not in a:
                raise _err(path, f"attribute {key}", "missing (see docs/sample-log-format.md)")
        try:
            self.width, self.height = int(a["width"]), int(a["height"])
        except (TypeError, ValueError):
            raise _err(path, "attribute width/height", "expected integers") from None
        if self.width < 1 or self.height < 1:
            raise _err(path, "attribute width/height", f"{self.width}x{self.height}, expected at least 1x1")
        self.channels = _str_list(a["channels"])
        if not self.channels or len(set(self.channels)) != len(self.channels):
            raise _err(path, "attribute channels", f"{self.channels}: expected distinct non-empty names")
        for name in ("positions", "values"):
            if name not in f or not isinstance(f[name], h5py.Dataset):
                raise _err(path, f"dataset /{name}", "missing (see docs/sample-log-format.md)")
        pos, val = f["positions"], f["values"]
        if pos.ndim != 2 or pos.shape[1] != 2:
            raise _err(path, "dataset /positions", f"shape {pos.shape}, expected (N, 2)")
        if val.ndim != 2 or val.shape[1] != len(self.channels):
            raise _err(path, "dataset /values", f"shape {val.shape}, expected (N, {len(self.channels)}) "
                       f"for channels {','.join(self.channels)}")
        if pos.dtype not in _VALID_FLOATS:
            raise _err(path, "dataset /positions", f"dtype {pos.dtype}, expected float32 or float64")
        if val.dtype not in _VALID_FLOATS:
            raise _err(path, "dataset /values", f"dtype {val.dtype}, expected float32 or float64")
        rows = min(pos.shape[0], val.shape[0])
        try:
            n = int(a.get("n_committed", rows))
        except (TypeError, ValueError):
            raise _err(path, "attribute n_committed", f"is {a.get('n_committed')!r}, expected an integer") from None
        if pos.shape[0] != val.shape[0] and "n_committed" not in a:
            raise _err(path, "dataset /values", f"{val.shape[0]} rows but /positions has {pos.shape[0]}")
        if n < 0 or n > rows:
            raise _err(path, "attribute n_committed", f"is {n} but the datasets hold {rows} rows: "
                       "the file is truncated")
        self.n_samples = n
        self.value_dtype = val.dtype
        self.position_dtype = pos.dtype
        self._has_round = "round" in f
        if self._has_round:
            r = f["round"]
            if r.ndim != 1 or r.shape[0] < n or r.dtype.kind not in "iu":
                raise _err(path, "dataset /round", f"shape {r.shape} dtype {r.dtype}, expected ({n},) integers")
        if n == 0:
            ends = np.zeros(0, np.int64)
        elif "rounds/end" in f:
            ends = np.asarray(f["rounds/end"][...], dtype=np.int64)
            ends = ends[ends <= n]
            if ends.size and (np.any(np.diff(ends) < 0)):
                raise _err(path, "dataset /rounds/end", "must be non-decreasing")
            if not ends.size or ends[-1] != n:
                ends = np.append(ends, n)
        elif self._has_round:
            ends = self._scan_round_ends(f["round"], n)
        else:
            ends = np.array([n], np.int64)
        self.round_ends = ends
        self.feature_names = tuple(sorted(f["features"].keys())) if "features" in f else ()
        for name in self.feature_names:
            d = f["features"][name]
            if not isinstance(d, h5py.Dataset) or d.shape[:1] < (n,):
                raise _err(path, f"dataset /features/{name}", f"shape {getattr(d, 'shape', None)}, expected ({n}, ...)")
        self.has_reference = "reference" in f
        if self.has_reference:
            ref = f["reference"]
            expect = (self.height, self.width, len(self.channels))
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
            if "records" in run:
                recs = [x.decode() if isinstance(x, bytes) else str(x) for x in run["records"][...].tolist()]
                self.round_records = [_json_attr(path, "dataset run/records", x)
                                      for x in recs[: len(self.round_ends)]]

    @staticmethod
    def _scan_round_ends(rds, n):
        ends = []
        prev = None
        for start in range(0, n, DEFAULT_READ_ROWS):
            r = np.asarray(rds[start:min(n, start + DEFAULT_READ_ROWS)], dtype=np.int64)
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
        starts = np.concatenate([[0], self.round_ends[:-1]])
        return [(int(a), int(b)) for a, b in zip(starts, self.round_ends)]

    def iter_chunks(self, *, chunk_size: int = DEFAULT_READ_ROWS, rounds=None,
                    start: int = 0, stop: int | None = None, with_round: bool = True) -> Iterator[LogChunk]:
        """Stream committed samples in chunks of at most ``chunk_size`` rows.

        Parameters
        ----------
        rounds : iterable of int, optional
            Only these rounds (indices into :meth:`round_slices`).
        start, stop : int
            Sample range when ``rounds`` is None.
        with_round : bool
            Read the per-sample round index (``chunk.round``; else None).
        """
        chunk_size = max(int(chunk_size), 1)
        if rounds is None:
            stop = self.n_samples if stop is None else min(int(stop), self.n_samples)
            ranges = [(int(start), stop)]
        else:
            sl = self.round_slices()
            ranges = [sl[int(r)] for r in rounds]
        with _open(self.path) as f:
            pos_d, val_d = f["positions"], f["values"]
            rd = f["round"] if self._has_round else None
            for a, b in ranges:
                for s in range(a, b, chunk_size):
                    e = min(b, s + chunk_size)
                    pos = pos_d[s:e]
                    val = val_d[s:e]
                    if not with_round:
                        rnd = None
                    elif rd is not None:
                        rnd = rd[s:e].astype(np.int64, copy=False)
                    else:
                        rnd = (np.searchsorted(self.round_ends, np.arange(s, e), side="right")).astype(np.int64)
                    yield LogChunk(pos, val, rnd, s)

    def iter_into(self, buffers, *, start: int = 0, stop: int | None = None):
        """Stream committed samples into caller-owned buffers, rotating through them.

        ``buffers`` is a sequence of ``(positions, values)`` array pairs of
        equal row count (the chunk size) and the log's dtypes.  Yields
        ``(positions_view, values_view)`` of the filled rows; a buffer is
        reused ``len(buffers)`` chunks later, so a consumer that overlaps
        work with reading must be done with a chunk by then.  Avoids
        allocating a fresh array per chunk (the hot path of
        :meth:`mcrecon.stats.PixelStats.from_log`).
        """
        rows = buffers[0][0].shape[0]
        stop = self.n_samples if stop is None else min(int(stop), self.n_samples)
        with _open(self.path) as f:
            pos_d, val_d = f["positions"], f["values"]
            for i, s in enumerate(range(int(start), stop, rows)):
                e = min(stop, s + rows)
                pb, vb = buffers[i % len(buffers)]
                pos_d.read_direct(pb, np.s_[s:e], np.s_[0:e - s])
                val_d.read_direct(vb, np.s_[s:e], np.s_[0:e - s])
                yield pb[:e - s], vb[:e - s]

    def read_all(self, *, rounds=None) -> LogChunk:
        """All committed samples (or those of some rounds) in memory."""
        chunks = list(self.iter_chunks(rounds=rounds))
        if not chunks:
            c = len(self.channels)
            return LogChunk(np.zeros((0, 2), self.position_dtype), np.zeros((0, c), self.value_dtype),
                            np.zeros(0, np.int64), 0)
        return LogChunk(np.concatenate([c.positions for c in chunks]),
                        np.concatenate([c.values for c in chunks]),
                        np.concatenate([c.round for c in chunks]), chunks[0].start)

    def read_feature(self, name: str, *, start: int = 0, stop: int | None = None) -> np.ndarray:
        if name not in self.feature_names:
            raise _err(self.path, f"dataset /features/{name}",
                       f"no such feature; valid: {', '.join(self.feature_names) or '(none)'}")
        stop = self.n_samples if stop is None else min(stop, self.n_samples)
        with _open(self.path) as f:
            return f["features"][name][start:stop]

    def reference(self) -> np.ndarray | None:
        """The reference image (H, W, C) float64, or None."""
        if not self.has_reference:
            return None
        with _open(self.path) as f:
            ref = np.asarray(f["reference"][...], dtype=np.float64)
        return ref

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


def _check_arrays(where, positions, values, width, height, n_channels):
    pos = np.asarray(positions)
    val = np.asarray(values)
    if val.ndim == 1 and n_channels == 1:
        val = val[:, None]
    if pos.ndim != 2 or pos.shape[1] != 2:
        raise _err(where, "positions", f"shape {pos.shape}, expected (N, 2)")
    if val.ndim != 2 or val.shape[1] != n_channels:
        raise _err(where, "values", f"shape {val.shape}, expected (N, {n_channels}) to match the channels")
    if pos.shape[0] != val.shape[0]:
        raise _err(where, "values", f"{val.shape[0]} rows but {pos.shape[0]} positions")
    if pos.dtype.kind != "f":
        raise _err(where, "positions", f"dtype {pos.dtype}, expected float32 or float64")
    if val.dtype.kind not in "fiu":
        raise _err(where, "values", f"dtype {val.dtype}, expected float32 or float64")
    if val.dtype.kind != "f":
        val = val.astype(np.float64)
    if pos.dtype == np.float16:
        pos = pos.astype(np.float32)
    if val.dtype == np.float16:
        val = val.astype(np.float32)
    if pos.size:
        bad = ~(np.isfinite(pos).all(axis=1) & (pos[:, 0] >= 0) & (pos[:, 0] < width)
                & (pos[:, 1] >= 0) & (pos[:, 1] < height))
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise _err(where, "positions", f"{int(bad.sum())} sample(s) off the film [0, {width}) x [0, {height}) "
                       f"or non-finite, first at row {k}: {pos[k].tolist()}")
    return pos, val


def _chunks_for(rows, cols):
    return (DEFAULT_CHUNK_ROWS,) if cols is None else (DEFAULT_CHUNK_ROWS, cols)


def write_log(path, positions, values, *, width: int, height: int,
              channels: Sequence[str] = ("R", "G", "B"), rounds=None,
              features: Mapping[str, np.ndarray] | None = None, reference=None,
              metadata: Mapping | None = None) -> Path:
    """Write a new sample log atomically (temporary file, then rename).

    Parameters
    ----------
    path : path-like
    positions : array_like of float, shape (N, 2)
        Film positions: x the column, y the row; pixel (i, j) covers
        [i, i+1) x [j, j+1).  Every position must lie on the film.
    values : array_like of float, shape (N, C)
        Sample values; float32 or float64 is stored as given.  NaN and Inf
        are stored (and counted by ``mcrecon info``); readers apply their
        policy.
    width, height : int
    channels : sequence of str
    rounds : array_like of int, shape (N,), optional
        Round index per sample, non-decreasing.  Default: all round 0.
    features : mapping of str to array_like (N, ...), optional
        Extra per-sample features (e.g. normals, depth).
    reference : array_like (H, W, C), optional
        A reference image stored beside the samples.
    metadata : mapping, optional
        JSON-serialisable: renderer, scene, seed, settings.

    Returns
    -------
    Path
    """
    path = Path(path)
    width, height = int(width), int(height)
    channels = tuple(str(c) for c in channels)
    if width < 1 or height < 1:
        raise _err(path, "width/height", f"{width}x{height}, expected at least 1x1")
    if not channels or len(set(channels)) != len(channels):
        raise _err(path, "channels", f"{channels}: expected distinct non-empty names")
    pos, val = _check_arrays(path, positions, values, width, height, len(channels))
    n = pos.shape[0]
    if rounds is None:
        rnd = np.zeros(n, np.int32)
    else:
        rnd = np.asarray(rounds)
        if rnd.shape != (n,) or rnd.dtype.kind not in "iu":
            raise _err(path, "rounds", f"shape {rnd.shape} dtype {rnd.dtype}, expected ({n},) integers")
        if n and np.any(np.diff(rnd) < 0):
            raise _err(path, "rounds", "must be non-decreasing (samples grouped by round in order)")
        rnd = rnd.astype(np.int32)
    if reference is not None:
        reference = np.asarray(reference)
        if reference.ndim == 2 and len(channels) == 1:
            reference = reference[..., None]
        if reference.shape != (height, width, len(channels)):
            raise _err(path, "reference", f"shape {reference.shape}, expected {(height, width, len(channels))}")
    try:
        meta_json = json.dumps(dict(metadata or {}), sort_keys=True, default=_json_default)
    except TypeError as exc:
        raise _err(path, "metadata", f"not JSON-serialisable: {exc}") from None
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        with h5py.File(tmp, "w") as f:
            f.attrs["format"] = FORMAT_NAME
            f.attrs["format_version"] = FORMAT_VERSION
            f.attrs["width"] = width
            f.attrs["height"] = height
            f.attrs["channels"] = np.array(channels, dtype=h5py.string_dtype())
            f.attrs["metadata_json"] = meta_json
            f.create_dataset("positions", data=pos, maxshape=(None, 2), chunks=_chunks_for(n, 2))
            f.create_dataset("values", data=val, maxshape=(None, val.shape[1]), chunks=_chunks_for(n, val.shape[1]))
            f.create_dataset("round", data=rnd, maxshape=(None,), chunks=_chunks_for(n, None))
            ends = (np.flatnonzero(np.diff(rnd)) + 1).tolist() + [n] if n else []
            f.create_dataset("rounds/end", data=np.asarray(ends, np.int64), maxshape=(None,), chunks=(256,))
            for name, arr in dict(features or {}).items():
                arr = np.asarray(arr)
                if arr.shape[:1] != (n,):
                    raise _err(path, f"features/{name}", f"shape {arr.shape}, expected ({n}, ...)")
                f.create_dataset(f"features/{name}", data=arr, maxshape=(None,) + arr.shape[1:],
                                 chunks=(DEFAULT_CHUNK_ROWS,) + arr.shape[1:])
            if reference is not None:
                f.create_dataset("reference", data=reference.astype(np.float32 if reference.dtype != np.float64 else np.float64))
            f.attrs["n_committed"] = n
        publish(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return path


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def append_log(path, positions, values, *, round_index: int | None = None,
               features: Mapping[str, np.ndarray] | None = None,
               round_record: Mapping | None = None) -> int:
    """Append one round of samples to an existing log and commit it.

    Rows beyond the committed count (left by an interrupted append) are
    discarded first.  The new rows, their round index and the optional
    ``round_record`` (JSON, e.g. times of an adaptive round) are written
    and flushed before ``n_committed`` is updated, so a crash loses at
    most this round.

    Returns
    -------
    int
        The committed sample count after the append.
    """
    path = Path(path)
    log = read_log(path)
    pos, val = _check_arrays(path, positions, values, log.width, log.height, len(log.channels))
    m = pos.shape[0]
    feats = dict(features or {})
    if feats and log.n_samples == 0 and not log.feature_names:
        # A log created before the renderer's first reply learns its features then.
        with _open(path, "r+") as f:
            for name, arr in feats.items():
                arr = np.asarray(arr)
                f.create_dataset(f"features/{name}", shape=(0,) + arr.shape[1:], dtype=arr.dtype,
                                 maxshape=(None,) + arr.shape[1:], chunks=(DEFAULT_CHUNK_ROWS,) + arr.shape[1:])
        log = read_log(path)
    if set(feats) != set(log.feature_names):
        raise _err(path, "features", f"append gives {sorted(feats)}, the log has {list(log.feature_names)}: "
                   "every round must carry the same features")
    n = log.n_samples
    if round_index is None:
        round_index = log.n_rounds
    with _open(path, "r+") as f:
        for name in ("positions", "values", "round"):
            if name in f and f[name].shape[0] != n:
                f[name].resize(n, axis=0)
        if "round" not in f:
            f.create_dataset("round", data=np.zeros(n, np.int32), maxshape=(None,), chunks=(DEFAULT_CHUNK_ROWS,))
        pos = cast_positions(pos, f["positions"].dtype)
        for name, data in (("positions", pos), ("values", val),
                           ("round", np.full(m, round_index, np.int32))):
            d = f[name]
            d.resize(n + m, axis=0)
            d[n:n + m] = data.astype(d.dtype, copy=False)
        for name, arr in feats.items():
            arr = np.asarray(arr)
            d = f["features"][name]
            if arr.shape[:1] != (m,) or arr.shape[1:] != d.shape[1:]:
                raise _err(path, f"features/{name}", f"shape {arr.shape}, expected ({m},) + {d.shape[1:]}")
            d.resize(n, axis=0)
            d.resize(n + m, axis=0)
            d[n:n + m] = arr
        ends = log.round_ends.tolist()
        if "rounds/end" in f:
            del f["rounds/end"]
        ends.append(n + m)
        f.create_dataset("rounds/end", data=np.asarray(ends, np.int64), maxshape=(None,), chunks=(256,))
        if round_record is not None:
            run = f.require_group("run")
            recs = [x.decode() if isinstance(x, bytes) else str(x) for x in run["records"][...].tolist()] \
                if "records" in run else []
            recs = recs[: len(ends) - 1]
            recs.append(json.dumps(dict(round_record), default=_json_default, sort_keys=True))
            if "records" in run:
                del run["records"]
            run.create_dataset("records", data=np.array(recs, dtype=h5py.string_dtype()))
        f.flush()
        f.attrs["n_committed"] = n + m
        f.flush()
    return n + m


def update_round_record(path, record: Mapping) -> None:
    """Replace the record of the last committed round (its times once fully known)."""
    with _open(path, "r+") as f:
        run = f.get("run")
        if run is None or "records" not in run or run["records"].shape[0] == 0:
            return
        recs = [x.decode() if isinstance(x, bytes) else str(x) for x in run["records"][...].tolist()]
        recs[-1] = json.dumps(dict(record), default=_json_default, sort_keys=True)
        del run["records"]
        run.create_dataset("records", data=np.array(recs, dtype=h5py.string_dtype()))
        f.flush()


def set_run_settings(path, settings: Mapping) -> None:
    """Store an adaptive run's settings (JSON) in the log, for resuming."""
    with _open(path, "r+") as f:
        f.require_group("run").attrs["settings_json"] = json.dumps(dict(settings), default=_json_default,
                                                                     sort_keys=True)
        f.flush()

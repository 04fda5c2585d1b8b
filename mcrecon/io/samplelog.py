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
import dataclasses
import errno
import fcntl
import json
import os
import threading
import time
from pathlib import Path
from typing import Iterator, Mapping, Sequence

import h5py
import numpy as np

from ..errors import InputError
from ..samples import check_reference, check_samples, lazy_njit, round_ends_of, round_slices
from ._atomic import atomic_path

__all__ = ["cast_positions", "FORMAT_NAME", "FORMAT_VERSION", "FORMAT_MINOR", "SampleLog", "LogChunk", "read_log",
           "write_log", "append_log", "update_round_record", "set_run_settings", "DEFAULT_CHUNK_ROWS",
           "MAX_PIXELS", "log_lock", "lock_path", "live_writer"]

FORMAT_NAME = "mcrecon-sample-log"
FORMAT_VERSION = 1
#: Compatible revision of version 1 written by this module (attribute ``format_minor``;
#: absent means 0).  1: ``/rounds/end`` and ``/run/records`` are resizable and grow by
#: one row per round; row i of ``/run/records`` is round i's record (``null``: none).
#: 2: round records are rows of the compound dataset /run/round_records (one column per
#: known key, a bit mask of the keys present), keys outside the columns in JSON in
#: /run/round_records_extra; /run/records (JSON) is kept for logs that already have it.
FORMAT_MINOR = 2
#: Rows per HDF5 chunk of a log written whole: 65536 samples = 512 KiB of float32 positions.
DEFAULT_CHUNK_ROWS = 1 << 16
#: Rows per chunk of a log that starts small and grows by appended rounds (the adaptive
#: driver's): HDF5 allocates whole chunks, so this bounds the slack of a small log
#: (24 B/sample with float32 RGB: 96 KiB) while keeping large logs fast to stream.
APPEND_CHUNK_ROWS = 1 << 12
#: Rows per chunk of the per-round datasets /rounds/end (8 B/row) and /run/records (16 B/row).
RECORD_CHUNK_ROWS = 1 << 8
#: Stand-in record of a round that has none (keeps /run/records aligned with the rounds).
_NO_RECORD = "null"
#: Columns of /run/round_records written by this module: the keys of the adaptive driver's
#: round records.  ``present`` is a bit mask: bit 0 set = the round has a record, bit k
#: (k >= 1) set = the k-th column after ``present`` holds that key's value.  An absent key
#: reads -1 (integer columns) or NaN (float columns), but only ``present`` says it is absent.
ROUND_RECORD_DTYPE = np.dtype([("present", "<u2"), ("round", "<i8"), ("samples", "<i8"), ("samples_total", "<i8"),
                               ("renderer_seconds", "<f8"), ("toolkit_seconds", "<f8"), ("wall_seconds", "<f8"),
                               ("error", "<f8"), ("eval_seconds", "<f8")])
#: Rows per chunk of /run/round_records: 64 rows of 66 B, about 4 KiB.
ROUND_RECORD_CHUNK_ROWS = 1 << 6
_HAS_RECORD = 1
#: Group holding a dataset being converted to a resizable one (see _ensure_resizable).
_CONVERT = "_convert"
#: Rows per read when streaming (a multiple of the chunk rows).
DEFAULT_READ_ROWS = 1 << 20
_VALID_FLOATS = (np.float32, np.float64)
#: Largest film a log may describe (width * height): refused before anything is allocated.
MAX_PIXELS = 1 << 31
#: Fletcher-32 checksum on every chunked dataset this module creates (variable-length string
#: datasets excepted: HDF5 filters only fixed-size types).  A damaged chunk fails to read.
_CHECKSUM = {"fletcher32": True}
#: Re-reads of a log a live run is appending to, when a read meets a half-written state.
_LIVE_RETRIES = 20
_LIVE_RETRY_SECONDS = 0.05


def _checksum_for(dtype) -> dict:
    dt = np.dtype(dtype)
    return {} if dt.kind in "OSUV" or h5py.check_string_dtype(dt) is not None or \
        h5py.check_vlen_dtype(dt) is not None else _CHECKSUM


# ------------------------------------------------------------------ exclusive writers
# A writer holds an exclusive flock on ``LOG.lock`` (holding its PID) for as long as it
# writes: the adaptive driver for a whole run, append_log & co. for one call (re-entrant
# within a process).  The kernel releases a flock when its holder dies, so the lock file a
# killed run leaves behind is simply taken over.
_HELD: dict = {}  # realpath of the log -> [fd, depth]
_HELD_GUARD = threading.RLock()


def lock_path(path) -> Path:
    """The lock file of a log: ``LOG.lock`` beside it."""
    return Path(str(path) + ".lock")


def _read_pid(fd) -> int | None:
    try:
        text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
        return int(text) if text.isdigit() else None
    except OSError:
        return None


def _acquire(path, wait: float) -> int:
    lp = lock_path(path)
    deadline = time.monotonic() + wait
    while True:
        try:
            lp.parent.mkdir(parents=True, exist_ok=True)  # a new log's directory (write_log makes it too)
            fd = os.open(lp, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as exc:
            raise _err(path, "lock", f"cannot create the lock file {lp} ({exc.strerror or exc}); a run needs "
                       "a writable directory beside its log") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            pid = _read_pid(fd)
            os.close(fd)
            if time.monotonic() < deadline:
                time.sleep(0.02)
                continue
            who = f"process {pid}" if pid else "another process"
            raise _err(path, "lock", f"the log is being written by {who} (lock {lp}): a second run or resume "
                       "on it is refused; wait for that run to end or stop it") from None
        try:  # a holder that released unlinks the file: we must hold the file that is at lp
            same = os.stat(lp).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if not same:
            os.close(fd)
            continue
        # A PID left in the file belongs to a killed holder (a live one would hold the flock).
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        return fd


@contextlib.contextmanager
def log_lock(path, *, wait: float = 0.5):
    """Hold the exclusive writer lock of a log (``LOG.lock``, with this process's PID).

    Re-entrant within a process.  Another process's lock is waited for at
    most ``wait`` seconds, then refused with an :class:`InputError` naming
    the holder's PID; a lock file left by a killed process is taken over.
    """
    key = os.path.realpath(path)
    with _HELD_GUARD:
        held = _HELD.get(key)
        if held is not None:
            held[1] += 1
        else:
            _HELD[key] = [_acquire(path, wait), 1]
    try:
        yield
    finally:
        with _HELD_GUARD:
            held = _HELD[key]
            held[1] -= 1
            if held[1] == 0:
                del _HELD[key]
                with contextlib.suppress(OSError):
                    os.unlink(lock_path(path))  # unlinked while locked: see _acquire
                os.close(held[0])


def live_writer(path) -> int | None:
    """PID of another live process holding the writer lock of ``path`` (-1 if unknown), or None."""
    if os.path.realpath(path) in _HELD:
        return None
    try:
        fd = os.open(lock_path(path), os.O_RDONLY)
    except OSError:
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError:
            return _read_pid(fd) or -1
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


def _detail(exc) -> str:
    return " ".join(str(exc).split())  # one line: h5py's messages carry newlines


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


@lazy_njit(cache=True, nogil=True)
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
    for attempt in range(_LIVE_RETRIES + 1):
        try:
            # No HDF5 file locking: writers exclude each other with log_lock, and readers
            # (info, denoise) must see a log while a run appends to it.
            return h5py.File(path, mode, locking=False)
        except (OSError, RuntimeError, ValueError, KeyError) as exc:
            failure, pid = exc, live_writer(path)
        if pid is None or mode != "r" or attempt == _LIVE_RETRIES:
            break
        time.sleep(_LIVE_RETRY_SECONDS)  # a run is half-way through an append: open again
    detail = _detail(failure)
    if pid is not None:
        raise _err(path, "file", f"could not be opened while process {pid} is writing it ({detail}); try again")
    if mode != "r" and isinstance(failure, OSError) and (
            failure.errno in (errno.EACCES, errno.EPERM, errno.EROFS)
            or "ermission" in detail or "Read-only file system" in detail):
        raise _err(path, "file", f"cannot be opened for writing ({detail}); the log is intact with every "
                   "committed round: make it writable and resume the run")
    kind = _file_kind(path)
    if kind == "hdf5":
        raise _err(path, "file", f"not a readable HDF5 file (truncated or damaged: {detail}); regenerate it")
    looks = f": it is {kind}" if kind else f" (truncated or another format: {detail})"
    raise _err(path, "file", f"not a readable HDF5 file{looks}; {_ACCEPTED_INPUTS}")


#: What the commands reading a file take, for the message about a file that is none of them.
_ACCEPTED_INPUTS = ("expected an HDF5 sample log (.h5, from a renderer or `mcrecon render-log`: "
                    "docs/sample-log-format.md); `mcrecon denoise` also takes a pixel-statistics EXR whose path "
                    "ends in .exr (mean, variance, count: docs/pixel-statistics-inputs.md)")

_SIGNATURES = ((b"\x89HDF\r\n\x1a\n", "hdf5"), (b"v/1\x01", "an OpenEXR image"),
               (b"\x89PNG\r\n\x1a\n", "a PNG image"), (b"\xff\xd8\xff", "a JPEG image"),
               (b"#?RADIANCE", "a Radiance HDR image"), (b"#?RGBE", "a Radiance HDR image"),
               (b"II*\x00", "a TIFF image"), (b"MM\x00*", "a TIFF image"), (b"PK\x03\x04", "a zip archive"))


def _file_kind(path) -> str | None:
    """What a file that h5py cannot open looks like, from its first bytes: "hdf5" (an HDF5 signature at
    offset 0 or at a user-block offset 512, 1024...: damaged), "an OpenEXR image", "a text file"...,
    or None (unknown)."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
            f.seek(0, os.SEEK_END)
            size = f.tell()
            offset = 512
            while offset < min(size, 1 << 20):  # the HDF5 signature after a user block
                f.seek(offset)
                if f.read(8) == _SIGNATURES[0][0]:
                    return "hdf5"
                offset *= 2
    except OSError:
        return None
    if not head:
        return "an empty file (0 bytes)"
    for magic, kind in _SIGNATURES:
        if head.startswith(magic):
            return kind
    try:
        head.decode("utf-8")
    except UnicodeDecodeError as exc:
        if exc.start < len(head) - 4:  # not only a character cut at the end of the block read
            return None
    return "a text file" if all(c >= 32 or c in b"\t\n\r" for c in head[:256]) else None


_H5_ERRORS = (OSError, RuntimeError, KeyError, ValueError, TypeError, IndexError, OverflowError)


def _bad_rows(d, s: int, e: int) -> tuple[int, int]:
    """The first chunk-aligned row range of [s, e) of ``d`` that fails to read (else (s, e))."""
    c = d.chunks[0] if d.chunks else max(e - s, 1)
    for a in range(s - s % c, e, c):
        b = min(a + c, d.shape[0])
        try:
            d[a:b]
        except _H5_ERRORS:
            return max(a, s), b
    return s, e


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


def _json_attr(path, field, raw):
    try:
        return json.loads(raw.decode() if isinstance(raw, bytes) else str(raw))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise _err(path, field, f"not valid JSON ({exc})") from None


def _int_attr(v) -> int:
    """An integer attribute: any HDF5 integer type, a scalar or a one-element array.

    Raises TypeError for anything else (a float such as 8.5 or 8.0, a string,
    a bool, several elements): ``int()`` would read 8.5 as 8 and "8" as 8.
    """
    arr = np.asarray(v)
    if arr.size != 1 or arr.dtype.kind not in "iu":
        raise TypeError(f"{v!r} is not an integer")
    return int(arr.reshape(()))


def _str_list(v) -> tuple[str, ...]:
    arr = np.atleast_1d(v)
    return tuple(x.decode() if isinstance(x, bytes) else str(x) for x in arr.tolist())


@dataclasses.dataclass(frozen=True)
class _Header:
    width: int
    height: int
    channels: tuple
    n: int  # committed samples
    rows: int  # rows of /positions and /values (>= n)
    position_dtype: np.dtype
    value_dtype: np.dtype
    format_minor: int
    positions: h5py.Dataset
    values: h5py.Dataset


def _read_header(path, f) -> _Header:
    """Validate the root attributes and the shapes of /positions and /values.

    Reads attributes and dataset metadata only (no samples, no per-round
    datasets): what an append needs, in time independent of the log's size.
    """
    attrs = f.attrs
    have = set(attrs.keys())  # one listing; then read only what is there
    a = {k: attrs[k] for k in ("format", "format_version", "format_minor", "width", "height", "channels",
                               "n_committed") if k in have}
    fmt = a.get("format")
    if fmt is not None and (fmt.decode() if isinstance(fmt, bytes) else str(fmt)) != FORMAT_NAME:
        raise _err(path, "attribute format", f"is {fmt!r}, expected {FORMAT_NAME!r}")
    ver = a.get("format_version")
    if ver is None:
        raise _err(path, "attribute format_version", f"missing; expected {FORMAT_VERSION} "
                   "(is this an mcrecon sample log? see docs/sample-log-format.md)")
    try:
        ver = _int_attr(ver)
    except (TypeError, ValueError):
        raise _err(path, "attribute format_version", f"is {ver!r}, expected the integer {FORMAT_VERSION}") from None
    if ver != FORMAT_VERSION:
        raise _err(path, "attribute format_version", f"is {ver}, this mcrecon reads version {FORMAT_VERSION}")
    try:
        minor = _int_attr(a.get("format_minor", 0))  # any compatible revision is readable
    except (TypeError, ValueError):
        raise _err(path, "attribute format_minor", f"is {a.get('format_minor')!r}, expected an integer") from None
    for key in ("width", "height", "channels"):
        if key not in a:
            raise _err(path, f"attribute {key}", "missing (see docs/sample-log-format.md)")
    try:
        width, height = _int_attr(a["width"]), _int_attr(a["height"])
    except (TypeError, ValueError):
        raise _err(path, "attribute width/height", "expected integers") from None
    if width < 1 or height < 1:
        raise _err(path, "attribute width/height", f"{width}x{height}, expected at least 1x1")
    if width * height > MAX_PIXELS:
        raise _err(path, "attribute width/height", f"{width}x{height} = {width * height} pixels, beyond the "
                   f"{MAX_PIXELS} pixels mcrecon can hold images of")
    try:
        channels = _str_list(a["channels"])
    except (TypeError, ValueError, UnicodeDecodeError) as exc:
        raise _err(path, "attribute channels", f"expected an array of strings ({_detail(exc)})") from None
    if not channels or len(set(channels)) != len(channels):
        raise _err(path, "attribute channels", f"{channels}: expected distinct non-empty names")
    pos, val = f.get("positions"), f.get("values")
    for name, d in (("positions", pos), ("values", val)):
        if not isinstance(d, h5py.Dataset):
            raise _err(path, f"dataset /{name}", "missing (see docs/sample-log-format.md)")
    if pos.ndim != 2 or pos.shape[1] != 2:
        raise _err(path, "dataset /positions", f"shape {pos.shape}, expected (N, 2)")
    if val.ndim != 2 or val.shape[1] != len(channels):
        raise _err(path, "dataset /values", f"shape {val.shape}, expected (N, {len(channels)}) "
                   f"for channels {','.join(channels)}")
    if pos.dtype not in _VALID_FLOATS:
        raise _err(path, "dataset /positions", f"dtype {pos.dtype}, expected float32 or float64")
    if val.dtype not in _VALID_FLOATS:
        raise _err(path, "dataset /values", f"dtype {val.dtype}, expected float32 or float64")
    rows = min(pos.shape[0], val.shape[0])
    try:
        n = _int_attr(a.get("n_committed", rows))
    except (TypeError, ValueError):
        raise _err(path, "attribute n_committed", f"is {a.get('n_committed')!r}, expected an integer") from None
    if pos.shape[0] != val.shape[0] and "n_committed" not in a:
        raise _err(path, "dataset /values", f"{val.shape[0]} rows but /positions has {pos.shape[0]}")
    if n < 0 or n > rows:
        raise _err(path, "attribute n_committed", f"is {n} but the datasets hold {rows} rows: "
                   "the file is truncated")
    return _Header(width, height, channels, n, rows, pos.dtype, val.dtype, minor, pos, val)


def _read_ds(path, d, name: str, s: int = 0, e: int | None = None):
    """Rows [s, e) of dataset ``d`` (``/name``); a failed read is a one-line InputError."""
    e = d.shape[0] if e is None else e
    try:
        return d[s:e]
    except _H5_ERRORS as exc:
        raise _read_error(path, name, d, s, e, exc) from None


def _strings(arr) -> list[str]:
    """Decode the elements of a string dataset slice (bytes or str) to str."""
    return [x.decode() if isinstance(x, bytes) else str(x) for x in np.asarray(arr, dtype=object).ravel().tolist()]


_ROW_TYPE = []  # the HDF5 type of ROUND_RECORD_DTYPE, made once


def _row_type():
    if not _ROW_TYPE:
        _ROW_TYPE.append(h5py.h5t.py_create(ROUND_RECORD_DTYPE))
    return _ROW_TYPE[0]


def _record_columns(path, d) -> tuple[np.dtype, tuple[str, ...]]:
    """Validate a /run/round_records dataset; return its dtype and value columns in bit order."""
    if not isinstance(d, h5py.Dataset) or d.ndim != 1:
        raise _err(path, "dataset /run/round_records", f"shape {getattr(d, 'shape', None)}, expected (R,) "
                   "compound rows (see docs/sample-log-format.md)")
    if d.id.get_type() == _row_type():
        # This module's layout.  (Converting an HDF5 compound type to a numpy dtype, as
        # Dataset.dtype does, costs more than the rest of an append's record.)
        return ROUND_RECORD_DTYPE, ROUND_RECORD_DTYPE.names[1:]
    dt = d.dtype
    names = dt.names
    if not names or "present" not in names:
        raise _err(path, "dataset /run/round_records", f"dtype {dt}, expected a compound with an integer "
                   "field 'present' (see docs/sample-log-format.md)")
    cols = tuple(n for n in names if n != "present")
    bad = [n for n in names if dt[n].shape != () or dt[n].kind not in ("iu" if n == "present" else "iuf")]
    if bad or len(cols) >= 8 * dt["present"].itemsize:
        raise _err(path, "dataset /run/round_records", f"dtype {dt}: fields must be scalar integers or floats, "
                   "one bit of 'present' per field")
    return dt, cols


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
    rows = _read_ds(path, d, "run/round_records", 0, min(n_rounds, d.shape[0]))
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
    out = np.empty(idx.size, np.int64)
    try:
        fspace = d.id.get_space()
        fspace.select_elements(np.asarray(idx, np.uint64).reshape(-1, 1))
        d.id.read(h5py.h5s.create_simple((idx.size,)), fspace, out, mtype=h5py.h5t.NATIVE_INT64)
    except _H5_ERRORS as exc:
        raise _read_error(path, name, d, int(idx[0]), int(idx[-1]) + 1, exc) from None
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
            ends = np.asarray(_read_ds(path, d, "rounds/end"), dtype=np.int64)
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
            self.round_records = _read_round_records(path, run, len(self.round_ends))

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
        with _Reader(self.path) as f:
            for a, b in ranges:
                for s in range(a, b, chunk_size):
                    e = min(b, s + chunk_size)
                    pos = f.read("positions", s, e)
                    val = f.read("values", s, e)
                    if not with_round:
                        rnd = None
                    elif self._has_round:
                        rnd = f.read("round", s, e).astype(np.int64, copy=False)
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
        with _Reader(self.path) as f:
            for i, s in enumerate(range(int(start), stop, rows)):
                e = min(stop, s + rows)
                pb, vb = buffers[i % len(buffers)]
                yield f.read("positions", s, e, out=pb), f.read("values", s, e, out=vb)

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


def _check_arrays(where, positions, values, width, height, n_channels):
    """Samples as the log stores them: the shared validation (NaN/Inf values are stored, readers apply their policy)."""
    pos, val, _ = check_samples(positions, values, width=width, height=height, n_channels=n_channels,
                                where=str(where))
    return pos, val


def _checked_arrays(where, positions, values, width, height, n_channels):
    """Arrays the caller validated (``append_log(..., checked=True)``): shapes and dtypes only, O(1).

    What check_samples returns is C-contiguous float32 or float64, (N, 2) and
    (N, C); arrays that are not (the caller's claim cannot hold) get the full
    check of :func:`_check_arrays`.
    """
    pos, val = np.asarray(positions), np.asarray(values)
    if val.ndim == 1 and n_channels == 1:
        val = val[:, None]
    ok = (pos.ndim == 2 and pos.shape[1] == 2 and val.ndim == 2 and val.shape == (pos.shape[0], n_channels)
          and pos.dtype in (np.float32, np.float64) and val.dtype in (np.float32, np.float64)
          and pos.flags.c_contiguous and val.flags.c_contiguous)
    if not ok:
        return _check_arrays(where, positions, values, width, height, n_channels)
    return pos, val


def _chunk_rows(n: int) -> int:
    """Chunk rows for sample datasets starting with ``n`` rows.

    A log written whole gets large chunks (fast streaming); one that starts
    small, like the adaptive driver's empty log, grows by appended rounds
    and gets small chunks, since HDF5 allocates every chunk in full.
    """
    return DEFAULT_CHUNK_ROWS if n >= DEFAULT_CHUNK_ROWS else APPEND_CHUNK_ROWS


def _chunks_for(rows, cols):
    c = _chunk_rows(rows)
    return (c,) if cols is None else (c, cols)


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
    if width * height > MAX_PIXELS:
        raise _err(path, "width/height", f"{width}x{height} = {width * height} pixels, beyond the {MAX_PIXELS} "
                   "pixels mcrecon can hold images of")
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
    with log_lock(path), atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            f.attrs["format"] = FORMAT_NAME
            f.attrs["format_version"] = FORMAT_VERSION
            f.attrs["format_minor"] = FORMAT_MINOR
            f.attrs["width"] = width
            f.attrs["height"] = height
            f.attrs["channels"] = np.array(channels, dtype=h5py.string_dtype())
            f.attrs["metadata_json"] = meta_json
            f.create_dataset("positions", data=pos, maxshape=(None, 2), chunks=_chunks_for(n, 2), **_CHECKSUM)
            f.create_dataset("values", data=val, maxshape=(None, val.shape[1]), chunks=_chunks_for(n, val.shape[1]),
                             **_CHECKSUM)
            f.create_dataset("round", data=rnd, maxshape=(None,), chunks=_chunks_for(n, None), **_CHECKSUM)
            ends = round_ends_of(rnd)
            f.create_dataset("rounds/end", data=np.asarray(ends, np.int64), maxshape=(None,),
                             chunks=(RECORD_CHUNK_ROWS,), **_CHECKSUM)
            for name, arr in dict(features or {}).items():
                arr = np.asarray(arr)
                if arr.shape[:1] != (n,):
                    raise _err(path, f"features/{name}", f"shape {arr.shape}, expected ({n}, ...)")
                f.create_dataset(f"features/{name}", data=arr, maxshape=(None,) + arr.shape[1:],
                                 chunks=(_chunk_rows(n),) + arr.shape[1:], **_checksum_for(arr.dtype))
            if reference is not None:
                f.create_dataset("reference", data=reference.astype(np.float32 if reference.dtype != np.float64
                                                                    else np.float64), **_CHECKSUM)
            f.attrs["n_committed"] = np.int64(n)
    return path


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def _committed_rows(ends: np.ndarray, n: int) -> int:
    """How many leading rows of /rounds/end (or of its tail) are committed rounds.

    An interrupted append leaves at most its own row past the committed ones:
    the new end (> n) or, when the disk filled before its value was written,
    the fill value 0 (found on a full disk: [2048, 4096, 0] with
    n_committed = 4096).  Trailing rows above ``n`` or below their
    predecessor are not committed.
    """
    k = int(ends.shape[0])
    while k > 0 and (ends[k - 1] > n or (k > 1 and ends[k - 1] < ends[k - 2])):
        k -= 1
    return k


def _committed_rounds(path, f, n: int) -> tuple[int, list[int]]:
    """Committed rounds of /rounds/end as a reader counts them, reading only its tail.

    Returns ``(keep, extra)``: the first ``keep`` rows of /rounds/end are
    committed rounds, and ``extra`` ([] or [n]) is a last round the reader
    infers because those rows do not end at ``n``.  The reader's round count
    is ``keep + len(extra)``.  Without /rounds/end the rounds come from
    /round (a one-time scan, for logs from other writers).
    """
    if n == 0:
        return 0, []
    if "rounds/end" not in f:
        if "round" in f:
            return 0, SampleLog._scan_round_ends(f["round"], n).tolist()
        return 0, [n]
    d = f["rounds/end"]
    if not isinstance(d, h5py.Dataset) or d.ndim != 1 or d.dtype.kind not in "iu":
        raise _err(path, "dataset /rounds/end", f"shape {getattr(d, 'shape', None)}, expected (R,) integers")
    # Rows are non-decreasing; uncommitted rows (an interrupted append) lie past n at the end.
    hi = d.shape[0]
    keep = 0
    block = 64
    while hi > 0:
        lo = max(0, hi - block)
        tail = np.asarray(d[lo:hi], np.int64)
        if tail[0] <= n:
            keep = lo + _committed_rows(tail, n)
            break
        hi, block = lo, block * 4
    last = int(d[keep - 1]) if keep else None
    return keep, ([] if last == n else [n])


def _ensure_resizable(f, name: str, keep: int, chunk_rows: int, *, dtype=None, head=None, fillvalue=None):
    """Return ``f[name]`` resizable along axis 0, copying it into one if it is not.

    Logs from other writers, and /run/records of logs written before
    format_minor 1, hold fixed-size datasets.  Such a dataset is copied once
    (its first ``keep`` rows, after the rows ``head``) into a chunked,
    unlimited one built under ``/_convert``, flushed, and only then swapped
    in under the original name, so a crash during the copy leaves the
    original intact (the leftover is discarded by the next append).
    """
    d = f[name]
    if d.chunks is not None and d.maxshape[0] is None and head is None:
        return d
    tmp = f"{_CONVERT}/{name}"
    if tmp in f:
        del f[tmp]
    head = [] if head is None else list(head)
    shape = (len(head) + keep,) + d.shape[1:]
    new = f.create_dataset(tmp, shape=shape, dtype=dtype or d.dtype, maxshape=(None,) + d.shape[1:],
                           chunks=(chunk_rows,) + d.shape[1:], fillvalue=fillvalue, **_checksum_for(dtype or d.dtype))
    if head:
        new[:len(head)] = np.array(head, dtype=object if new.dtype.kind == "O" else new.dtype)
    for s in range(0, keep, DEFAULT_READ_ROWS):
        e = min(keep, s + DEFAULT_READ_ROWS)
        block = d[s:e]
        if new.dtype.kind == "O":
            block = np.array(_strings(block), dtype=object)
        new[len(head) + s:len(head) + e] = block
    for k, v in d.attrs.items():
        new.attrs[k] = v
    f.flush()
    del f[name]
    f.move(tmp, name)
    del f[_CONVERT]
    return f[name]


def _recover_conversions(f) -> None:
    """Finish or discard a conversion a crash interrupted (see _ensure_resizable)."""
    if _CONVERT not in f:
        return
    left = []
    f[_CONVERT].visititems(lambda k, v: left.append(k) if isinstance(v, h5py.Dataset) else None)
    for k in left:
        if k not in f:  # the original was already unlinked: the copy is complete
            f.move(f"{_CONVERT}/{k}", k)
    del f[_CONVERT]


def _record_json(path, record) -> str:
    try:  # compact separators: a record is stored once per round, as large as a small round's samples
        return json.dumps(dict(record), default=_json_default, sort_keys=True, separators=(",", ":"))
    except (TypeError, ValueError) as exc:
        raise _err(path, "round_record", f"not JSON-serialisable: {exc}") from None


def _blank_row(dtype) -> np.ndarray:
    """A /run/round_records row (shape (1,)) of a round without record: present 0, -1 / NaN elsewhere."""
    row = np.zeros(1, dtype)
    for name in dtype.names:
        if name != "present":
            kind = dtype[name].kind
            row[name] = np.nan if kind == "f" else (-1 if kind == "i" else 0)
    return row


def _fits(value, dt: np.dtype) -> bool:
    """Whether ``value`` is stored exactly in a column of type ``dt`` and reads back as the same JSON value."""
    if dt.kind in "iu":
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
            return False  # a bool or a float in an integer column would come back as an int
        info = np.iinfo(dt)
        return info.min <= int(value) <= info.max
    if isinstance(value, (float, np.float32, np.float16)):  # float64 is a float; not longdouble
        x = dt.type(value)
        return float(x) == float(value) or (x != x and value != value)
    return False


def _split_record(record, dtype) -> tuple[np.ndarray, str | None]:
    """A record as a row of a /run/round_records dataset of ``dtype`` and the JSON of the other keys.

    A key goes to its column when there is one and the value is stored
    exactly with its JSON type (an int in an integer column, a float in a
    float column); every other key goes to the JSON (None when none do).
    """
    row = _blank_row(dtype)
    cols = [n for n in dtype.names if n != "present"]
    present, extra = _HAS_RECORD, {}
    for key, value in dict(record).items():
        k = cols.index(key) if isinstance(key, str) and key in cols else -1
        if k >= 0 and _fits(value, dtype[key]):
            row[key] = value
            present |= 1 << (k + 1)
        else:
            extra[key] = value
    row["present"] = present
    if not extra:
        return row, None
    return row, json.dumps(extra, default=_json_default, sort_keys=True, separators=(",", ":"))


def _write_round_record(f, run, d, i: int, rec, *, n_rows: int) -> None:
    """Write round ``i``'s record (or, for ``rec`` None, its no-record row) in the format_minor 2 layout.

    ``d`` is ``/run/round_records`` (validated) or None to create it.  It
    gets ``n_rows`` rows: in an append ``n_rows == i + 1``, so rows an
    interrupted append left past row ``i`` are dropped; an update passes
    at least the rows it has and rewrites row ``i`` only.
    ``/run/round_records_extra`` gets row ``i`` only if the record has
    keys outside the columns (rows past its end read as none), is cut to
    ``n_rows`` rows, and loses row ``i``'s old extra keys if the record
    has none.
    """
    if d is None:
        dt = ROUND_RECORD_DTYPE
        d = run.create_dataset("round_records", shape=(0,), dtype=dt, maxshape=(None,),
                               chunks=(ROUND_RECORD_CHUNK_ROWS,), fillvalue=_blank_row(dt)[0], **_CHECKSUM)
    else:
        dt, _ = _record_columns(None, d)
        if d.chunks is None or d.maxshape[0] is not None:  # other writers' fixed-size datasets: converted once
            d = _ensure_resizable(f, "run/round_records", min(d.shape[0], n_rows), ROUND_RECORD_CHUNK_ROWS,
                                  fillvalue=_blank_row(dt)[0])
    if d.shape[0] != n_rows:
        d.resize(n_rows, axis=0)  # grown rows read as the fill value: no record
    row, extra = (_blank_row(dt), None) if rec is None else _split_record(rec, dt)
    ex = run.get("round_records_extra")
    if ex is not None:
        ex = _ensure_resizable(f, "run/round_records_extra", min(ex.shape[0], n_rows), RECORD_CHUNK_ROWS,
                               dtype=h5py.string_dtype("utf-8"))
        if ex.shape[0] > n_rows:
            ex.resize(n_rows, axis=0)  # rows of an interrupted append
        top = min(ex.shape[0], i + 1)
        # Whether row i has extra keys.  Reading the last rows before writing a string also
        # loads their global-heap collection, so the string joins it instead of opening a
        # fresh 4 KiB collection per append.
        low = max(0, top - (64 if extra is not None else 1))
        had = top == i + 1 and bool(_strings(ex[low:top])[-1])
    if extra is not None:
        if ex is None:
            ex = run.create_dataset("round_records_extra", shape=(0,), dtype=h5py.string_dtype("utf-8"),
                                    maxshape=(None,), chunks=(RECORD_CHUNK_ROWS,))
        if ex.shape[0] <= i:
            ex.resize(i + 1, axis=0)
        ex[i] = extra
    elif ex is not None and had:
        if ex.shape[0] == i + 1:
            ex.resize(i, axis=0)  # drop the old extra keys (no empty string written: it costs a heap object)
        else:
            ex[i] = ""
    fspace = d.id.get_space()
    fspace.select_hyperslab((i,), (1,))
    mtype = _row_type() if dt == ROUND_RECORD_DTYPE else h5py.h5t.py_create(dt)
    d.id.write(h5py.h5s.create_simple((1,)), fspace, row, mtype=mtype)


def append_log(path, positions, values, *, round_index: int | None = None,
               features: Mapping[str, np.ndarray] | None = None,
               round_record: Mapping | None = None, checked: bool = False) -> int:
    """Append one round of samples to an existing log and commit it.

    Rows beyond the committed count (left by an interrupted append) are
    discarded first, in every dataset.  The new rows, their round index,
    the round's end in ``/rounds/end`` and the optional ``round_record``
    (a JSON-serialisable mapping, e.g. times of an adaptive round) are
    written and flushed before ``n_committed`` is updated, so a crash loses
    at most this round.

    Records go to a row of ``/run/round_records`` (format_minor 2), with
    keys outside its columns in ``/run/round_records_extra``; a log that
    already keeps JSON records in ``/run/records`` (written before
    format_minor 2) continues in that layout.

    The file is opened once and only its attributes, dataset shapes and
    last rows are read: the cost is proportional to the round, not to the
    log.  A fixed-size dataset (other writers, or ``/run/records`` of logs
    written before format_minor 1) is converted to a resizable one once.

    ``checked=True`` says the caller has already validated these arrays
    for this log (:func:`mcrecon.samples.check_samples` with its width,
    height and channels: contiguous float arrays, positions finite and on
    the film): only their shapes and dtypes are checked again, not every
    sample.  The adaptive driver passes it for the replies it validated
    itself, so a round is validated and committed in one pass over it; the
    file written is the same as without it.

    Returns
    -------
    int
        The committed sample count after the append.
    """
    path = Path(path)
    feats = {str(k): np.asarray(v) for k, v in dict(features or {}).items()}
    rec = None if round_record is None else _record_json(path, round_record)
    with log_lock(path):
        try:
            return _append(path, pos_in=positions, val_in=values, round_index=round_index, feats=feats, rec=rec,
                           round_record=round_record, checked=checked)
        except _H5_ERRORS as exc:
            if isinstance(exc, InputError):
                raise
            # Keep the failed write's h5py objects alive (through its traceback's frames):
            # freeing them makes HDF5 retry the close that could not flush, which crashes
            # the process (SIGSEGV after ENOSPC, measured).  See _write_error.
            _FAILED_WRITES.append(exc)
            raise _write_error(path, exc) from None


#: Exceptions of appends that failed inside HDF5, kept for the life of the process.
_FAILED_WRITES: list = []


def _write_error(path, exc) -> InputError:
    """A failed write (a full disk, an I/O error): one line; the committed rounds are untouched.

    The error is marked ``write_failed``: HDF5 keeps the file open
    internally when its close cannot flush, and its clean-up at
    interpreter exit can then crash the process (measured: HDF5 2.0 via
    h5py 3.x, SIGSEGV after ENOSPC), and so can freeing the h5py objects
    of the failed append, which are therefore kept alive.  The ``mcrecon``
    program ends such a process with ``os._exit`` after its one-line
    message (:func:`mcrecon.cli.run`); a Python program that catches the
    error should do the same once it has saved what it needs.
    """
    detail = " ".join(str(getattr(exc, "strerror", None) or _detail(exc)).split())
    err = _err(path, "append", f"writing the round failed ({detail}); it was not committed and every round "
               "committed before is kept: fix the cause (disk space, permissions) and resume the run")
    err.write_failed = True
    return err


#: Space kept free beyond the round's chunks: HDF5 metadata (B-tree nodes, the
#: records' rows, attributes) written by one append.
APPEND_SPACE_MARGIN = 256 * 1024


def _check_free_space(path, n: int, m: int, chunk: int, row_bytes: int) -> None:
    """Refuse an append the file system has no room for, before the first write.

    The estimate counts every chunk the append writes (the partial last one
    and the new ones, at full size: HDF5 allocates whole chunks) plus
    :data:`APPEND_SPACE_MARGIN`.  Running out of space inside HDF5 is
    survivable (the round is not committed) but leaves HDF5 unable to
    close the file; refusing first is the clean path.  A file system that
    cannot tell (no ``statvfs``) is not checked.
    """
    if m <= 0:
        return
    try:
        st = os.statvfs(Path(path).parent)
    except (OSError, AttributeError):
        return
    free = st.f_bavail * st.f_frsize
    chunks = -(-(n + m) // chunk) - n // chunk
    need = chunks * chunk * row_bytes + APPEND_SPACE_MARGIN
    if free < need:
        err = _err(path, "append", f"not enough free disk space for the round ({m} samples need about "
                   f"{need / 2**20:.1f} MiB, {free / 2**20:.1f} MiB free); it was not written and every round "
                   "committed before is kept: free some space and resume the run")
        raise err


def _append(path, *, pos_in, val_in, round_index, feats, rec, round_record, checked=False) -> int:  # noqa: C901
    positions, values = pos_in, val_in
    with _open(path, "r+") as f:
        _recover_conversions(f)
        h = _read_header(path, f)
        if checked:
            pos, val = _checked_arrays(path, positions, values, h.width, h.height, len(h.channels))
        else:
            pos, val = _check_arrays(path, positions, values, h.width, h.height, len(h.channels))
        m, n = pos.shape[0], h.n
        # ---- validate everything before the first write: a refused append leaves the file as it was
        fgroup = f.get("features")
        have = sorted(fgroup.keys()) if fgroup is not None else []
        new_features = bool(feats) and n == 0 and not have  # learnt from the renderer's first reply
        if not new_features and set(feats) != set(have):
            raise _err(path, "features", f"append gives {sorted(feats)}, the log has {have}: "
                       "every round must carry the same features")
        for name, arr in feats.items():
            d = None if new_features else fgroup[name]
            if d is not None and (not isinstance(d, h5py.Dataset) or d.shape[0] < n):
                raise _err(path, f"dataset /features/{name}",
                           f"shape {getattr(d, 'shape', None)}, expected ({n}, ...)")
            if arr.shape[:1] != (m,) or (d is not None and arr.shape[1:] != d.shape[1:]):
                expect = "(...)" if d is None else str(d.shape[1:])
                raise _err(path, f"features/{name}", f"shape {arr.shape}, expected ({m},) + {expect}")
        if "round" in f:
            r = f["round"]
            if not isinstance(r, h5py.Dataset) or r.ndim != 1 or r.shape[0] < n or r.dtype.kind not in "iu":
                raise _err(path, "dataset /round", f"shape {getattr(r, 'shape', None)}, expected ({n},) integers")
        keep, extra = _committed_rounds(path, f, n)
        n_rounds = keep + len(extra)
        # The round's label in /round must exceed the last committed one (readers refuse a /round
        # that contradicts /rounds/end): by default the number of committed rounds, or more.
        last = int(_read_rows(path, f["round"], "round", np.array([n - 1]))[0]) if n and "round" in f else None
        if round_index is None:
            round_index = n_rounds if last is None else max(n_rounds, last + 1)
        elif last is not None and int(round_index) <= last:
            raise _err(path, "round_index", f"{round_index}, but the last committed round's label in /round is "
                       f"{last}: a new round needs a larger one (leave it out to get {max(n_rounds, last + 1)})")
        run = f.get("run")
        rows = run.get("round_records") if run is not None else None
        recs = run.get("records") if run is not None and rows is None else None  # the JSON layout (minor < 2)
        if rows is not None:
            _record_columns(path, rows)  # refuses a malformed dataset before the first write
            ex = run.get("round_records_extra")
            if ex is not None and (not isinstance(ex, h5py.Dataset) or ex.ndim != 1 or ex.dtype.kind not in "OSU"):
                raise _err(path, "dataset /run/round_records_extra",
                           f"shape {getattr(ex, 'shape', None)}, expected (R,) strings")
        if recs is not None and (not isinstance(recs, h5py.Dataset) or recs.ndim != 1):
            raise _err(path, "dataset /run/records", f"shape {getattr(recs, 'shape', None)}, expected (R,) strings")

        # ---- samples: truncate to n, extend by m
        chunk = h.positions.chunks[0] if h.positions.chunks else _chunk_rows(n)
        _check_free_space(path, n, m, chunk, pos.dtype.itemsize * 2 + h.values.dtype.itemsize * val.shape[1] + 4
                          + sum(a.dtype.itemsize * int(np.prod(a.shape[1:])) for a in feats.values()))
        pos = cast_positions(pos, h.position_dtype)
        if "round" not in f:  # reads as round 0 for the committed samples (fill value, no data written)
            rd = f.create_dataset("round", shape=(n,), dtype=np.int32, maxshape=(None,), chunks=(chunk,),
                                  fillvalue=0, **_CHECKSUM)
            if n_rounds > 1:  # label the rounds /rounds/end gives, or /round would contradict it (written once)
                ends = np.concatenate([np.asarray(f["rounds/end"][:keep], np.int64), extra]) \
                    if "rounds/end" in f else np.asarray(extra, np.int64)
                for k, (a, b) in enumerate(round_slices(ends)):
                    for c in range(a, b if k else a, DEFAULT_READ_ROWS):
                        rd[c:min(b, c + DEFAULT_READ_ROWS)] = k
        columns = [("positions", pos), ("values", val), ("round", np.full(m, round_index, np.int32))]
        if new_features:
            for name, arr in feats.items():
                f.create_dataset(f"features/{name}", shape=(0,) + arr.shape[1:], dtype=arr.dtype,
                                 maxshape=(None,) + arr.shape[1:], chunks=(chunk,) + arr.shape[1:],
                                 **_checksum_for(arr.dtype))
        columns += [(f"features/{name}", arr) for name, arr in feats.items()]
        for name, data in columns:
            d = _ensure_resizable(f, name, n, chunk)
            if d.shape[0] != n + m:
                d.resize(n + m, axis=0)
            if m:
                d[n:n + m] = data.astype(d.dtype, copy=False)

        # ---- per-round rows: /rounds/end and the records grow by one row (plus a round the reader inferred)
        new_ends = extra + [n + m]
        if "rounds/end" not in f:
            f.create_dataset("rounds/end", shape=(0,), dtype=np.int64, maxshape=(None,), chunks=(RECORD_CHUNK_ROWS,),
                             **_CHECKSUM)
        d = _ensure_resizable(f, "rounds/end", keep, RECORD_CHUNK_ROWS, dtype=np.int64)
        d.resize(keep + len(new_ends), axis=0)
        d[keep:] = new_ends
        minor = FORMAT_MINOR
        if recs is not None:
            # A log of format_minor 0 or 1 that keeps JSON records continues in that layout
            # (older mcrecon versions keep reading its records).
            # Row i holds round i's record: pad rounds without one (a log's first, written
            # whole, or records of old logs that skipped rounds) with null at the front.
            minor = 1
            have_rows = min(recs.shape[0], n_rounds)
            head = [_NO_RECORD] * (n_rounds - have_rows)
            if have_rows:
                # Load the heap collection of the last record, so the new record joins it
                # instead of opening a fresh 4 KiB global-heap collection per append.
                recs[have_rows - 1]
            recs = _ensure_resizable(f, "run/records", have_rows, RECORD_CHUNK_ROWS,
                                     dtype=h5py.string_dtype("utf-8"), head=head or None)
            recs.resize(n_rounds + 1, axis=0)
            recs[n_rounds] = _NO_RECORD if rec is None else rec
        elif rows is not None or rec is not None:
            # Row i of /run/round_records is round i's record; rows of earlier rounds
            # (none before the first record) read as the fill value: no record.
            _write_round_record(f, f.require_group("run"), rows, n_rounds, round_record, n_rows=n_rounds + 1)
        if h.format_minor < minor:
            f.attrs["format_minor"] = minor  # the layout now follows it
        f.flush()
        _commit(f, n + m)
    return n + m


def _commit(f, n: int) -> None:
    """Set ``n_committed`` (one in-place attribute write when it is a scalar int64) and flush."""
    a = f.attrs
    if "n_committed" in a:
        cur = a.get_id("n_committed")
        if cur.dtype == np.int64 and cur.shape in ((), (1,)):
            a.modify("n_committed", n)
            f.flush()
            return
    a["n_committed"] = np.int64(n)  # absent, or another type (other writers): written once as int64
    f.flush()


def update_round_record(path, record: Mapping) -> None:
    """Replace the record of the last committed round (its times once fully known).

    Overwrites that one row of ``/run/round_records`` in place (and its row
    of ``/run/round_records_extra`` if either record has keys outside the
    columns), or of ``/run/records`` in a log that keeps JSON records.
    Does nothing if the log holds no records.
    """
    path = Path(path)
    rec = _record_json(path, record)  # refuses what is not JSON-serialisable, in either layout
    with log_lock(path):
        try:
            _update_round_record(path, record, rec)
        except _H5_ERRORS as exc:
            if isinstance(exc, InputError):
                raise
            raise _write_error(path, exc) from None


def _update_round_record(path, record, rec) -> None:
    with _open(path, "r+") as f:
        run = f.get("run")
        rows = run.get("round_records") if run is not None else None
        d = run.get("records") if run is not None and rows is None else None
        if rows is not None:
            _record_columns(path, rows)
            if rows.shape[0] == 0:
                return
        elif not isinstance(d, h5py.Dataset) or d.ndim != 1 or d.shape[0] == 0:
            return
        h = _read_header(path, f)
        keep, extra = _committed_rounds(path, f, h.n)
        n_rounds = keep + len(extra)
        if rows is not None:
            # Row i is round i's record; rows past the committed rounds (an interrupted
            # append) are left for the next append to drop.
            if n_rounds:
                _write_round_record(f, run, rows, n_rounds - 1, record, n_rows=max(rows.shape[0], n_rounds))
                f.flush()
            return
        # Row i is round i's record; logs written before format_minor 1 may hold fewer rows
        # than rounds (the last row is then the last round's).
        i = min(d.shape[0], n_rounds) - 1
        if i < 0:
            return
        d[i] = rec
        f.flush()


def set_run_settings(path, settings: Mapping) -> None:
    """Store an adaptive run's settings (JSON) in the log, for resuming."""
    with log_lock(path), _open(path, "r+") as f:
        f.require_group("run").attrs["settings_json"] = json.dumps(dict(settings), default=_json_default,
                                                                     sort_keys=True)
        f.flush()

"""The sample log's format: constants, the header, opening a file, errors that name it.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import time
import zlib
from pathlib import Path

import h5py
import numpy as np

from ..core.samples import lazy_njit
from .lock import _err, live_writer

__all__ = ['cast_positions', 'FORMAT_NAME', 'FORMAT_VERSION', 'FORMAT_MINOR', 'LogChunk', 'DEFAULT_CHUNK_ROWS',
           'MAX_PIXELS', 'declared_samples']

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
#: Group holding, per checksummed dataset, the digest of the committed rows of its partly filled
#: last chunk, written and flushed before an append rewrites that chunk (see _tail_rows).
_TAIL = "_tail"
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


def _detail(exc) -> str:
    return " ".join(str(exc).split())  # one line: h5py's messages carry newlines


@dataclasses.dataclass(eq=False)
class LogChunk:
    """A contiguous run of samples read from a log."""

    positions: np.ndarray  # (n, 2)
    values: np.ndarray  # (n, C)
    round: np.ndarray  # (n,) int
    start: int  # index of the first sample in the log
    features: dict = dataclasses.field(default_factory=dict)  # name -> (n, ...), the features asked for

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
                    "docs/sample-log-format.md); `mcrecon reconstruct` also takes a pixel-statistics EXR whose path "
                    "ends in .exr (mean, variance, count: docs/pixel-statistics-inputs.md)")


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


def declared_samples(path) -> int:
    """The number of samples a file in the sample-log format declares, from its metadata alone.

    A renderer's reply is checked with this before it is read: a reply declaring 200 M rows
    (unwritten chunks cost no disk) is refused without reading it.  Raises :class:`InputError`
    naming the file where it is not such a file.
    """
    try:
        with _open(path) as f:
            return _read_header(path, f).n
    except _H5_ERRORS as exc:
        raise _err(Path(path), "file", f"malformed: {' '.join(str(exc).split())}") from None


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


def _tail_digest(raw: bytes) -> np.ndarray:
    """The digest /_tail keeps of a chunk's committed bytes: CRC-32 and Adler-32, as two int64.

    Two independent 32-bit checks (64 bits in all, stronger than the
    chunk's own Fletcher-32), at about 0.5 ms per MiB: a 65 536-row chunk
    is digested in a fraction of the time HDF5 takes to rewrite it.
    """
    return np.array([zlib.crc32(raw), zlib.adler32(raw)], np.int64)


def _tail_info(f, name: str, d):
    """``(a, b, same, digest, old)`` noted in /_tail for ``d`` (``/name``) if they describe it now, else None.

    Rows [a, b) of ``d`` are the committed rows of its partly filled last
    chunk when an append (or a record's update) began to rewrite it: rows
    [a, same) are rewritten with the same bytes, whose digest is noted;
    rows [same, b) are replaced (a record's update), their old bytes are
    noted in ``old``.  The notes (attribute ``name`` of /_tail: int64
    start, stop, same_stop, n_committed, digest; ``name:old``: uint8)
    describe ``d`` now while the file's ``n_committed`` is the one they
    were made in, and only for chunks spanning every column.
    """
    t = f.get(_TAIL)
    if not isinstance(t, h5py.Group) or d.chunks is None or tuple(d.chunks[1:]) != tuple(d.shape[1:]):
        return None
    try:
        at = t.attrs
        note = np.asarray(at[name])
        if note.shape != (6,) or note.dtype.kind not in "iu":
            return None
        a, b, same, nc = (int(x) for x in note[:4])
        old = np.asarray(at[f"{name}:old"], np.uint8).tobytes() if same < b else b""
        cur = _int_attr(f.attrs["n_committed"])
    except (KeyError, TypeError, ValueError, OSError):
        return None
    c = d.chunks[0]
    if nc != cur or a < 0 or a % c or not 0 < b - a < c or not a <= same <= b or b > d.shape[0]:
        return None
    return a, b, same, note[4:].astype("<i8"), old


def _raw_chunk(d, a: int) -> bytes | None:
    """The stored bytes of the chunk of ``d`` at row ``a`` (unchecked), for chunks stored with Fletcher-32
    alone (what this module writes: the bytes are the rows, then the checksum); else None."""
    try:
        dcpl = d.id.get_create_plist()
        if [dcpl.get_filter(i)[0] for i in range(dcpl.get_nfilters())] != [h5py.h5z.FILTER_FLETCHER32]:
            return None
        mask, raw = d.id.read_direct_chunk((a,) + (0,) * (d.ndim - 1))
    except (AttributeError, *_H5_ERRORS):
        return None
    full = d.dtype.itemsize * int(np.prod(d.chunks))
    return bytes(raw[:full]) if mask == 0 and len(raw) == full + 4 else None


def _tail_rows(f, name: str, d, s: int, e: int, *, short: bool = False):
    """Rows [s, e) of ``d`` (``/name``) after a read failed: those of a torn last chunk from its stored bytes.

    HDF5 writes into a partly filled chunk by rewriting it whole (its
    committed rows with the same bytes) and then its Fletcher-32 checksum;
    a kill in the middle leaves the committed rows' bytes intact and the
    checksum wrong.  So when /_tail's notes describe ``d`` now (see
    :func:`_tail_info`) and the chunk's stored bytes of rows [a, same) have
    the digest kept there, they are the committed rows; anything else
    (damage) gets None, so it is reported.  Rows past ``b`` are not
    committed: with ``short`` the rows are cut there (a caller that reads a
    dataset whole and keeps its committed rows), else such a request gets
    None.
    """
    info = _tail_info(f, name, d)
    if info is None:
        return None
    a, b, same, digest, old = info
    if e > b:
        if not short:
            return None
        e = b
    if e <= a or s >= e:
        return None
    row_bytes = d.dtype.itemsize * int(np.prod(d.shape[1:]))
    raw = _raw_chunk(d, a)
    if raw is None or len(old) != (b - same) * row_bytes:
        return None
    kept = raw[:(same - a) * row_bytes]
    if not np.array_equal(_tail_digest(kept), digest):
        return None
    rows = np.frombuffer(kept + old, dtype=d.dtype).reshape((b - a,) + d.shape[1:])
    try:
        head = d[s:a] if s < a else None
    except _H5_ERRORS:
        return None
    tail = rows[max(s, a) - a:e - a].copy()
    return tail if head is None else np.concatenate([head, tail])


def _read_slice(f, name: str, d, s: int, e: int, *, short: bool = False):
    """``d[s:e]`` (``d`` is ``/name``), reading a torn last chunk's committed rows from /_tail; else raises."""
    try:
        return d[s:e]
    except _H5_ERRORS:
        rows = _tail_rows(f, name, d, s, e, short=short)
        if rows is None:
            raise
        return rows


_SIGNATURES = ((b"\x89HDF\r\n\x1a\n", "hdf5"), (b"v/1\x01", "an OpenEXR image"),
               (b"\x89PNG\r\n\x1a\n", "a PNG image"), (b"\xff\xd8\xff", "a JPEG image"),
               (b"#?RADIANCE", "a Radiance HDR image"), (b"#?RGBE", "a Radiance HDR image"),
               (b"II*\x00", "a TIFF image"), (b"MM\x00*", "a TIFF image"), (b"PK\x03\x04", "a zip archive"))


def _labels_are_indices(rnd) -> bool:
    """Whether non-decreasing round labels are 0, 1, 2, ... (each sample's label its round's index), which
    readers derive from /rounds/end: /round would repeat it in 4 bytes per sample."""
    return not rnd.size or (int(rnd[0]) == 0 and bool(np.all(np.diff(rnd) <= 1)))


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")

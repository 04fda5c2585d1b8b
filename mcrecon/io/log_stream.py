"""Writing a new sample log piece by piece: memory bounded by a piece, not by the log.

:func:`stream_log` creates a log of a known number of samples and lets the
caller write its rows in any number of pieces (:meth:`LogStream.write`), so
a renderer that produces a frame's samples block by block never holds them
all.  The file is the one :func:`mcrecon.io.write_log` writes from the same
samples held whole: the same attributes, datasets, dtypes, HDF5 chunk
shapes and checksums, every row equal.  It is published only when every
row is written (temporary file, then rename); an exception inside the block
leaves no file.
"""

from __future__ import annotations

import contextlib
import json
import shutil
from pathlib import Path
from typing import Iterator, Mapping, Sequence

import h5py
import numpy as np

from ._atomic import atomic_path
from .lock import _err, log_lock
from ..core.requests import check_sampler
from ..core.samples import check_samples
from .logformat import (APPEND_CHUNK_ROWS, DEFAULT_CHUNK_ROWS, FORMAT_MINOR, FORMAT_NAME, FORMAT_VERSION, MAX_PIXELS,
                        RECORD_CHUNK_ROWS, _CHECKSUM, _checksum_for, _json_default, cast_positions)

__all__ = ["LogStream", "stream_log"]


def _check_arrays(where, positions, values, width, height, n_channels):
    """Samples as the log stores them: the shared validation (NaN/Inf values are stored, readers apply their policy)."""
    pos, val, _ = check_samples(positions, values, width=width, height=height, n_channels=n_channels,
                                where=str(where))
    return pos, val


def _chunk_rows(n: int) -> int:
    """Chunk rows for sample datasets starting with ``n`` rows.

    A log written whole gets large chunks (fast streaming); one that starts
    small, like the adaptive driver's empty log, grows by appended rounds
    and gets small chunks, since HDF5 allocates every chunk in full.
    """
    return DEFAULT_CHUNK_ROWS if n >= DEFAULT_CHUNK_ROWS else APPEND_CHUNK_ROWS


def check_header(path: Path, width, height, channels, metadata) -> tuple[int, int, tuple, str]:
    """``(width, height, channels, metadata JSON)`` of a new log, or the one-line error naming the field."""
    width, height = int(width), int(height)
    channels = tuple(str(c) for c in channels)
    if width < 1 or height < 1:
        raise _err(path, "width/height", f"{width}x{height}, expected at least 1x1")
    if width * height > MAX_PIXELS:
        raise _err(path, "width/height", f"{width}x{height} = {width * height} pixels, beyond the {MAX_PIXELS} "
                   "pixels mcrecon can hold images of")
    if not channels or len(set(channels)) != len(channels):
        raise _err(path, "channels", f"{channels}: expected distinct non-empty names")
    try:
        meta_json = json.dumps(dict(metadata or {}), sort_keys=True, default=_json_default)
    except TypeError as exc:
        raise _err(path, "metadata", f"not JSON-serialisable: {exc}") from None
    return width, height, channels, meta_json


def write_header(f, width: int, height: int, channels: tuple, meta_json: str, sampler: str | None = None) -> None:
    """The root attributes of a new log, before its datasets (``n_committed`` comes last, when complete).

    ``sampler`` (checked by :func:`~mcrecon.core.requests.check_sampler`): written as the attribute
    ``sampler`` where given; a log without it reads as ``independent``."""
    f.attrs["format"] = FORMAT_NAME
    f.attrs["format_version"] = FORMAT_VERSION
    f.attrs["format_minor"] = FORMAT_MINOR
    f.attrs["width"] = width
    f.attrs["height"] = height
    f.attrs["channels"] = np.array(channels, dtype=h5py.string_dtype())
    f.attrs["metadata_json"] = meta_json
    if sampler is not None:
        f.attrs["sampler"] = sampler


def sample_chunks(n: int, cols) -> tuple:
    """HDF5 chunk shape of a per-sample dataset of a new ``n``-row log (``cols``: its other axes)."""
    return (_chunk_rows(n),) + tuple(cols)


def check_reference(path: Path, reference, width: int, height: int, n_channels: int):
    """A reference image as a new log stores it ((H, W, C), a 2-D image for one channel), or None."""
    if reference is None:
        return None
    reference = np.asarray(reference)
    if reference.ndim == 2 and n_channels == 1:
        reference = reference[..., None]
    if reference.shape != (height, width, n_channels):
        raise _err(path, "reference", f"shape {reference.shape}, expected {(height, width, n_channels)}")
    return reference


def write_reference(f, reference) -> None:
    """``/reference``: float64 kept, any other dtype as float32."""
    if reference is not None:
        f.create_dataset("reference", data=reference.astype(np.float32 if reference.dtype != np.float64
                                                            else np.float64), **_CHECKSUM)


class LogStream:
    """A new log being written piece by piece (from :func:`stream_log`).

    Attributes
    ----------
    n : int
        The log's samples.
    written : int
        Rows written so far (pieces must come in order, without gaps).
    """

    def __init__(self, f, path: Path, n: int, width: int, height: int, n_channels: int, features: dict):
        self._f, self.path, self.n = f, path, n
        self.width, self.height, self.n_channels = width, height, n_channels
        self._features = features
        self.written = 0

    def write(self, positions, values, *, features: Mapping[str, np.ndarray] | None = None) -> None:
        """Write the next rows: ``positions`` (m, 2), ``values`` (m, C), and every declared feature (m, ...).

        Rows are checked as :func:`mcrecon.io.write_log` checks a whole log
        (positions on the film, the shapes); positions are stored in the
        dtype declared, without moving any into the next pixel.
        """
        f, path = self._f, self.path
        pos, val = _check_arrays(path, positions, values, self.width, self.height, self.n_channels)
        m, a = pos.shape[0], self.written
        if a + m > self.n:
            raise _err(path, "rows", f"{a} written and {m} more, beyond the {self.n} samples declared")
        feats = dict(features or {})
        if set(feats) != set(self._features):
            raise _err(path, "features", f"a piece gives {sorted(feats)}, the log declares {sorted(self._features)}")
        for name, arr in feats.items():
            arr = np.asarray(arr)
            if arr.shape != (m,) + self._features[name][0]:
                raise _err(path, f"features/{name}", f"shape {arr.shape}, expected {(m,) + self._features[name][0]}")
            feats[name] = arr
        d = f["positions"]
        d[a:a + m] = cast_positions(pos, d.dtype)
        f["values"][a:a + m] = val.astype(f["values"].dtype, copy=False)
        for name, arr in feats.items():
            d = f[f"features/{name}"]
            d[a:a + m] = arr.astype(d.dtype, copy=False)
        self.written = a + m


def _check_disk(path: Path, n: int, dtypes: dict, c: int, feats: dict) -> None:
    """Refuse, in one line and before anything is rendered or written, a log larger than the free space
    of its folder: a streamed log's memory is bounded by a block, so its size is bounded only by the disk,
    and a budget of 10^12 samples would otherwise write until the disk is full."""
    per = 2 * dtypes["position_dtype"].itemsize + c * dtypes["value_dtype"].itemsize
    per += sum(int(np.prod(shape, dtype=np.int64)) * dt.itemsize for shape, dt in feats.values())
    need = float(n) * per
    try:
        free = shutil.disk_usage(path.parent if str(path.parent) else Path(".")).free
    except OSError:
        return  # the folder's own error comes from the write, naming it
    if need > free:
        raise _err(path, "samples", f"{n} samples need {need / 2**30:.3g} GiB on disk, more than the "
                   f"{free / 2**30:.3g} GiB free in {path.parent}; lower --spp or --size, or write the log elsewhere")


@contextlib.contextmanager
def stream_log(path, n: int, *, width: int, height: int, channels: Sequence[str] = ("R", "G", "B"),
               position_dtype=np.float32, value_dtype=np.float32,
               features: Mapping[str, tuple] | None = None, reference=None,
               metadata: Mapping | None = None, sampler: str | None = None) -> Iterator[LogStream]:
    """Create a log of ``n`` samples (all round 0) and yield a :class:`LogStream` to write its rows.

    Parameters
    ----------
    path : path-like
    n : int
        Samples the log holds; the block must write exactly that many.
    width, height, channels, reference, metadata, sampler
        As :func:`mcrecon.io.write_log`.
    position_dtype, value_dtype : float32 or float64
        Stored dtypes of the positions and values.
    features : mapping of str to (shape, dtype), optional
        Per-sample features: each one's shape after the sample axis
        (``(3,)`` for an albedo, ``()`` for a scalar) and stored dtype.

    Notes
    -----
    Write pieces whose boundaries fall on multiples of
    :data:`~mcrecon.io.logformat.DEFAULT_CHUNK_ROWS` (but the last): then no
    HDF5 chunk is read back and rewritten.
    """
    path = Path(path)
    width, height, channels, meta_json = check_header(path, width, height, channels, metadata)
    sampler = None if sampler is None else check_sampler(sampler, where=str(path))
    n = int(n)
    if n < 0:
        raise _err(path, "n", f"{n}, expected 0 or more samples")
    dtypes = {}
    for field, dt in (("position_dtype", position_dtype), ("value_dtype", value_dtype)):
        dtypes[field] = np.dtype(dt)
        if dtypes[field] not in (np.float32, np.float64):
            raise _err(path, field, f"{dt!r}, expected float32 or float64")
    feats = {}
    for name, spec in dict(features or {}).items():
        shape, dt = spec
        dt = np.dtype(dt)
        if dt.kind not in "fiub":
            raise _err(path, f"features/{name}", f"dtype {dt}, expected a numeric dtype (integer, float or bool)")
        feats[str(name)] = (tuple(int(k) for k in shape), dt)
    reference = check_reference(path, reference, width, height, len(channels))
    _check_disk(path, n, dtypes, len(channels), feats)
    with log_lock(path), atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            write_header(f, width, height, channels, meta_json, sampler)
            f.create_dataset("positions", shape=(n, 2), dtype=dtypes["position_dtype"], maxshape=(None, 2),
                             chunks=sample_chunks(n, (2,)), **_CHECKSUM)
            c = len(channels)
            f.create_dataset("values", shape=(n, c), dtype=dtypes["value_dtype"], maxshape=(None, c),
                             chunks=sample_chunks(n, (c,)), **_CHECKSUM)
            f.create_dataset("rounds/end", data=np.asarray([n] if n else [], np.int64), maxshape=(None,),
                             chunks=(RECORD_CHUNK_ROWS,), **_CHECKSUM)
            for name, (shape, dt) in feats.items():
                f.create_dataset(f"features/{name}", shape=(n,) + shape, dtype=dt, maxshape=(None,) + shape,
                                 chunks=sample_chunks(n, shape), **_checksum_for(dt))
            write_reference(f, reference)
            stream = LogStream(f, path, n, width, height, c, feats)
            yield stream
            if stream.written != n:
                raise _err(path, "rows", f"{stream.written} written, {n} declared")
            f.attrs["n_committed"] = np.int64(n)


"""Writing sample logs: create, append a committed round, round records, run settings.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Mapping, Sequence

import h5py
import numpy as np

from ..errors import InputError
from ..core.requests import check_sampler
from ..core.samples import round_ends_of, round_slices
from ._atomic import atomic_path
from ..core.samples import DEFAULT_READ_ROWS
from .lock import _err, log_lock
from .logformat import (FORMAT_MINOR,
                        RECORD_CHUNK_ROWS, ROUND_RECORD_CHUNK_ROWS, ROUND_RECORD_DTYPE, _CHECKSUM,
                        _CONVERT, _H5_ERRORS, _HAS_RECORD, _NO_RECORD, _checksum_for, _committed_rows, _detail,
                        _json_default, _labels_are_indices, _open, _read_header, _read_slice, _record_columns,
                        _row_type, _strings, cast_positions)
from .reader import SampleLog, _read_rows
from ._tail import _save_tail
from .log_stream import _check_arrays, _chunk_rows, check_header, check_reference, write_header, write_reference

__all__ = ['write_log', 'append_log', 'update_round_record', 'set_run_settings']

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


def _chunks_for(rows, cols):
    c = _chunk_rows(rows)
    return (c,) if cols is None else (c, cols)


def write_log(path, positions, values, *, width: int, height: int,
              channels: Sequence[str] = ("R", "G", "B"), rounds=None,
              features: Mapping[str, np.ndarray] | None = None, reference=None,
              metadata: Mapping | None = None, sampler: str | None = None) -> Path:
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
        Round label per sample, non-decreasing.  Default: all round 0.  Labels
        0, 1, 2, ... are what ``/rounds/end`` already gives, and are not
        stored per sample; other labels (gaps, a first label above 0) are
        kept in ``/round``.
    features : mapping of str to array_like (N, ...), optional
        Extra per-sample features (e.g. normals, depth).
    reference : array_like (H, W, C), optional
        A reference image stored beside the samples.
    metadata : mapping, optional
        JSON-serialisable: renderer, scene, seed, settings.
    sampler : {"independent", "sobol"}, optional
        What each pixel's samples are (:data:`~mcrecon.core.requests.SAMPLERS`), stored as the root
        attribute ``sampler``: ``sobol`` where sample k of a pixel is sample k of its stratified
        sequence, in stream order (the halves then split by prefix blocks,
        :func:`~mcrecon.core.halves.split_halves`).  None writes no attribute (read as ``independent``).

    Returns
    -------
    Path
    """
    path = Path(path)
    width, height, channels, meta_json = check_header(path, width, height, channels, metadata)
    sampler = None if sampler is None else check_sampler(sampler, where=str(path))
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
    reference = check_reference(path, reference, width, height, len(channels))
    with log_lock(path), atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            write_header(f, width, height, channels, meta_json, sampler)
            f.create_dataset("positions", data=pos, maxshape=(None, 2), chunks=_chunks_for(n, 2), **_CHECKSUM)
            f.create_dataset("values", data=val, maxshape=(None, val.shape[1]), chunks=_chunks_for(n, val.shape[1]),
                             **_CHECKSUM)
            ends = round_ends_of(rnd)
            if not _labels_are_indices(rnd):  # else /rounds/end gives every sample's round: no per-sample copy
                f.create_dataset("round", data=rnd, maxshape=(None,), chunks=_chunks_for(n, None), **_CHECKSUM)
            f.create_dataset("rounds/end", data=np.asarray(ends, np.int64), maxshape=(None,),
                             chunks=(RECORD_CHUNK_ROWS,), **_CHECKSUM)
            for name, arr in dict(features or {}).items():
                arr = _feature_array(path, name, arr)
                if arr.shape[:1] != (n,):
                    raise _err(path, f"features/{name}", f"shape {arr.shape}, expected ({n}, ...)")
                f.create_dataset(f"features/{name}", data=arr, maxshape=(None,) + arr.shape[1:],
                                 chunks=(_chunk_rows(n),) + arr.shape[1:], **_checksum_for(arr.dtype))
            write_reference(f, reference)
            f.attrs["n_committed"] = np.int64(n)
    return path


def _feature_array(path, name, arr) -> np.ndarray:
    """A feature as an array of a dtype the reader takes (integer, float, bool), else refused naming it."""
    arr = np.asarray(arr)
    if arr.dtype.kind not in "fiub":
        raise _err(path, f"features/{name}", f"dtype {arr.dtype}, expected a numeric dtype (integer, float or "
                   "bool): one number per component and sample")
    return arr


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
        tail = np.asarray(_read_slice(f, "rounds/end", d, lo, hi, short=True), np.int64)
        if tail[0] <= n:
            keep = lo + _committed_rows(tail, n)
            break
        hi, block = lo, block * 4
    last = int(_read_slice(f, "rounds/end", d, keep - 1, keep)[0]) if keep else None
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
    discarded first, in every dataset.  The new rows, the round's end in
    ``/rounds/end`` (its label ``round_index``, by default the next index,
    goes to ``/round`` only when the log has one or the label is not the
    round's index), and the optional ``round_record``
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
    for this log (:func:`mcrecon.core.samples.check_samples` with its width,
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
    feats = {str(k): _feature_array(path, k, v) for k, v in dict(features or {}).items()}
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


def check_log_fits(path, n: int, n_channels: int, *, where: str, spp: int | None = None,
                   film: str = "--size") -> None:
    """Refuse, before anything is rendered, a log of ``n`` float32 samples that ``path``'s disk cannot take.

    With ``spp`` (``n`` is that many samples per pixel) the advice is one that works: the largest spp
    that fits, or, when even 1 spp does not, a smaller film (``film`` says how to make it smaller: a
    scene file's film is set in the file) or another disk.
    """
    need = 4.0 * n * (2 + n_channels)
    try:
        st = os.statvfs(Path(path).parent)
    except (OSError, AttributeError):  # no such folder (the writer names it), or no statvfs
        return
    free = st.f_bavail * st.f_frsize
    if need > free:
        per_spp = need / spp if spp else None
        if per_spp is None:
            advice = f"lower --spp, or make the film smaller ({film})"
        elif per_spp <= free:
            advice = f"lower --spp to at most {int(free // per_spp)}, or free disk space"
        else:
            advice = (f"even 1 spp needs {per_spp / 2**30:.3g} GiB: make the film smaller ({film}), free disk "
                      "space, or write the log to a larger disk")
        raise InputError(where, "spp", f"{n} samples make a log of {need / 2**30:.3g} GiB, more than the "
                         f"{free / 2**30:.3g} GiB free for {path}; {advice}")


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
        # Without /round the labels are the rounds' indices (/rounds/end gives them): the new round's is n_rounds.
        last = int(_read_rows(path, f["round"], "round", np.array([n - 1]))[0]) if n and "round" in f else None
        if round_index is None:
            round_index = n_rounds if last is None else max(n_rounds, last + 1)
        elif last is not None and int(round_index) <= last:
            raise _err(path, "round_index", f"{round_index}, but the last committed round's label in /round is "
                       f"{last}: a new round needs a larger one (leave it out to get {max(n_rounds, last + 1)})")
        elif "round" not in f and int(round_index) < n_rounds:
            raise _err(path, "round_index", f"{round_index}, but the log holds {n_rounds} committed round(s) "
                       f"labelled 0-{n_rounds - 1}: a new round needs a larger label (leave it out to get {n_rounds})")
        # /round is written only where the labels are not the indices (another writer's labels, a gap)
        labels = "round" in f or int(round_index) != n_rounds
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
        _check_free_space(path, n, m, chunk, pos.dtype.itemsize * 2 + h.values.dtype.itemsize * val.shape[1]
                          + 4 * labels + sum(a.dtype.itemsize * int(np.prod(a.shape[1:])) for a in feats.values()))
        pos = cast_positions(pos, h.position_dtype)
        if labels and "round" not in f:  # reads as round 0 for the committed samples (fill value, no data written)
            rd = f.create_dataset("round", shape=(n,), dtype=np.int32, maxshape=(None,), chunks=(chunk,),
                                  fillvalue=0, **_CHECKSUM)
            if n_rounds > 1:  # label the rounds /rounds/end gives, or /round would contradict it (written once)
                ends = np.concatenate([np.asarray(f["rounds/end"][:keep], np.int64), extra]) \
                    if "rounds/end" in f else np.asarray(extra, np.int64)
                for k, (a, b) in enumerate(round_slices(ends)):
                    for c in range(a, b if k else a, DEFAULT_READ_ROWS):
                        rd[c:min(b, c + DEFAULT_READ_ROWS)] = k
        columns = [("positions", pos), ("values", val)] + ([("round", np.full(m, round_index, np.int32))] if labels
                                                           else [])
        if new_features:
            for name, arr in feats.items():
                f.create_dataset(f"features/{name}", shape=(0,) + arr.shape[1:], dtype=arr.dtype,
                                 maxshape=(None,) + arr.shape[1:], chunks=(chunk,) + arr.shape[1:],
                                 **_checksum_for(arr.dtype))
        columns += [(f"features/{name}", arr) for name, arr in feats.items()]
        ds = [(_ensure_resizable(f, name, n, chunk), data) for name, data in columns]
        # ---- before the first rewrite of a chunk holding committed rows: note their digest (/_tail)
        if "n_committed" not in f.attrs:  # a log from another writer: every row is committed
            f.attrs["n_committed"] = np.int64(n)
        for (name, _), (d, _) in zip(columns, ds):
            _save_tail(path, f, name, n, n, d=d)
        if "rounds/end" in f:
            _save_tail(path, f, "rounds/end", keep, n)
        if rows is not None:
            _save_tail(path, f, "run/round_records", min(rows.shape[0], n_rounds), n)
        f.flush()
        for d, data in ds:
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
                if "n_committed" in f.attrs:  # note the rows the rewrite of the last round's row rewrites
                    _save_tail(path, f, "run/round_records", min(rows.shape[0], n_rounds), h.n,
                               same=n_rounds - 1)
                    f.flush()
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

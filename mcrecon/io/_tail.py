"""Before an append rewrites a chunk holding committed rows: the notes in /_tail (docs/sample-log-format.md).

The reading side (telling a torn chunk from a damaged one) is
:func:`mcrecon.io.logformat._tail_rows`.
"""

from __future__ import annotations

import h5py
import numpy as np

from .logformat import _H5_ERRORS, _TAIL, _tail_digest, _tail_info, _tail_rows
from .reader import _read_error


def _set_attr(attrs, key: str, v) -> None:
    """Attribute ``key`` = ``v``: written in place when it has that shape already (no churn per append)."""
    try:
        attrs.modify(key, v)
    except (TypeError, OSError):
        del attrs[key]
        attrs[key] = v


def _save_tail(path, f, name: str, b: int, n: int, *, same: int | None = None, d=None) -> None:
    """Before a write rewrites the partly filled chunk of ``/name`` holding committed rows [a, b): note them.

    HDF5 writes into a partly filled chunk by rewriting it whole, committed
    rows [a, b) included (with the same bytes), then its Fletcher-32
    checksum.  A kill during that rewrite leaves those bytes intact but the
    checksum wrong, which would make the whole log unreadable.  So
    attribute ``name`` of the group ``/_tail`` gets a, b, ``same``, n and
    the digest of those rows' bytes; the caller flushes before the
    rewrite.  A reader meeting a chunk that fails its checksum then takes
    its stored rows if they have that digest (a torn rewrite, see
    :func:`mcrecon.io.logformat._tail_rows`), and reports it as damaged
    otherwise.  ``same`` < b: rows [same, b) are being replaced
    (a record's update); their old bytes are kept (attribute ``name:old``)
    and only rows [a, same) are digested.

    A chunk that already fails to read while ``/_tail`` describes it
    (a resume after such a kill) is first rewritten whole from its
    committed rows, the notes left as they are.  Costs one read of at most
    a chunk and one attribute per dataset: no sample is written twice.
    ``d`` is ``f[name]`` when the caller has it.
    """
    d = f.get(name) if d is None else d
    if not isinstance(d, h5py.Dataset) or d.chunks is None or tuple(d.chunks[1:]) != tuple(d.shape[1:]) \
            or not d.fletcher32:
        return  # no checksum to fail (or chunks this module does not write)
    c = d.chunks[0]
    b = min(b, d.shape[0])
    a = b - b % c
    if a == b:
        return  # the committed rows end on a chunk boundary: no chunk holding them is rewritten
    same = b if same is None else max(a, min(same, b))
    try:
        rows = d[a:b]
    except _H5_ERRORS as exc:
        info = _tail_info(f, name, d)
        good = _tail_rows(f, name, d, a, b) if info is not None and info[:2] == (a, b) else None
        if good is None:
            raise _read_error(path, name, d, a, b, exc) from None
        _rewrite_chunk(d, a, good)
        return
    raw = np.ascontiguousarray(rows, dtype=d.dtype).tobytes()
    k = (same - a) * (len(raw) // (b - a))
    t = f.get(_TAIL)
    at = (t if isinstance(t, h5py.Group) else f.require_group(_TAIL)).attrs
    _set_attr(at, name, np.concatenate([np.array([a, b, same, n], np.int64), _tail_digest(raw[:k])]))
    if same < b:
        _set_attr(at, f"{name}:old", np.frombuffer(raw[k:], np.uint8))


def _rewrite_chunk(d, a: int, rows: np.ndarray) -> None:
    """Write the chunk of ``d`` at row ``a`` whole: ``rows``, then the fill value (HDF5 reads no torn chunk back)."""
    c = d.chunks[0]
    shape0 = d.shape[0]
    if shape0 < a + c:
        d.resize(a + c, axis=0)
    buf = np.zeros((c,) + d.shape[1:], d.dtype)
    if d.fillvalue is not None:
        buf[...] = d.fillvalue
    buf[:len(rows)] = rows
    d[a:a + c] = buf
    if d.shape[0] != shape0:
        d.resize(shape0, axis=0)

"""``scipy.ndimage.uniform_filter`` over the two image axes, compiled, term for term as scipy computes it.

The planners' neighbourhood statistics (gem's and awr's rare-component floor, the
stratification gain) are box means of a few planes per round; scipy's filter
costs a pass per axis and per plane through its line buffers, plus the numpy
temporaries around it.  :func:`box_mean` gives the same bits (tested against
scipy): along axis 0, then axis 1, a running sum ``t`` over the extended line
(``mode`` 'constant': zeros outside, 'nearest': the edge repeated), first
``((0 + x_-r) + ...) + x_r``, then ``t += x_new - x_old``, each output
``t / size``, the first pass stored as float64.  :func:`box_any` is the
dilation of a boolean plane by the same window, clipped to the film: what
``maximum_filter(x, mode='nearest') > t`` is wherever ``x`` holds no NaN.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["BOX_MODES", "box_mean", "box_any"]

#: The border modes :func:`box_mean` computes (scipy's names).
BOX_MODES = ("constant", "nearest")


@numba.njit(cache=True, nogil=True, inline="always")
def _at(line, k, n, nearest):
    # the extended line's entry k (k may lie outside [0, n))
    if 0 <= k < n:
        return line[k]
    if nearest:
        return line[0] if k < 0 else line[n - 1]
    return 0.0


@numba.njit(cache=True, nogil=True)
def _box_axis0(src, dst, r, nearest):
    # lines along axis 0 of src (H, M): every column's running sum at once, row by row
    h, m = src.shape
    size = 2 * r + 1
    t = np.zeros(m)
    for k in range(-r, r + 1):
        kk = k if 0 <= k < h else ((0 if k < 0 else h - 1) if nearest else -1)
        if kk >= 0:
            for q in range(m):
                t[q] += np.float64(src[kk, q])
        else:
            for q in range(m):
                t[q] += 0.0
    for q in range(m):
        dst[0, q] = t[q] / size
    for i in range(1, h):
        a = i + r
        b = i - r - 1
        ia = a if a < h else (h - 1 if nearest else -1)
        ib = b if b >= 0 else (0 if nearest else -1)
        for q in range(m):
            xa = np.float64(src[ia, q]) if ia >= 0 else 0.0
            xb = np.float64(src[ib, q]) if ib >= 0 else 0.0
            t[q] += xa - xb
            dst[i, q] = t[q] / size


@numba.njit(cache=True, nogil=True)
def _box_axis1(src, dst, r, nearest):
    # lines along axis 1 of src (H, W, C): per row and channel a running sum over the columns
    h, w, c = src.shape
    size = 2 * r + 1
    for i in range(h):
        for ch in range(c):
            line = src[i, :, ch]
            t = 0.0
            for k in range(-r, r + 1):
                t += _at(line, k, w, nearest)
            dst[i, 0, ch] = t / size
            for j in range(1, w):
                t += _at(line, j + r, w, nearest) - _at(line, j - r - 1, w, nearest)
                dst[i, j, ch] = t / size


def _checked(name: str, x: np.ndarray, radius) -> int:
    # the window's half-size (a negative one would sum an empty window), after the planes' shape
    if x.ndim not in (2, 3):
        raise ValueError(f"{name}: (H, W) or (H, W, C) expected, got shape {x.shape}")
    r = int(radius)
    if r < 0:
        raise ValueError(f"{name}: radius {radius!r}; a window half-size >= 0 expected")
    return r


def box_mean(a: np.ndarray, radius: int, mode: str = "constant") -> np.ndarray:
    """``scipy.ndimage.uniform_filter(a.astype(float64), size=(2 radius + 1, 2 radius + 1[, 1]), mode=mode)``, bit for bit.

    Parameters
    ----------
    a : ndarray (H, W) or (H, W, C)
        Any real or boolean dtype, read as float64.
    radius : int
        Half-size of the window (>= 0).
    mode : {'constant', 'nearest'}
        Zeros outside the film (cval 0) or the edge repeated.
    """
    if mode not in BOX_MODES:
        raise ValueError(f"box_mean: mode {mode!r}; valid: {', '.join(BOX_MODES)}")
    x = np.asarray(a)
    r = _checked("box_mean", x, radius)
    if r == 0:
        return np.array(x, dtype=np.float64)
    x3 = np.ascontiguousarray(x if x.ndim == 3 else x[..., None])
    if x3.dtype == np.bool_:
        x3 = x3.astype(np.float64)
    h, w, c = x3.shape
    tmp = np.empty((h, w, c))
    out = np.empty((h, w, c))
    if h and w and c:
        nearest = mode == "nearest"
        _box_axis0(x3.reshape(h, w * c), tmp.reshape(h, w * c), r, nearest)
        _box_axis1(tmp, out, r, nearest)
    return out if x.ndim == 3 else out[..., 0]


@numba.njit(cache=True, nogil=True)
def _any_rows(b, r, out):
    # out[i, q] = any b[k, q] for k in [i - r, i + r] (clipped): the last row set so far, per column q
    h, m = b.shape
    last = np.full(m, -r - 2)
    for k in range(min(r, h - 1) + 1):
        for q in range(m):
            if b[k, q]:
                last[q] = k
    for i in range(h):
        e = i + r
        if i > 0 and e < h:
            for q in range(m):
                if b[e, q]:
                    last[q] = e
        for q in range(m):
            out[i, q] = last[q] >= i - r


@numba.njit(cache=True, nogil=True)
def _any_cols(b, r, out):
    h, w, c = b.shape
    for i in range(h):
        for ch in range(c):
            last = -r - 2  # the last column j with b set, so far
            for j in range(min(r, w - 1) + 1):
                if b[i, j, ch]:
                    last = j
            for j in range(w):
                e = j + r
                if j > 0 and e < w and b[i, e, ch]:
                    last = e
                out[i, j, ch] = last >= j - r


def box_any(b: np.ndarray, radius: int) -> np.ndarray:
    """Whether any entry of the boolean plane(s) ``b`` (H, W[, C]) is set in each pixel's
    ``(2 radius + 1)^2`` window clipped to the film (per channel)."""
    x = np.asarray(b, dtype=np.bool_)
    r = _checked("box_any", x, radius)
    x3 = np.ascontiguousarray(x if x.ndim == 3 else x[..., None])
    tmp = np.empty(x3.shape, np.bool_)
    out = np.empty(x3.shape, np.bool_)
    if x3.size:
        h, w, c = x3.shape
        _any_rows(x3.reshape(h, w * c), r, tmp.reshape(h, w * c))
        _any_cols(tmp, r, out)
    return out if x.ndim == 3 else out[..., 0]

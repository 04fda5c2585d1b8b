"""auto's compiled passes over every candidate's maps at once: channel means, floors and the choice, picks.

Each kernel reads the arrays all candidates share (the denominators, the
pixel means and standard errors) once per row for all of them, the
candidates' own arrays given as a typed list (one compiled kernel for any
number of candidates), and writes into one (K, H, W) array or the picked
image: no per-candidate full-image temporaries (fresh memory costs this
machine more than the arithmetic).
"""

from __future__ import annotations

import numba
import numpy as np
from numba.typed import List

from ...filters.engine import parallel_rows


def _c64(a):
    return None if a is None else np.ascontiguousarray(a, dtype=np.float64)


#: The dtype the candidates' images and estimates are held in from their creation through the selection:
#: float32 halves what the selection holds (19 candidates at 1920 x 1080: 0.95 GB, not 1.9 GB); every
#: kernel reads them into float64 arithmetic (docs/methods/auto.md, "Cost").
STORE = np.float32


def _stored(a: np.ndarray) -> np.ndarray:
    """``a`` as held through the selection: :data:`STORE`, C order; ``a`` in float64 where a finite value
    lies beyond float32's range (it would become infinite: "impossible" to the choice)."""
    with np.errstate(over="ignore"):   # the overflow is what the test below looks for
        s = np.ascontiguousarray(a, dtype=STORE)
    if s.dtype != a.dtype and not _representable(np.ascontiguousarray(a, dtype=np.float64).reshape(-1),
                                                 s.reshape(-1)):
        return np.ascontiguousarray(a, dtype=np.float64)
    return s


@numba.njit(cache=True, nogil=True)
def _representable(a, s):
    # every finite value of a finite in s (its float32 rounding)
    for p in range(a.size):
        if np.isfinite(a[p]) and not np.isfinite(s[p]):
            return False
    return True


def _arrays(arrays) -> List:
    """The candidates' (H, W, C) arrays for the kernels that read all of them in one pass over the rows
    (a typed list: one compiled kernel for any number of candidates, per dtype).  Held as stored
    (:data:`STORE`; float64 where any of them is: a typed list holds one dtype).  Built by cached
    kernels: the typed list's own Python methods compile anew in every process (0.2 s)."""
    dt = np.result_type(*[a.dtype for a in arrays], STORE)
    arrays = [np.ascontiguousarray(a, dtype=dt) for a in arrays]
    out = _list_start(arrays[0])
    for a in arrays[1:]:
        _list_push(out, a)
    return out


@numba.njit(cache=True, nogil=True)
def _list_start(a):
    out = List()
    out.append(a)
    return out


@numba.njit(cache=True, nogil=True)
def _list_push(arrays, a):
    arrays.append(a)


@numba.njit(cache=True, nogil=True)
def _pairwise_block(a, o, n):
    # numpy's pairwise sum of a[o:o + n], n <= 128: below 8 values in order from 0, else eight partial
    # sums combined as ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7)) and the rest in order
    if n < 8:
        t = 0.0
        for p in range(n):
            t += a[o + p]
        return t
    r0, r1, r2, r3 = a[o], a[o + 1], a[o + 2], a[o + 3]
    r4, r5, r6, r7 = a[o + 4], a[o + 5], a[o + 6], a[o + 7]
    p = 8
    while p < n - n % 8:
        r0 += a[o + p]
        r1 += a[o + p + 1]
        r2 += a[o + p + 2]
        r3 += a[o + p + 3]
        r4 += a[o + p + 4]
        r5 += a[o + p + 5]
        r6 += a[o + p + 6]
        r7 += a[o + p + 7]
        p += 8
    t = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while p < n:
        t += a[o + p]
        p += 1
    return t


@numba.njit(cache=True, nogil=True)
def _pairwise_sum(a, o, n):
    # numpy's pairwise sum of a[o:o + n]: above 128 values the sum of its two halves (the first a
    # multiple of 8), recursively -- here by an explicit stack (a recursive function compiled into
    # numba's cache crashed when loaded from it)
    if n <= 128:
        return _pairwise_block(a, o, n)
    fo, fn, st = np.empty(64, np.int64), np.empty(64, np.int64), np.empty(64, np.int64)
    vals = np.empty(64)
    top, nv = 0, 0
    fo[0], fn[0], st[0] = o, n, 0
    while top >= 0:
        m = fn[top]
        if m <= 128:
            vals[nv] = _pairwise_block(a, fo[top], m)
            nv += 1
            top -= 1
            continue
        m2 = m // 2
        m2 -= m2 % 8
        if st[top] == 0:
            st[top] = 1
            fo[top + 1], fn[top + 1], st[top + 1] = fo[top], m2, 0
            top += 1
        elif st[top] == 1:
            st[top] = 2
            fo[top + 1], fn[top + 1], st[top + 1] = fo[top] + m2, m - m2, 0
            top += 1
        else:
            vals[nv - 2] = vals[nv - 2] + vals[nv - 1]
            nv -= 1
            top -= 1
    return vals[0]


@numba.njit(cache=True, nogil=True, inline="always")
def _channel_mean(a, o, c):
    # the mean of a[o:o + c] as auto has always taken a channel mean of its estimates: below 8 channels
    # added in order from the first, then divided by C (np.mean(axis=2) but for a zero sum's sign: numpy
    # starts from +0), from 8 channels numpy's own pairwise sum
    if c >= 8:
        return _pairwise_sum(a, o, c) / c
    t = a[o]
    for ch in range(1, c):
        t += a[o + ch]
    return t / c


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _means_rows(arrays, den, cap, s, v, out, i0, i1):
    # rows [i0, i1) of _means: a row's ratios in one flat loop (vectorised), then the channel means
    # (one signature whether capped or not: each costs a compilation and a load from the cache)
    w, c = out.shape[2], arrays[0].shape[2]
    n = w * c
    buf = np.empty(n)
    for i in range(i0, i1):
        dr, vr = den[i].reshape(n), v[i].reshape(n)
        for k in range(len(arrays)):
            ar = arrays[k][i].reshape(n)
            if cap:
                for q in range(n):
                    x = ar[q]
                    m = s * vr[q]
                    buf[q] = (x if x < m or x != x else m) / dr[q]
            else:
                for q in range(n):
                    buf[q] = ar[q] / dr[q]
            ok = out[k, i]
            for j in range(w):
                ok[j] = _channel_mean(buf, j * c, c)


def _means(arrays: list, den: np.ndarray | None = None, v: np.ndarray | None = None,
           s: float | None = None) -> np.ndarray:
    """``np.mean(a / den, axis=2)`` of every array (K, H, W); with ``s`` of ``np.minimum(a, s * v) / den``.

    One compiled pass over the rows for all of them (``den`` and ``v`` read once, not once per
    candidate).  Bit-identical to numpy from 8 channels; below, the channels added in order from
    the first, as numpy does but for the sign of a zero sum.  A NaN estimate stays NaN through the cap.
    Without ``den`` the means of the arrays themselves (divided by ones: the same values).
    """
    first = arrays[0]
    out = np.empty((len(arrays),) + first.shape[:2])
    den = np.ones(first.shape) if den is None else _c64(den)
    parallel_rows(_means_rows, (_arrays(arrays), den, s is not None, 0.0 if s is None else float(s),
                                den if s is None else _c64(v), out), first.shape[0])
    return out


def _mean_c(a: np.ndarray, den: np.ndarray | None = None) -> np.ndarray:
    """``np.mean(a / den, axis=2)`` (:func:`_means` of one array)."""
    return _means([a], den)[0]


@numba.njit(cache=True, nogil=True, inline="always")
def _sum_channels(buf, c, out_row):
    # out_row[j] = (buf[j c] + buf[j c + 1] + ...) / c, added in order from the first
    for j in range(out_row.size):
        s = buf[j * c]
        for ch in range(1, c):
            s += buf[j * c + ch]
        out_row[j] = s / c


@numba.njit(cache=True, nogil=True)
def _nanmax(a, b):
    # NaN if either is NaN, else the larger (the first of +0 and -0, where np.maximum gives the second:
    # the kernels that compare its result, not store it, use it in place of np.maximum)
    if a != a or b != b:
        return np.nan
    return a if a >= b else b


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _floor_choose_rows(rel, images, y, sd, den, has, z, choice, i0, i1):
    # rows [i0, i1) of _floor_and_choose: per candidate, the squared bias bounds of a row in one flat
    # loop (vectorised), summed per pixel (an empty pixel's bound is 0: its terms 0 / den), the floor
    # applied and the choice updated; y, sd and den read once for all candidates
    K, h, w = rel.shape
    c = y.shape[2]
    n = w * c
    buf = np.empty(n)
    fl = np.empty(w)
    best = np.empty(w)
    for i in range(i0, i1):
        yr, sr, dr = y[i].reshape(n), sd[i].reshape(n), den[i].reshape(n)
        every = True
        for j in range(w):
            every = every and has[i, j]
            best[j] = np.inf
            choice[i, j] = 0
        for k in range(K):
            xr = images[k][i].reshape(n)
            for q in range(n):
                lb = abs(xr[q] - yr[q]) - z * sr[q]
                lb = np.nan if lb != lb else (lb if lb >= 0.0 else 0.0)
                buf[q] = lb * lb / dr[q]
            for j in range(0 if every else w):
                if not has[i, j]:
                    for ch in range(c):
                        buf[j * c + ch] = 0.0 / dr[j * c + ch]
            _sum_channels(buf, c, fl)
            rk = rel[k, i]
            for j in range(w):
                t = _nanmax(rk[j], fl[j])
                rk[j] = t
                if t < best[j]:
                    best[j] = t
                    choice[i, j] = k


def _floor_and_choose(rel, images, y, sd, den, has, z) -> np.ndarray:
    """Floor each ``rel[k]`` in place: ``max(rel[k], mean_c max(|x_k - y| - z sd, 0)^2 / den)`` (0 where the
    pixel is empty, ``has`` False; NaN as np.maximum, the channel terms added in order), ``x_k =
    images[k]``; returns the per-pixel choice: the first candidate of least floored estimate (NaN
    counting as +inf; a pixel where all are NaN or +inf takes 0, as ``np.argmin`` of the stack)."""
    h = rel.shape[1]
    choice = np.empty(rel.shape[1:], np.int64)
    parallel_rows(_floor_choose_rows, (rel, _arrays(images), _c64(y), _c64(sd), _c64(den), np.ascontiguousarray(has),
                                       float(z), choice), h)
    return choice


@numba.njit(cache=True, nogil=True)
def _take_lower_rows(vals, k, best, idx, i0, i1):
    # where vals (NaN as +inf) < best: best = vals, idx = k
    for i in range(i0, i1):
        for j in range(vals.shape[1]):
            x = vals[i, j]
            if x < best[i, j]:
                best[i, j] = x
                idx[i, j] = k


class _FirstLeast:
    """The index of the least of maps offered one at a time (NaN counting as +inf): ``np.argmin`` of their
    stack, ties to the first, without the stack.  A pixel where every map is NaN or +inf keeps index 0."""

    def __init__(self, shape):
        self.best = np.full(shape, np.inf)
        self.index = np.zeros(shape, np.int64)

    def offer(self, k: int, vals: np.ndarray) -> None:
        parallel_rows(_take_lower_rows, (_c64(vals), int(k), self.best, self.index), vals.shape[0])


def _picked(cands, rel, choice):
    """Per pixel, the chosen candidate's image, the channel mean of its unbiased estimate and its
    relative estimate (``rel[k]`` where ``k`` is chosen; ``rel`` indexed by candidate, read once for each
    candidate chosen somewhere)."""
    h, w = choice.shape
    img = np.empty(cands[0].image.shape)
    raw_abs = np.empty((h, w))
    est = np.empty((h, w))
    parallel_rows(_pick_rows, (_arrays([c.image for c in cands]), _arrays([c.mse for c in cands]),
                               np.ascontiguousarray(choice), img, raw_abs), h)
    for k in np.unique(choice):
        at = choice == k
        est[at] = rel[int(k)][at]
    return img, raw_abs, est


@numba.njit(cache=True, nogil=True)
def _pick_rows(images, mses, choice, img, raw_abs, i0, i1):
    h, w, c = img.shape
    a = np.empty(w * c)
    for i in range(i0, i1):
        for k in range(len(images)):
            xk, mk = images[k], mses[k]
            for j in range(w):
                if choice[i, j] != k:
                    continue
                o = j * c
                for ch in range(c):
                    img[i, j, ch] = xk[i, j, ch]
                    a[o + ch] = mk[i, j, ch]
                raw_abs[i, j] = _channel_mean(a, o, c)


class _Floored:
    """Every candidate's smoothed relative estimate floored by its own evidence of bias: ``rel[k]``, an
    (H, W) map, computed where it is read (one candidate's pass of :func:`_floor_and_choose` at ``z``
    standard errors ``sd``), not all K kept: the (K, H, W) stack is 0.3 GB at 1920 x 1080 with 19
    candidates, its recomputation a smoothing a candidate.  The same bits at every read of a candidate:
    ``cands`` is read as it stands then, so the global prior pins its default's map (``rel[g] = x``
    holds x) before it replaces the candidate by a blend."""

    def __init__(self, cands, den, y, sd, has, smoothing, z):
        self.cands, self.den, self.y, self.sd, self.has = cands, den, y, sd, has
        self.smoothing, self.z = smoothing, z
        self.held = {}

    def __len__(self):
        return len(self.cands)

    def __getitem__(self, k):
        if k in self.held:
            return self.held[k]
        c = self.cands[k]
        r = _means([c.mse], self.den)
        self.smoothing([r[0]], out=[r[0]])
        _floor_and_choose(r, [c.image], self.y, self.sd, self.den, self.has, self.z)
        return r[0]

    def __setitem__(self, k, x):
        self.held[k] = x


def _relative_choice(cands, den, y, sd, count, smoothing, z):
    """Every candidate's smoothed relative estimate floored by its own evidence of bias
    (:class:`_Floored`, read where needed) and the per-pixel choice (the first of least estimate; an
    undefined one, NaN, never chosen over a defined one), the candidates offered one at a time."""
    rel = _Floored(cands, den, _c64(y), _c64(sd), np.ascontiguousarray(count > 0), smoothing, z)
    least = _FirstLeast(count.shape)
    for k in range(len(cands)):
        least.offer(k, rel[k])
    return rel, least.index


@numba.njit(cache=True, nogil=True)
def _compress(a, keep, out):
    # out[:n] = a[keep], returns n (each value written, the next one over it unless kept: no branch)
    n = 0
    for p in range(a.size):
        out[n] = a[p]
        n += keep[p]
    return n

"""auto's per-pixel selection: channel means of estimates, floors, the global prior, heavy tails.
"""

from __future__ import annotations


import numba
import numpy as np

from ...filters.engine import parallel_calls

from .estimates import (sorted_neighbours8)
from ...filters.masked import _smooth_masked_many

@numba.njit(cache=True, nogil=True)
def _chan_mean_ratio(mse, den, out):
    # out = mean over channels of mse / den: the channel terms added in order
    # from the first, then divided by C -- numpy's np.mean(axis=2) for C < 8
    h, w, c = mse.shape
    for i in range(h):
        for j in range(w):
            s = mse[i, j, 0] / den[i, j, 0]
            for ch in range(1, c):
                s += mse[i, j, ch] / den[i, j, ch]
            out[i, j] = s / c


@numba.njit(cache=True, nogil=True)
def _chan_mean(a, out):
    h, w, c = a.shape
    for i in range(h):
        for j in range(w):
            s = a[i, j, 0]
            for ch in range(1, c):
                s += a[i, j, ch]
            out[i, j] = s / c


def _mean_c(a: np.ndarray, den: np.ndarray | None = None) -> np.ndarray:
    """``np.mean(a / den, axis=2)`` (bit-identical; compiled for fewer than 8 channels)."""
    if a.shape[2] >= 8:
        return np.mean(a if den is None else a / den, axis=2)
    out = np.empty(a.shape[:2])
    if den is None:
        _chan_mean(np.ascontiguousarray(a, dtype=np.float64), out)
    else:
        _chan_mean_ratio(np.ascontiguousarray(a, dtype=np.float64), np.ascontiguousarray(den, dtype=np.float64),
                         out)
    return out


@numba.njit(cache=True, nogil=True)
def _nanmax(a, b):
    # np.maximum: NaN if either is NaN
    if a != a or b != b:
        return np.nan
    return a if a >= b else b


@numba.njit(cache=True, nogil=True)
def _floored(r, x, y, sd, den, has, z, out):
    """``max(r, mean_c max(|x - y| - z sd, 0)^2 / den)`` (0 floor where the pixel is empty), NaN as np.maximum."""
    h, w, c = x.shape
    for i in range(h):
        for j in range(w):
            s = 0.0
            for ch in range(c):
                lb = abs(x[i, j, ch] - y[i, j, ch]) - z * sd[i, j, ch]
                lb = _nanmax(lb, 0.0)
                if not has[i, j]:
                    lb = 0.0
                t = lb * lb / den[i, j, ch]
                s = t if ch == 0 else s + t
            out[i, j] = _nanmax(r[i, j], s / c)


def _global_prior(raw, loo, smoothed, rel, relm, choice, sigma, z):
    """The per-pixel choice with the best single candidate over the image as the default.

    ``g`` = the candidate of least summed relative estimate over the pixels
    where every candidate has one (far less noisy than any per-pixel
    estimate).  A pixel keeps ``g`` unless another candidate k's smoothed
    estimate is lower by more than ``z`` standard errors of the smoothed
    difference ``raw_k - raw_g`` (local spread over ``N = 4 pi sigma^2``
    effective pixels); among ``g`` and such candidates the least smoothed
    estimate wins.  Where ``g`` itself shows evidence of bias (its floor is
    active) the plain per-pixel choice stands.  Returns ``(choice, g)``.
    """
    fin = np.logical_and.reduce([np.isfinite(r) for r in loo])
    if not fin.any():
        return choice, None
    g = int(np.argmin([float(np.sum(r[fin])) for r in loo]))
    n_eff = 4.0 * np.pi * sigma * sigma
    ok = np.zeros(relm.shape, bool)
    ok[g] = True
    others = [k for k in range(len(raw)) if k != g]
    maps = []
    for k in others:
        d = loo[k] - loo[g]
        d = np.where(np.isnan(loo[k]) | np.isnan(loo[g]) | np.isinf(loo[g]), np.nan, d)
        maps += [d, d * d]
    sm = _smooth_masked_many(maps, sigma)
    for i, k in enumerate(others):
        m, q = sm[2 * i], sm[2 * i + 1]
        with np.errstate(invalid="ignore"):
            se = np.sqrt(np.maximum(q - m * m, 0.0) / n_eff)
            ok[k] = np.isfinite(m) & (m < -z * se)
    default = np.isfinite(relm[g]) & (rel[g] <= np.maximum(smoothed[g], 0.0))
    c2 = np.argmin(np.where(ok, relm, np.inf), axis=0)
    return np.where(default, c2, choice), g


def _pick_where(choice, k, src, out):
    """``out[p] = src[p]`` where ``choice[p] == k`` (src and out (H, W, C) or (H, W), C-contiguous, raveled alike).

    Both as 2-D (pixels, values) views: one compiled kernel for images and maps (it was compiled for each).
    """
    m = choice.size
    if not out.flags.c_contiguous:
        raise ValueError("_pick_where writes into a C-contiguous out")
    _pick_rows(np.ascontiguousarray(choice, dtype=np.int64), int(k), np.ascontiguousarray(src).reshape(m, -1),
               out.reshape(m, -1))


@numba.njit(cache=True, nogil=True)
def _pick_rows(choice, k, s2, o2):
    m, n = s2.shape
    for p in range(m):
        if choice[p] == k:
            for q in range(n):
                o2[p, q] = s2[p, q]


#: A pixel's neighbourhood is heavy-tailed when the largest sample around it exceeds this many times its mean.
HEAVY_TAIL = 10.0


def _no_push_in_heavy_tails(img: np.ndarray, y: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Where the samples around a pixel are heavy-tailed, a candidate may pull it towards its neighbours, not away.

    A pixel is heavy-tailed when the largest sample of its 3 x 3
    neighbourhood (``hi``, from :func:`sample_range_bounds`) exceeds
    :data:`HEAVY_TAIL` times its mean ``y``: rare huge samples (caustics,
    small lights) are around.  There the error estimates that chose a
    candidate are least reliable, and a candidate that moves the pixel
    *further* from the median of its 8 neighbours' means than its own mean
    is (above it when the mean is above the median, or below) carries a
    neighbour's rare sample into it; the pixel keeps its own mean.  Per
    channel; at the film's border the missing neighbours repeat the edge
    (the pixel itself may count up to three times), an empty neighbour's
    mean is 0.  From pixel statistics without a sample range (a half-buffer
    pair, an EXR) ``hi`` is the 3 x 3 maximum of the pixel means, so the
    rule then fires at any edge of more than 10x contrast.  Measured (128^2, 32 spp, 5 seeds, ratio to box): caustic
    0.757 -> 0.522; soft shadow, depth of field, motion blur, hdr and flat
    within 0.1 %; Mitsuba Cornell boxes +1.5-1.7 % (docs/methods/auto.md).
    """
    # one compiled pass: the test and the 8-neighbour median only where the rule can fire
    # (the numpy formulation, kept in the tests as the reference, was 1.2 s of auto's 8 s at 1024^2)
    img = np.ascontiguousarray(img, dtype=np.float64)
    out = img.copy()
    y = np.ascontiguousarray(y, dtype=np.float64)
    hi = np.ascontiguousarray(hi, dtype=np.float64)
    every = np.ones(y.shape[:2], bool)
    # row blocks on the filters' thread pool (a parallel=True kernel cost 1.5 s of compilation on a first run)
    parallel_calls(_no_push_rows, [(img, y, hi, every, HEAVY_TAIL, out, i0, min(i0 + _ROWS, y.shape[0]))
                                   for i0 in range(0, y.shape[0], _ROWS)])
    return out


#: Rows per call of :func:`_no_push_rows` (each output pixel is computed by one call: no effect on the result).
_ROWS = 64


@numba.njit(cache=True, nogil=True)
def _no_push_rows(img, y, hi, every, heavy_tail, out, i0, i1):
    """:func:`_no_push_in_heavy_tails` per pixel and channel in rows [i0, i1) (``out`` starts as a copy of ``img``).

    The median of the 8 neighbours (edge-repeated; ``every`` all True:
    an empty neighbour's mean counts) is the mean of the 4th and 5th of
    them sorted, as :func:`numpy.median` computes it; NaN anywhere among
    them makes it NaN, and a NaN median never reverts.
    """
    h, w, c = y.shape
    nb = np.empty(8)
    for i in range(i0, i1):
        for j in range(w):
            for ch in range(c):
                yc = y[i, j, ch]
                oc = img[i, j, ch]
                if not (hi[i, j, ch] > heavy_tail * abs(yc)) or not (oc != yc):
                    continue
                sorted_neighbours8(y, every, i, j, ch, nb)
                nan = False
                for m in range(8):
                    if nb[m] != nb[m]:
                        nan = True
                if nan:
                    continue
                med = (nb[3] + nb[4]) / 2.0
                if (yc > med and oc > yc) or (yc < med and oc < yc):
                    out[i, j, ch] = yc


def _largest_remainder(pri: np.ndarray, total: int) -> np.ndarray:
    """Integer counts summing to ``total`` in proportion to ``pri`` (inf: served first, evenly)."""
    h, w = pri.shape
    flat = pri.ravel()
    counts = np.zeros(flat.size, np.int64)
    inf = np.isposinf(flat)
    if inf.any():
        idx = np.flatnonzero(inf)
        k = min(total, idx.size)
        counts[idx[:k]] += 1
        total -= k
        flat = np.where(inf, 0.0, flat)
    s = float(flat.sum())
    if total > 0:
        if not s > 0:
            flat = np.ones(flat.size)
            s = float(flat.size)
        share = flat * (total / s)
        base = np.floor(share).astype(np.int64)
        rest = total - int(base.sum())
        if rest > 0:
            order = np.argsort(-(share - base), kind="stable")[:rest]
            base[order] += 1
        counts += base
    return counts.reshape(h, w)

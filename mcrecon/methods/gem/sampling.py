"""Sample distribution of ``gem`` (Rousselle et al. 2011, Sec. 5).

:func:`sample_priority`: relative MSE of each pixel's selected filter and
its expected reduction from n new samples; :func:`distribute_samples`:
the pixels of highest priority each get n samples, importance-sampled
over their selected filter.
"""

from __future__ import annotations


import numba
import numpy as np

from ...core.samples import check_memory
from ...filters.gaussian import pixel_kernel
from ...core.samples import sort_by_row

__all__ = ['SAMPLING_EPS', 'sample_priority', 'distribute_samples']

#: Bytes a planned sample takes while its position is drawn: pixel and offset (4 int64),
#: the position (2 float64) and the row sort's order and copy.
_BYTES_PER_PLANNED_SAMPLE = 80.0

#: Sec. 5: relative MSE for sampling divides by value^2 + 0.001.
SAMPLING_EPS = 1e-3


def sample_priority(mse: np.ndarray, value: np.ndarray, n_eff: np.ndarray, n_new: int, *,
                    eps: float = SAMPLING_EPS) -> tuple[np.ndarray, np.ndarray]:
    """Relative MSE and the expected reduction from n new samples (Sec. 5).

    ``relMSE = mean_c MSE_c / (value_c^2 + eps)``; adding n samples over a
    filter that saw n_s samples multiplies its MSE by n_s / (n + n_s), so
    the reduction (the priority) is ``relMSE * n / (n + n_s)``.  Pixels
    without samples (MSE inf) get priority +inf.

    Returns
    -------
    rel_mse, priority : ndarray (H, W)
    """
    if mse.ndim == 3 and mse.shape[2] <= 4 and value.shape == mse.shape and n_eff.shape == mse.shape[:2]:
        h, w, c = mse.shape
        rel = np.empty((h, w))
        pri = np.empty((h, w))
        _priority_kernel(np.ascontiguousarray(mse, dtype=np.float64).reshape(h * w, c),
                         np.ascontiguousarray(value, dtype=np.float64).reshape(h * w, c),
                         np.ascontiguousarray(n_eff, dtype=np.float64).reshape(-1), float(n_new), float(eps),
                         rel.reshape(-1), pri.reshape(-1))
        return rel, pri
    inf = ~np.isfinite(mse).all(axis=2)
    m = np.where(inf[..., None], 0.0, mse)
    rel = np.mean(m / (value * value + eps), axis=2)
    pri = rel * (n_new / (n_new + n_eff))
    rel = np.where(inf, np.inf, rel)
    pri = np.where(inf, np.inf, pri)
    return rel, pri


@numba.njit(cache=True, nogil=True)
def _priority_kernel(mse, value, n_eff, n_new, eps, rel, pri):
    # the numpy expressions of sample_priority, element by element (the mean
    # over a short axis adds left to right, then divides by the count)
    n, c = mse.shape
    for p in range(n):
        finite = True
        for ch in range(c):
            if not np.isfinite(mse[p, ch]):
                finite = False
        if not finite:
            rel[p] = np.inf
            pri[p] = np.inf
            continue
        s = 0.0
        for ch in range(c):
            v = value[p, ch]
            t = mse[p, ch] / (v * v + eps)
            s = t if ch == 0 else s + t
        r = s / c
        rel[p] = r
        pri[p] = r * (n_new / (n_new + n_eff[p]))


@numba.njit(cache=True, nogil=True)
def _owner_pixels(idx, per, w, px, py):
    # np.divmod(np.repeat(idx, per), w) without the temporaries
    q = 0
    for a in range(idx.size):
        yy = idx[a] // w
        xx = idx[a] - yy * w
        for _ in range(per[a]):
            px[q] = xx
            py[q] = yy
            q += 1


@numba.njit(cache=True, nogil=True)
def _search_right(cdf, u, guide, nb):
    # np.searchsorted(cdf, u, side="right"), the number of entries <= u: start
    # from guide[b - 1] = that count at (b - 1) / nb <= u and scan forward
    b = int(u * nb) - 1
    i = guide[min(max(b, 0), nb)]
    while i < cdf.size and cdf[i] <= u:
        i += 1
    return i


@numba.njit(cache=True, nogil=True)
def _kernel_offsets(cdf, r, ux, uy, todo, px, py, w, h, ox, oy):
    """Pixel offsets min(searchsorted(cdf, u, 'right'), size - 1) - r for the
    samples ``todo``; returns those whose pixel lies off the film."""
    top = cdf.size - 1
    # guide[b] = number of entries <= b / nb; buckets fine enough that the
    # scan in _search_right rarely takes a step (a predictable branch)
    nb = 1024
    guide = np.empty(nb + 1, np.int64)
    i = 0
    for b in range(nb + 1):
        t = b / nb
        while i < cdf.size and cdf[i] <= t:
            i += 1
        guide[b] = i
    off = np.empty(todo.size, np.int64)
    m = 0
    for t in range(todo.size):
        s = todo[t]
        dx = min(_search_right(cdf, ux[t], guide, nb), top) - r
        dy = min(_search_right(cdf, uy[t], guide, nb), top) - r
        ox[s] = dx
        oy[s] = dy
        x = px[s] + dx
        y = py[s] + dy
        if x < 0 or x >= w or y < 0 or y >= h:
            off[m] = s
            m += 1
    return off[:m]


@numba.njit(cache=True, nogil=True)
def _place_in_pixels(pos, px, py, ox, oy):
    # positions uniform in the (offset) pixel, kept strictly below its upper edge
    for i in range(pos.shape[0]):
        fx = np.float64(px[i] + ox[i])
        fy = np.float64(py[i] + oy[i])
        # min(u + x, nextafter(x + 1, 0)); u + x <= x + 1, so only a sum that
        # rounded up to x + 1 needs the (slow) nextafter
        a = pos[i, 0] + fx
        if a >= fx + 1.0:
            a = np.nextafter(fx + 1.0, 0.0)
        pos[i, 0] = a
        a = pos[i, 1] + fy
        if a >= fy + 1.0:
            a = np.nextafter(fy + 1.0, 0.0)
        pos[i, 1] = a


def distribute_samples(priority: np.ndarray, selected: np.ndarray, sigmas, n_total: int,
                       n_per_pick: int, rng: np.random.Generator, *, subpixels: int = 4,
                       as_counts: bool = False) -> np.ndarray:
    """Positions (or per-pixel counts) of ``n_total`` new samples (Sec. 5).

    The ``m = n_total // n_per_pick`` pixels of highest priority each get
    ``n_per_pick`` samples (the next one the remainder), placed in pixels
    drawn by importance sampling of their selected filter: the pixel
    filter keeps them in the pixel, a Gaussian scale draws the pixel
    offset from the separable pixel kernel (x and y independently), draws
    off the film are redrawn (the filter is renormalised there too).  Each
    sample lies uniformly at random inside its pixel.

    Parameters
    ----------
    as_counts : bool
        Return the samples per pixel instead of positions.  The position
        inside a pixel is uniform and carries no decision, so a request for
        counts has the same distribution and lets the renderer place them:
        a renderer with a per-pixel low-discrepancy sampler continues each
        pixel's sequence (stratified), which film positions chosen here
        would break (their film dimensions are independent uniforms).

    Returns
    -------
    ndarray (n_total, 2) float64, or (H, W) int64 with ``as_counts``
        Film positions (x = column, y = row), ordered by row
        (:func:`sort_by_row`); or the samples per pixel (summing to ``n_total``).
    """
    h, w = selected.shape
    n_total = int(n_total)
    n_per_pick = max(1, int(n_per_pick))
    if n_total <= 0:
        return np.zeros((h, w), np.int64) if as_counts else np.zeros((0, 2))
    # the positions and their per-sample temporaries (pixel, offset, order): refused in one
    # line before a budget the machine cannot hold is allocated
    check_memory("method gem", "spp", _BYTES_PER_PLANNED_SAMPLE * n_total,
                 f"a round of {n_total} sample positions", "lower the budget (--spp)")
    m = n_total // n_per_pick
    rem = n_total - m * n_per_pick
    n_pick = min(m + (1 if rem else 0), h * w)
    flat = priority.ravel()
    if n_pick < flat.size:
        idx = np.argpartition(-flat, n_pick - 1)[:n_pick]
    else:
        idx = np.arange(flat.size)
    idx = idx[np.argsort(-flat[idx], kind="stable")]
    per = np.full(idx.size, n_per_pick, np.int64)
    if idx.size * n_per_pick >= n_total:
        # the last pick gets the remainder (or everything fits on fewer picks)
        per[-1] = n_total - n_per_pick * (idx.size - 1)
    else:
        # fewer pixels than picks: spread the rest evenly over them
        per += (n_total - per.sum()) // idx.size
        per[: n_total - per.sum()] += 1
    # group the picks by selected scale so each scale's samples are one slice
    scale_pick = selected.ravel()[idx]
    order = np.argsort(scale_pick, kind="stable")
    idx, per, scale_pick = idx[order], per[order], scale_pick[order]
    n_all = int(per.sum())
    px = np.empty(n_all, np.int64)
    py = np.empty(n_all, np.int64)
    _owner_pixels(idx, per, w, px, py)
    ends = np.cumsum(per)
    starts = ends - per
    ox = np.zeros(n_all, np.int64)
    oy = np.zeros(n_all, np.int64)
    sig = np.asarray(sigmas, dtype=np.float64)
    for k in np.unique(scale_pick):
        if k == 0:
            continue                      # the pixel filter: samples stay in the pixel
        picks = np.flatnonzero(scale_pick == k)
        lo, hi = int(starts[picks[0]]), int(ends[picks[-1]])
        ker = pixel_kernel(sig[k - 1], subpixels)
        r = (ker.size - 1) // 2
        cdf = np.cumsum(ker)
        cdf /= cdf[-1]
        todo = np.arange(lo, hi)
        for _ in range(64):
            if todo.size == 0:
                break
            # inverse-CDF draws from the separable pixel kernel (x and y
            # independent); the draws still off the film are redrawn
            ux = rng.random(todo.size)
            uy = rng.random(todo.size)
            todo = _kernel_offsets(cdf, r, ux, uy, todo, px, py, w, h, ox, oy)
        ox[todo] = 0  # (practically never) still off the film: keep them in their own pixel
        oy[todo] = 0
    if as_counts:
        return np.bincount((py + oy) * w + (px + ox), minlength=h * w).astype(np.int64).reshape(h, w)
    pos = rng.random((n_all, 2))
    _place_in_pixels(pos, px, py, ox, oy)
    return sort_by_row(pos, h)

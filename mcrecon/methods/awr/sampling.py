"""Adaptive sampling (Overbeck et al. 2009, §4.1): scale-coefficient priorities and the sampler.

Scale coefficients of levels 0..5 are ranked by the priority
``P = sigma^2(S) - mean(W^2)`` (Eq. 8, :func:`scale_priorities`); each
selected coefficient receives ``64 * 2**k`` samples importance-sampled
from ``|Phi|`` (separable 1-D CDF tables, Fig. 5:
:func:`sample_scale_functions`).  :func:`plan_awr_positions` is one
batch of it, a plain sample request usable with any reconstruction
(paper Fig. 10).
"""

from __future__ import annotations

import functools

import numba
import numpy as np

from ...core.samples import check_memory
from ...core.nets import fill_lowest
from ...core.safeguard import neighbourhood_mean_variance, rare_component_mask
from ...core.stats import PixelStats
from ...core.fill import fill_empty_pixels
from .reconstruction import functional_variance
from .wavelets import SAMPLING_RENORM, analysis_matrices, analyze, coefficient_variances, default_levels, get_wavelet

__all__ = ["scale_priorities", "sample_scale_functions", "plan_awr_positions"]


def scale_priorities(mean: np.ndarray, var: np.ndarray, *, wavelet: str = "cdf97", levels: int = 5,
                     mode: str = "symmetric", renorm: float | None = SAMPLING_RENORM,
                     propagation: str = "exact") -> list[np.ndarray]:
    """Priorities ``P(S_k) = sigma^2(S_k) - mean_alpha(W_k^alpha)^2`` (Eq. 8).

    Parameters
    ----------
    mean : ndarray (H, W, C) or (H, W)
        Pixel means; the wavelets are taken of their channel mean (the
        paper's "intensity image", Table 1).
    var : ndarray (H, W) or (H, W, C)
        sigma^2(B) from the sampler's estimator (Mitchell contrast, Eq. 5,
        6), averaged over channels.
    levels : int
        Highest scale level; level 0 (the pixels, which have no wavelets)
        has priority ``sigma^2(B)``.

    Returns
    -------
    list of ndarray
        ``out[k]`` (n_k^y, n_k^x) for k = 0..levels.

    References
    ----------
    .. [1] Overbeck et al. 2009, Eq. 8 and 9.
    """
    mean = np.asarray(mean, dtype=np.float64)
    var = np.asarray(var, dtype=np.float64)
    # Scalar intensity images, as in the paper's implementation (Table 1:
    # "intensity images" for the wavelet and the variance updates): the
    # channel mean of the pixel means and of sigma^2(B).
    inten = mean.mean(axis=2) if mean.ndim == 3 else mean
    v = var.mean(axis=2) if var.ndim == 3 else var
    out = [v.copy()]
    if levels <= 0:
        return out
    # float32: the wavelets only rank coefficients; halves the DWT's cost.
    _, details, _, _ = analyze(inten.astype(np.float32), wavelet, levels, mode=mode, axes=(0, 1))
    svar = coefficient_variances(v, wavelet, levels, mode=mode, axes=(0, 1), propagation=propagation,
                                 renorm=renorm, which="scales")
    for k in range(levels):
        # (W~)^2 = mean over the 3 wavelets (Eq. 8).
        w2 = sum(np.square(c, dtype=np.float64) for c in details[k].values()) / len(details[k])
        out.append(svar[k] - w2)
    return out


@functools.lru_cache(maxsize=32)
def _cdf_tables(n: int, wavelet: str, mode: str, levels: int):
    """Per level: (indptr, indices, G) with G = row + within-row CDF of |Phi_k|.

    Row r's entries have G in (r, r + 1], so one ``searchsorted`` on
    ``r + u`` finds the pixel for many rows at once (Fig. 5's tables).
    """
    lo, _ = analysis_matrices(n, wavelet, mode, levels)
    tables = []
    for m in lo:
        a = np.abs(m.data)
        csum = np.cumsum(a)
        start = np.repeat(csum[m.indptr[:-1]] - a[m.indptr[:-1]], np.diff(m.indptr))
        tot = np.repeat(np.add.reduceat(a, m.indptr[:-1]), np.diff(m.indptr))
        within = (csum - start) / tot
        within[m.indptr[1:] - 1] = 1.0
        rows = np.repeat(np.arange(m.shape[0]), np.diff(m.indptr))
        tables.append((m.indptr.copy(), m.indices.astype(np.int64), rows + within, within))
    return tables


@functools.lru_cache(maxsize=64)
def _centre_offset(wavelet: str, mode: str, level: int) -> float:
    """``offset`` with row ``a``'s |Phi_k| centroid at ``2^k a + offset`` (independent of n).

    Measured on a row of a signal long enough that the middle row is more
    than half a support away from both borders.
    """
    big = 2 ** level * (get_wavelet(wavelet).dec_len + 2) * 2
    m = analysis_matrices(big, wavelet, mode, level)[0][level - 1]
    a_mid = m.shape[0] // 2
    row = m.getrow(a_mid)
    wts = np.abs(row.data)
    return float(np.sum(row.indices * wts) / np.sum(wts)) - 2 ** level * a_mid


@functools.lru_cache(maxsize=64)
def _rows_on_film(n: int, wavelet: str, mode: str, levels: int, level: int) -> np.ndarray:
    """Level-``k`` scale coefficients whose unfolded centre lies on the film.

    With ``symmetric`` extension PyWavelets keeps extra coefficients whose
    basis functions are centred beyond the border and fold back onto the
    border pixels; ranking them would count the border several times (it
    drew 3x the interior sample density into the corners).  The sampler
    ranks the coefficients of the paper's grid only: interior rows have
    their |Phi| centroid at ``2^k a + offset``; keep ``a`` with that
    centre in ``[-1/2, n - 1/2]`` (``periodization``: every row).
    """
    lo, _ = analysis_matrices(n, wavelet, mode, levels)
    n_k = lo[level - 1].shape[0]
    if mode == "periodization":
        return np.ones(n_k, bool)
    centre = 2 ** level * np.arange(n_k) + _centre_offset(wavelet, mode, level)
    return (centre >= -0.5) & (centre <= n - 0.5)


@functools.lru_cache(maxsize=64)
def _support_bounds(n: int, wavelet: str, mode: str, levels: int, level: int):
    """First and one-past-last pixel of each level-``k`` scale function's support."""
    m = analysis_matrices(n, wavelet, mode, levels)[0][level - 1]
    starts = m.indptr[:-1]
    return (np.minimum.reduceat(m.indices, starts).astype(np.int64),
            np.maximum.reduceat(m.indices, starts).astype(np.int64) + 1)


def sample_scale_functions(level: int, iy: np.ndarray, ix: np.ndarray, counts: np.ndarray, *, width: int,
                           height: int, rng: np.random.Generator, wavelet: str = "cdf97",
                           mode: str = "symmetric", levels: int | None = None) -> np.ndarray:
    """Film positions importance-sampled from ``|Phi_{k, iy, ix}|`` (§4.1 Step 3, Fig. 5).

    Each axis is sampled independently from the 1-D CDF of the absolute
    boundary-folded discrete scale function (its row of
    :func:`analysis_matrices`); within the chosen pixel the position is
    uniform.  Level 0 is the pixel itself.

    Parameters
    ----------
    level : int
    iy, ix : ndarray of int
        Coefficient indices at that level.
    counts : ndarray of int
        Samples for each coefficient.

    Returns
    -------
    ndarray (sum(counts), 2)
        (x, y) positions on the film, grouped by coefficient.
    """
    counts = np.asarray(counts, dtype=np.int64)
    iy = np.ascontiguousarray(iy, dtype=np.int64)
    ix = np.ascontiguousarray(ix, dtype=np.int64)
    n = int(counts.sum())
    # float32 uniforms: half the cost; 2^-24 of a pixel is far below any
    # renderer's resolution.
    u = rng.random((n, 4), dtype=np.float32)
    out = np.empty((n, 2))
    if level == 0:
        empty_p, empty_i, empty_c = np.zeros(1, np.int64), np.zeros(1, np.int64), np.zeros(1)
        _draw_kernel(iy, ix, counts, u, empty_p, empty_i, empty_c, empty_p, empty_i, empty_c, False, out)
        return out
    lv = max(level, levels or level)
    ty = _cdf_tables(height, wavelet, mode, lv)[level - 1]
    tx = _cdf_tables(width, wavelet, mode, lv)[level - 1]
    _draw_kernel(iy, ix, counts, u, ty[0], ty[1], ty[3], tx[0], tx[1], tx[3], True, out)
    return out


# Largest jitter inside a pixel: p + u * _JIT < p + 1 in float64 for films
# narrower than ~1e6 pixels (spacing there is 1.2e-10 < 1e-9).
_JIT = 1.0 - 1e-9


@numba.njit(cache=True, nogil=True)
def _paint_boxes(diff, y0, y1, x0, x1):
    """Add the corners of boxes [y0, y1) x [x0, x1) to a 2-D difference array."""
    for i in range(y0.shape[0]):
        diff[y0[i], x0[i]] += 1
        diff[y1[i], x0[i]] -= 1
        diff[y0[i], x1[i]] -= 1
        diff[y1[i], x1[i]] += 1


@numba.njit(cache=True, nogil=True)
def _search_row(indptr, indices, within, r, u):
    """Pixel of row ``r`` whose within-row CDF first exceeds ``u`` (binary search)."""
    lo = indptr[r]
    hi = indptr[r + 1] - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if within[mid] > u:
            hi = mid
        else:
            lo = mid + 1
    return indices[lo]


@numba.njit(cache=True, nogil=True)
def _draw_kernel(iy, ix, counts, u, py_ptr, py_idx, py_cdf, px_ptr, px_idx, px_cdf, scaled, out):
    """Fill ``out`` with ``counts[c]`` positions per coefficient (Fig. 5).

    ``u[:, 0:2]`` choose the pixel rows/columns by inverse CDF of |phi|,
    ``u[:, 2:4]`` the position inside the pixel.
    """
    k = 0
    for c in range(counts.shape[0]):
        for _ in range(counts[c]):
            if scaled:
                y = _search_row(py_ptr, py_idx, py_cdf, iy[c], u[k, 0])
                x = _search_row(px_ptr, px_idx, px_cdf, ix[c], u[k, 1])
            else:
                y = iy[c]
                x = ix[c]
            out[k, 0] = x + u[k, 2] * _JIT
            out[k, 1] = y + u[k, 3] * _JIT
            k += 1


def plan_awr_positions(stats: PixelStats, n_samples: int, rng: np.random.Generator, *, wavelet: str = "cdf97",
                       levels: int = 5, mode: str = "symmetric", per_coefficient: int = 64,
                       renorm: float = SAMPLING_RENORM, propagation: str = "exact",
                       priority_threshold: float | None = None, estimator: str = "contrast",
                       pending: np.ndarray | None = None, as_counts: bool = False,
                       rare_light_floor: bool = False, pixel_pops: int = 1, owed: np.ndarray | None = None):
    """One batch of the adaptive wavelet sampler (§4.1 Steps 2-3).

    Ranks all scale coefficients of levels 0..``levels`` by Eq. 8 and
    takes them in decreasing priority (a priority queue popped without
    intermediate updates: the batch is the unit after which priorities
    are recomputed), giving ``per_coefficient * 2**k`` samples to each
    until ``n_samples`` are placed (the last one gets the remainder).

    Usable with any reconstruction (paper Fig. 10): the positions are a
    plain sample request.

    ``pending`` (H, W), optional: samples per pixel of a round in flight
    (a pipelined run).  They are counted as taken: sigma^2(B) =
    sigma^2(F) / (N + pending) (Eq. 6 with the samples to come), so the
    batch does not rank first the coefficients the round in flight already
    serves.  The wavelet coefficients (the committed means) are unchanged:
    the pending samples' expected mean is the current one.

    ``rare_light_floor``: floor each pixel's sigma^2(F) at the mean of its
    5 x 5 neighbourhood's where a neighbour's samples show a rare bright
    component (:func:`~mcrecon.core.safeguard.rare_component_variance`): a
    pixel whose samples all missed a spotlight or a caustic its neighbours
    found reads a variance near 0 and would get no coefficient's samples.

    ``pixel_pops``: how often one batch may pop a pixel's (level-0)
    coefficient, its priority after ``m`` pops ``sigma^2(F) / (N + m
    per_coefficient)`` (the variance its mean then has).  1: once, the
    paper's queue without updates inside a batch.  With a small
    ``per_coefficient`` a pixel of huge variance (an HDR edge) still gets
    what a large one would give it, while the pixels one noisy estimate
    ranks high get a fraction of the round each, not all of it.

    ``owed`` (H, W), optional, with ``as_counts``: samples per pixel the
    batch gives first (a stratified pixel's rare-component net,
    :func:`~mcrecon.core.nets.rare_net_deficit`); the coefficients share
    the rest.  A batch smaller than what is owed raises the pixels owed
    from the fewest samples up (:func:`~mcrecon.core.nets.fill_lowest`).

    ``as_counts``: return the samples per pixel instead of positions.  The
    position inside the chosen pixel is uniform and carries no decision, so
    a request for counts has the same distribution and lets the renderer
    place them: a renderer with a per-pixel low-discrepancy sampler
    continues each pixel's sequence (stratified), which film positions
    chosen here would break (their film dimensions are independent uniforms).

    Returns
    -------
    positions : ndarray (M, 2), (H, W) int64 with ``as_counts``, or None
        None when no coefficient's priority exceeds ``priority_threshold``
        (or ``n_samples <= 0``).
    info : dict
        ``max_priority``, ``levels_used`` (samples per level),
        ``affected_fraction`` (share of pixels inside the support of a
        selected coefficient, i.e. what a local update would recompute).
    """
    n_samples = int(n_samples)
    info = {"max_priority": float("nan"), "levels_used": {}, "affected_fraction": 0.0}
    if n_samples <= 0:
        return None, info
    if owed is not None and as_counts and np.any(owed):
        taken = stats.count + np.asarray(pending) if pending is not None else stats.count
        owed = np.asarray(owed, dtype=np.int64)
        if int(owed.sum()) >= n_samples:
            return fill_lowest(taken, n_samples, rng, cap=taken + owed), info
        rest, info = plan_awr_positions(
            stats, n_samples - int(owed.sum()), rng, wavelet=wavelet, levels=levels, mode=mode,
            per_coefficient=per_coefficient, renorm=renorm, propagation=propagation,
            priority_threshold=priority_threshold, estimator=estimator, pending=pending, as_counts=True,
            rare_light_floor=rare_light_floor, pixel_pops=pixel_pops)
        return owed if rest is None else owed + rest, info
    # the positions and their per-sample temporaries: refused in one line before a budget the
    # machine cannot hold is allocated
    check_memory("method awr", "spp", 64.0 * n_samples, f"a round of {n_samples} sample positions",
                 "lower the budget (--spp)")
    h, w = stats.height, stats.width
    levels = int(min(levels, default_levels((h, w))))
    mean = fill_empty_pixels(stats.mean.copy(), stats.count, source="awr sampler") if (stats.count == 0).any() \
        else stats.mean
    fvar = functional_variance(stats, estimator)
    if rare_light_floor:
        # the evidence is the samples' variance whatever sigma^2(F) estimator ranks the coefficients
        n = np.maximum(stats.count, 1)[..., None]
        rare = rare_component_mask(stats.sample_variance(undefined=0.0) / n, stats.mean, stats.count)
        fvar = np.where(rare, np.maximum(fvar, neighbourhood_mean_variance(fvar / n, stats.count) * n), fvar)
    taken = stats.count + np.asarray(pending) if pending is not None and np.any(pending) else stats.count
    var = fvar / np.maximum(taken, 1)[..., None]
    pri = scale_priorities(mean, var, wavelet=wavelet, levels=levels, mode=mode, renorm=renorm,
                           propagation=propagation)
    for k in range(1, levels + 1):
        on = (_rows_on_film(h, wavelet, mode, levels, k)[:, None]
              & _rows_on_film(w, wavelet, mode, levels, k)[None, :])
        pri[k] = np.where(on, pri[k], -np.inf)
    pops = max(1, int(pixel_pops))
    if pops > 1:
        # the m-th pop of a pixel: the variance of its mean with m * per_coefficient more samples
        t = np.maximum(taken, 1).astype(np.float64)
        pri[0] = np.concatenate([pri[0] * (t / (t + m * per_coefficient)) for m in range(pops)], axis=0)
    flat = np.concatenate([p.ravel() for p in pri])
    lev_of = np.concatenate([np.full(p.size, k, np.int64) for k, p in enumerate(pri)])
    off = np.concatenate([[0], np.cumsum([p.size for p in pri])])
    info["max_priority"] = float(flat.max())
    if priority_threshold is not None and not flat.max() > priority_threshold:
        return None, info
    # Enough candidates for the batch even if all are level 0.
    m = min(flat.size, n_samples // per_coefficient + 1)
    cand = np.argpartition(-flat, m - 1)[:m] if m < flat.size else np.arange(flat.size)
    cand = cand[np.argsort(-flat[cand], kind="stable")]
    if priority_threshold is not None:
        cand = cand[flat[cand] > priority_threshold]
    cost = per_coefficient * (2 ** lev_of[cand])
    csum = np.cumsum(cost)
    k_last = int(np.searchsorted(csum, n_samples))          # first index reaching the quota
    cand = cand[:k_last + 1]
    cost = cost[:k_last + 1].copy()
    placed = int(cost[:-1].sum())
    cost[-1] = min(cost[-1], n_samples - placed)
    parts = []
    # Support bounding boxes of the selected coefficients, painted with a
    # 2-D difference array: the area a local priority update would redo.
    diff = np.zeros((h + 1, w + 1), np.int64)
    for k in range(levels + 1):
        sel = lev_of[cand] == k
        if not sel.any():
            continue
        local = cand[sel] - off[k]
        ny, nx = pri[k].shape
        if k == 0:
            local, ny = local % (h * w), h  # the pops of one pixel are the same coefficient
        iy, ix = local // nx, local % nx
        parts.append(sample_scale_functions(k, iy, ix, cost[sel], width=w, height=h, rng=rng, wavelet=wavelet,
                                            mode=mode, levels=levels))
        info["levels_used"][k] = int(cost[sel].sum())
        if k == 0:
            y0, y1, x0, x1 = iy, iy + 1, ix, ix + 1
        else:
            sy, sx = _support_bounds(h, wavelet, mode, levels, k), _support_bounds(w, wavelet, mode, levels, k)
            y0, y1, x0, x1 = sy[0][iy], sy[1][iy], sx[0][ix], sx[1][ix]
        _paint_boxes(diff, np.asarray(y0, np.int64), np.asarray(y1, np.int64),
                     np.asarray(x0, np.int64), np.asarray(x1, np.int64))
    cover = np.cumsum(np.cumsum(diff, axis=0), axis=1)[:h, :w] > 0
    info["affected_fraction"] = float(cover.mean())
    pos = np.concatenate(parts, axis=0) if parts else np.zeros((0, 2))
    if as_counts:
        # positions lie strictly inside their pixel (x + u * _JIT < x + 1): the floor is the pixel
        pix = pos[:, 1].astype(np.int64) * w + pos[:, 0].astype(np.int64)
        return np.bincount(pix, minlength=h * w).astype(np.int64).reshape(h, w), info
    # by row: the statistics take the reply several times faster (see sort_by_row)
    from ...core.samples import sort_by_row

    return sort_by_row(pos, h), info

"""Collaborative first-order regression (NFOR Sec. 5.2, after Moon et al. 2014).

For every pixel p, a weighted least-squares fit of the colour y over the
(2R+1)^2 window N(p) on the design

    x_q = (1, (q_x - p_x) / R, (q_y - p_y) / R, f(q) - f(p))       (one column per feature channel)

with the NL-means weights w_pq of :mod:`.nlmeans` (from a guide image,
one weight for all channels: the smallest channel weight):

    beta_p = argmin_b  sum_q w_pq |y_q - x_q^T b|^2 + lambda S0_p |b_1..|^2,   S0_p = sum_q w_pq

(the ridge ``lambda`` is on every column but the constant, on features
standardised over the image: it makes flat or collinear features solvable
and moves an exact linear fit by O(lambda), 1e-10 by default).  Each pixel's
fit predicts its whole window (``y_hat_p(q) = x_q^T beta_p``); the estimate
at q is the weighted average of the predictions of every window covering it:

    y_out(q) = sum_p w_pq y_hat_p(q) / sum_p w_pq          (collaborative averaging)

The pixel-offset columns are those of the reference implementation
(Tungsten's ``Regression.cpp``); normal equations in float64, solved by
Cholesky (d <= a few dozen columns).
"""

from __future__ import annotations

import numba
import numpy as np

from .engine import n_threads, parallel_calls
from .window_algebra import LEVERAGE_BLOCK, NE_PAD, _leverages, _normal_equations, _predict, _solve_spd
from .nlmeans import (BAND, DISTANCE_CLAMP, MIN_CENTER_WEIGHT, NLM_EPS, as_planes, exp_neg, offset_distances,
                      scaled_planes)

__all__ = ["RIDGE", "collaborative_regression", "collaborative_regressions", "feature_scale", "standardise"]

#: Default ridge on the non-constant columns, relative to the window's total weight.
RIDGE = 1e-10
#: Weight of the grid's pixels below which a pixel of a strided regression fits its own window too
#: (:func:`collaborative_regression`'s ``min_weight``): its own window would give it weight 1.
MIN_COVER_WEIGHT = 1.0
#: Bands per thread whose accumulators :func:`collaborative_regression` holds at once.
BANDS_PER_THREAD = 4
#: Floats added to each offset's row of weights in :func:`_band` (one cache line: see there).
WEIGHT_PAD = 16


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _band(ypad, guide, var, fpad, r, f, k2s, ridge, eps, clamp, min_centre, leverage, stride, min_weight, band, b,
          acc):
    """Band ``b``: rows [i0, i1) = [b band, min(H, (b + 1) band)) as window centres, for every bandwidth of
    ``k2s`` (K,) (the k^2 of the weights); bandwidth b's predictions written into its private accumulators
    acc[b] (C + 1 [+ 1], i1 - i0 + 2r, W + 2r) (zeroed here: bands run on separate threads, and the band
    is the kernel the thread pool calls, so that no wrapper recompiles its body), whose (t, u)
    is image pixel (i0 - r + t, u - r) (plane C: the weights; with ``leverage``, plane C + 1:
    sum_p w_pq^2 x_q^T A_p^-1 x_q, the numerator of the filter's centre weight :func:`_leverages`).
    With ``stride`` s > 1, a pixel fits a window for bandwidth b only where its row and column are multiples
    of s (the grid), or where its own weights of the grid pixels in its window sum below ``min_weight`` (its
    patch is alike in too few of theirs: the windows of the grid would leave it nearly unweighted); every
    fit is the same arithmetic as with s = 1.  The bandwidths share the window's design and colours (gathered once per pixel); each bandwidth's
    arithmetic is that of a call with it alone, so its result is bit-identical to one.

    ypad (C, H + 2r, W + 2r), fpad (D, H + 2r, W + 2r): colour and features padded by r zeros, so that
    every window is whole (outside the image the weight is 0 and adds exactly nothing).  Offset-major:
    for a run of ``chunk`` pixels of a row, each offset adds its term to the pixels' packed normal
    equations at once (loops along the row, vectorised, no reduction); the sums per pixel are in the
    reference's order (the window's offsets row by row), so the normal equations equal the reference's
    but for the weights' rounding.  Then one (d x d) Cholesky per pixel, and a second pass over the
    offsets scatters each fit's predictions of its window.
    """
    nc = ypad.shape[0]
    h, w = guide.shape[1], guide.shape[2]
    i0 = b * band
    i1 = min(h, i0 + band)
    acc[:] = 0.0
    nf = fpad.shape[0]
    d = 3 + nf
    n_rows = i1 - i0
    side = 2 * r + 1
    cg = guide.shape[0]
    # 1. the weights of every offset for the band's pixels (0 where q is outside the image)
    # one row of ``wts`` per offset, pixel (rr, j) at rr * w + j; rows WEIGHT_PAD floats longer than the band
    # so that consecutive offsets do not share cache sets (a band of 16 rows of a width multiple of 64 makes
    # the plain stride a multiple of 4 KiB: each pixel's 361 weights would all map to one L1 set)
    nk = k2s.shape[0]
    wts = np.zeros((nk, side * side, n_rows * w + WEIGHT_PAD), np.float32)
    pd = np.zeros((cg, n_rows + 2 * f, w + 2 * f), np.float32)
    vs = np.zeros(w + 2 * f)
    ic = np.zeros(w + 2 * f)
    dist = np.zeros((cg, n_rows, w), np.float32)
    dmax = np.zeros(w, np.float32)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            o = (dy + r) * side + (dx + r)
            j0 = max(0, -dx)
            j1 = min(w, w - dx)
            if j1 <= j0:  # the offset leaves a film narrower than it: no pair (weights stay 0)
                continue
            floor = min_centre if dy == 0 and dx == 0 else 0.0
            for b in range(nk):
                offset_distances(guide, var, dy, dx, i0, i1, f, k2s[b], eps, clamp, pd, vs, ic, dist)
                for rr in range(n_rows):
                    qi = i0 + rr + dy
                    if qi < 0 or qi >= h:
                        continue
                    dst = wts[b, o, rr * w + j0:rr * w + j1]
                    d0 = dist[0, rr, j0:j1]
                    for t in range(j1 - j0):  # element loop, not a slice assignment (see engine._corr2_rows)
                        dmax[t] = d0[t]
                    for ch in range(1, cg):  # the largest channel distance (slices: vectorised, see offset_distances)
                        dc = dist[ch, rr, j0:j1]
                        for t in range(j1 - j0):
                            dmax[t] = max(dmax[t], dc[t])
                    for t in range(j1 - j0):
                        dst[t] = max(exp_neg(max(float(dmax[t]), 0.0)), floor)
    # 2. per pixel: the window's design, weights and colours as contiguous rows (d rounded up to even,
    # the extra row 0), the normal equations as 2 x 2 blocks of dot products over the window
    n = side * side
    # the normal equations' sums run over the window padded with zero weights and zero rows to a multiple of
    # NE_PAD positions: their vectorised loops then end without a scalar remainder (a window of 361 positions: 368)
    npad = (n + NE_PAD - 1) // NE_PAD * NE_PAD
    de = d + (d & 1)
    xt = np.zeros((de, npad))
    yt = np.zeros((nc, npad))
    yp = np.zeros((nc, n))
    wv = np.zeros(npad)
    a = np.zeros((de, de))
    bm = np.zeros((d, nc))
    tsol = np.zeros(max(d, nc))
    zt = np.zeros((de, LEVERAGE_BLOCK)) if leverage else np.zeros((0, LEVERAGE_BLOCK))
    lev = np.zeros(n) if leverage else np.zeros(0)
    fit = np.zeros(nk, np.bool_)
    inv_r = 1.0 / max(r, 1)
    for dy in range(-r, r + 1):  # the pixel-offset columns are the same for every window
        for dx in range(-r, r + 1):
            t = (dy + r) * side + (dx + r)
            xt[0, t] = 1.0
            xt[1, t] = dx * inv_r
            xt[2, t] = dy * inv_r
    for rr in range(n_rows):
        i = i0 + rr
        for j in range(w):
            if stride > 1:
                _fits(wts, fit, i, j, rr * w + j, r, stride, h, w, min_weight)
                if not fit.any():
                    continue
            for m in range(nf):
                fc = fpad[m, i + r, j + r]
                xm = xt[3 + m]
                for dy in range(side):
                    src = fpad[m, i + dy, j:j + side]
                    dst = xm[dy * side:(dy + 1) * side]
                    for u in range(side):
                        dst[u] = src[u] - fc
            for c in range(nc):
                yc = yt[c]
                for dy in range(side):
                    src = ypad[c, i + dy, j:j + side]
                    dst = yc[dy * side:(dy + 1) * side]
                    for u in range(side):
                        dst[u] = src[u]
            for b in range(nk):
                if stride > 1 and not fit[b]:
                    continue
                for t in range(n):
                    wv[t] = float(wts[b, t, rr * w + j])
                _normal_equations(xt, wv, yt, a, bm, d, de, npad)
                s0 = a[0, 0]
                for p in range(1, d):
                    a[p, p] += ridge * s0
                _solve_spd(a, bm, d, nc, tsol)
                _predict(xt, bm, yp, d, n)
                if leverage:
                    _leverages(a, xt, zt, lev, d, n)
                # 3. each fit predicts its window: acc(q) += w_pq x_q^T beta_p
                # (three colours a pass along the window's row: one load of each weight for three products)
                ab = acc[b]
                for dy in range(side):
                    ws = wv[dy * side:(dy + 1) * side]
                    c = 0
                    while c + 2 < nc:
                        d0, d1, d2 = ab[c, rr + dy, j:j + side], ab[c + 1, rr + dy, j:j + side], ab[c + 2, rr + dy,
                                                                                                  j:j + side]
                        s0 = yp[c, dy * side:(dy + 1) * side]
                        s1 = yp[c + 1, dy * side:(dy + 1) * side]
                        s2 = yp[c + 2, dy * side:(dy + 1) * side]
                        for u in range(side):
                            wu = ws[u]
                            d0[u] += wu * s0[u]
                            d1[u] += wu * s1[u]
                            d2[u] += wu * s2[u]
                        c += 3
                    while c < nc:
                        dst = ab[c, rr + dy, j:j + side]
                        src = yp[c, dy * side:(dy + 1) * side]
                        for u in range(side):
                            dst[u] += ws[u] * src[u]
                        c += 1
                    dst = ab[nc, rr + dy, j:j + side]
                    for u in range(side):
                        dst[u] += ws[u]
                    if leverage:
                        dst = ab[nc + 1, rr + dy, j:j + side]
                        ls = lev[dy * side:(dy + 1) * side]
                        for u in range(side):
                            dst[u] += ws[u] * ws[u] * ls[u]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _fits(wts, fit, i, j, col, r, s, h, w, min_weight):
    """fit[b]: pixel (i, j) fits a window for bandwidth b (see :func:`_band`'s ``stride``); ``wts[b, o, col]``
    is its weight of the window position o.  The weights of the grid pixels p in its window approximate
    those the grid's windows give it (w_qp for w_pq: the same patch pairs, the variance terms swapped), and
    need nothing from other bands."""
    on_grid = i % s == 0 and j % s == 0
    side = 2 * r + 1
    dy0 = (-((i - r) % s)) % s - r  # the first dy >= -r with (i + dy) a multiple of s
    dx0 = (-((j - r) % s)) % s - r
    for b in range(fit.shape[0]):
        if on_grid:
            fit[b] = True
            continue
        cover = 0.0
        for dy in range(dy0, r + 1, s):
            for dx in range(dx0, r + 1, s):
                cover += wts[b, (dy + r) * side + (dx + r), col]
        fit[b] = cover < min_weight


@numba.njit(cache=True, nogil=True)
def _gather(accs, kb, r, band, b0, out):
    """Add bandwidth ``kb``'s sums of bands b0, b0 + 1, ... (accs[k, kb]: band b0 + k) to out (C + 1, H, W),
    in band order, serially (bands overlap by 2r rows): each pixel's sum is the same whichever bands are
    held at once."""
    h = out.shape[1]
    n_bands = min((h + band - 1) // band - b0, accs.shape[0])
    for k in range(n_bands):
        top = (b0 + k) * band - r
        for t in range(accs.shape[3]):
            i = top + t
            if 0 <= i < h:
                for c in range(out.shape[0]):
                    for j in range(out.shape[2]):
                        out[c, i, j] += accs[k, kb, c, t, j + r]


def _accumulate(args, accs, outs, r, n_bands, threads) -> None:
    """Every band's windows (:func:`_band` with ``args``), BANDS_PER_THREAD bands per thread at a time on the
    thread pool, added to ``outs`` (one (C + 1 [+ 1], H, W) per bandwidth) in band order."""
    for b0 in range(0, n_bands, accs.shape[0]):
        parallel_calls(_band, [(*args, BAND, b0 + t, accs[t]) for t in range(min(accs.shape[0], n_bands - b0))],
                       threads)
        for kb in range(len(outs)):
            _gather(accs, kb, r, BAND, b0, outs[kb])


def feature_scale(plane) -> tuple[float, float]:
    """The mean and standard deviation by which :func:`standardise` scales one feature plane (H, W):
    ``(mean, deviation of the plane less its mean)``, both over the plane.

    A tiled reconstruction computes them once on the film's plane and hands them to every tile
    (``feature_scales`` of :func:`collaborative_regression`): a tile's own would scale its ridge
    differently.  Taken of a contiguous float64 copy, as the untiled regression takes them: a
    strided view sums in another order."""
    f = np.array(plane, dtype=np.float64, order="C", copy=True)
    mean = f.mean()
    f -= mean
    return float(mean), float(f.std())


def _standard_plane(plane, scale=None) -> np.ndarray:
    """One feature plane (H, W) as a contiguous float64 copy shifted and scaled to mean 0 and standard
    deviation 1 (a constant plane: shifted only); ``scale``: the ``(mean, deviation)`` to use instead of
    the plane's own (:func:`feature_scale`).  The mean and deviation of the contiguous copy: a strided
    view sums in another order."""
    f = np.array(plane, dtype=np.float64, order="C", copy=True)
    if scale is None:
        f -= f.mean()
        sd = f.std()
    else:
        mean, sd = scale
        f -= mean
    if sd > 0:
        f /= sd
    return f


def standardise(features, scales=None) -> np.ndarray:
    """Feature planes (D, H, W) shifted and scaled to mean 0 and standard deviation 1 over the image
    (a constant plane: shifted only), so that one ridge suits every feature; ``scales``: D
    ``(mean, deviation)`` pairs to use instead of the planes' own (:func:`feature_scale`)."""
    f = np.array(features, dtype=np.float64, copy=True)
    for m in range(f.shape[0]):
        f[m] = _standard_plane(f[m], None if scales is None else scales[m])
    return f


def collaborative_regression(image, guide, variance, features, *, radius: int = 9, patch: int = 3, k: float = 1.0,
                             variance_scale: float = 2.0, ridge: float = RIDGE, threads: int | None = None,
                             return_weights: bool = False, return_centre_weight: bool = False, stride: int = 1,
                             min_weight: float = MIN_COVER_WEIGHT, feature_scales=None):
    """Collaborative first-order regression of ``image`` on ``features``, weighted by NL-means of ``guide``.

    Parameters
    ----------
    image : ndarray (H, W, C), or a sequence of them
        The colour regressed (HDR, never clipped); a sequence is regressed as
        its arrays concatenated on the channel axis, without that copy.
    guide : ndarray (H, W, Cg)
        The image the NL-means weights compare (NFOR: the *other* half
        buffer's colour, so the weights do not correlate with the noise of
        ``image``).
    variance : ndarray (H, W, Cg)
        Variance of the guide's pixel values before ``variance_scale``.
    features : ndarray (H, W, D)
        Feature channels (standardised here: :func:`standardise`); D may be 0.
    radius, patch, k : int, int, float
        Window (2 radius + 1)^2 (NFOR: 9), NL-means patch (2 patch + 1)^2
        (3) and bandwidth (0.5 and 1.0 as the two candidates).
    variance_scale : float
        Factor on ``variance`` (2: half buffers with the full buffer's variance).
    ridge : float
        Ridge on the non-constant columns, times the window's total weight.
    return_weights : bool
        Also return the per-pixel sum of the weights of the predictions
        averaged (the collaborative denominator).
    return_centre_weight : bool
        Also return each pixel's centre weight ``w_ii``, the derivative of
        its output by its own input value, ``sum_p w_pi^2 x_i^T A_p^-1 x_i
        / sum_p w_pi``: with a guide and features independent of ``image``
        the filter is linear in it, and Stein's estimate of its MSE is
        exact with this ``w_ii``
        (:func:`mcrecon.methods.auto.estimates.sure`).  Costs about half
        the regression again.
    stride : int
        Fit a window at every ``stride``-th pixel of every ``stride``-th
        row only (1: every pixel, the paper); each fit still predicts its
        whole window, and each pixel averages the windows that cover it.
        A pixel whose own weights of the grid pixels in its window sum
        below ``min_weight`` (its patch is alike in few of theirs: a thin
        edge, a firefly, the grid's windows would leave it nearly
        unweighted) fits its own window too, as with stride 1.  Every
        weight is still computed; the normal equations, solves and scatters
        drop to the grid's pixels and those.
    min_weight : float
        With ``stride`` > 1: the grid weight below which a pixel fits its
        own window (where its own window would give it weight 1).
    feature_scales : sequence of D (mean, deviation) pairs, optional
        Standardise the features by these (:func:`feature_scale` of a
        larger image's planes: a tile of a film takes the film's) instead
        of their own mean and deviation over ``features``.

    Returns
    -------
    ndarray (H, W, C) float64, then (H, W) weights with ``return_weights``
    and (H, W) centre weights with ``return_centre_weight``
    """
    return collaborative_regressions(image, guide, variance, features, ks=(k,), radius=radius, patch=patch,
                                     variance_scale=variance_scale, ridge=ridge, threads=threads,
                                     return_weights=return_weights, return_centre_weight=return_centre_weight,
                                     stride=stride, min_weight=min_weight, feature_scales=feature_scales)[0]


def collaborative_regressions(image, guide, variance, features, *, ks, radius: int = 9, patch: int = 3,
                              variance_scale: float = 2.0, ridge: float = RIDGE, threads: int | None = None,
                              return_weights: bool = False, return_centre_weight: bool = False, stride: int = 1,
                              min_weight: float = MIN_COVER_WEIGHT, feature_scales=None) -> list:
    """:func:`collaborative_regression` of one image for several bandwidths ``ks`` in one pass.

    The bandwidths share the guide, the design and the colour: each
    pixel's window is gathered once for all of them, and each bandwidth's
    result is bit-identical to :func:`collaborative_regression` with that
    ``k`` alone (the same operations in the same order).  NFOR's candidates
    (k = 0.5 and 1.0 for each half) are such a set.

    Parameters
    ----------
    ks : sequence of float
        The NL-means bandwidths, one result each (at least one).
    image, guide, variance, features, radius, patch, variance_scale, ridge, threads, return_weights,
    return_centre_weight, stride, min_weight, feature_scales
        As :func:`collaborative_regression` (with a stride, each bandwidth's
        own weights choose its fallback windows: still bit-identical to a
        call with that bandwidth alone).

    Returns
    -------
    list, one entry per bandwidth, each what :func:`collaborative_regression` returns
    """
    ks = [float(k) for k in ks]
    if not ks:
        raise ValueError("collaborative_regressions: no bandwidth")
    # the colours as given (several: their planes written into the padded planes below one after the
    # other, so no concatenated copy of them sits beside those)
    parts = [np.asarray(a, dtype=np.float64) for a in (image if isinstance(image, (list, tuple)) else [image])]
    parts = [a[..., None] if a.ndim == 2 else a for a in parts]
    if not parts or any(a.shape[:2] != parts[0].shape[:2] for a in parts):
        raise ValueError("collaborative_regression: the colours' shapes differ: "
                         f"{[a.shape for a in parts]} (H, W[, C])")
    g = as_planes(guide, np.float32)
    v = scaled_planes(variance, variance_scale)
    feats = np.asarray(features, dtype=np.float64)
    if feats.ndim == 2:
        feats = feats[..., None]
    h, w = parts[0].shape[:2]
    nc = sum(a.shape[2] for a in parts)
    if g.shape[1:] != (h, w) or v.shape != g.shape or feats.shape[:2] != (h, w):
        raise ValueError(f"collaborative_regression: shapes differ: image {(h, w, nc)}, guide {g.shape[1:]}, "
                         f"variance {v.shape[1:]}, features {feats.shape} (H, W[, C])")
    if feature_scales is not None and len(feature_scales) != feats.shape[2]:
        raise ValueError(f"collaborative_regression: {len(feature_scales)} feature scales for "
                         f"{feats.shape[2]} feature planes")
    r = int(radius)
    s = int(stride)
    if s < 1 or s > r + 1:
        raise ValueError(f"collaborative_regression: stride {stride!r}: 1 to radius + 1 = {r + 1} (every pixel "
                         "then lies in a fitted window)")
    n_bands = (h + BAND - 1) // BAND
    planes = nc + 1 + bool(return_centre_weight)
    # the kernel's padded planes are filled in place, one plane at a time (no unpadded copy of the colour or
    # of the standardised features beside them: 14 float64 values per pixel fewer at the peak with 6
    # channels and 8 features)
    ypad = np.zeros((nc, h + 2 * r, w + 2 * r))
    c = 0
    for a in parts:
        for ca in range(a.shape[2]):
            ypad[c, r:r + h, r:r + w] = a[..., ca]
            c += 1
    del parts
    fpad = np.zeros((feats.shape[2], h + 2 * r, w + 2 * r))
    for m in range(feats.shape[2]):
        fpad[m, r:r + h, r:r + w] = _standard_plane(feats[..., m], None if feature_scales is None
                                                    else feature_scales[m])
    nk = len(ks)
    outs = [np.zeros((planes, h, w)) for _ in range(nk)]
    nt = n_threads(threads)
    # BANDS_PER_THREAD bands per thread at a time, on the thread pool: the bands' private accumulators
    # (each 1 + 2r / BAND times its rows) are a few megabytes whatever the image, not twice the output
    accs = np.empty((min(n_bands, BANDS_PER_THREAD * nt), nk, planes, BAND + 2 * r, w + 2 * r))
    k2s = np.array([k ** 2 for k in ks], np.float32)  # each k^2 rounded to float32, as the distances use it
    common = (ypad, g, v, fpad, r, int(patch), k2s, float(ridge), np.float32(NLM_EPS),
              np.float32(DISTANCE_CLAMP), MIN_CENTER_WEIGHT, bool(return_centre_weight))
    _accumulate(common + (s, float(min_weight)), accs, outs, r, n_bands, threads)
    del accs, ypad, fpad
    results = []
    for out in outs:
        # the quotients in place: no second image beside the sums
        if return_centre_weight:
            out[nc + 1] /= out[nc]
        out[:nc] /= out[nc]
        res = np.moveaxis(out[:nc], 0, 2)
        extra = ((out[nc],) if return_weights else ()) + ((out[nc + 1],) if return_centre_weight else ())
        results.append((res,) + extra if extra else res)
    return results

"""NL-means weights with the variance-normalised patch distance, as NFOR uses them.

Bitterli et al. 2016 (NFOR) weight every pixel pair (p, q = p + o) of a
search window with the NL-means weight of Rousselle, Knaus, Zwicker 2012:
per channel c, the pixel distance

    d_c(s, s + o) = ((u_c(s) - u_c(s+o))^2 - (V_c(s) + min(V_c(s), V_c(s+o))))
                    / (eps + k^2 (V_c(s) + V_c(s+o))),     clamped at 1e4,

averaged over the (2f+1)^2 patch pixels s around p (only pairs with s and
s + o inside the image), gives the patch distance D_c(p, o).  The weight
of a channel is ``exp(-max(0, D_c))``; a weight shared by all channels (the
regression's) is the smallest of the channels' weights, i.e. uses the
largest channel distance (the reference implementation's choice, Tungsten's
``src/denoiser/NlMeans.hpp``; Rousselle 2012 average the channels instead).
``V`` is the variance of the guide's pixel values: the variance of the full
buffer's mean times ``variance_scale`` (2 for a half buffer, whose mean has
twice the variance of the mean of all samples).  The centre weight is at
least 1e-4, so a pixel always keeps some of itself.

:func:`offset_distances` is the one compiled kernel of the distance (also used
by the regression), :func:`nlmeans_filter` the per-channel NL-means filter
of an image guided by another (feature prefiltering, MSE and selection-map
filtering).
"""

from __future__ import annotations

import numba
import numpy as np

from .engine import parallel_calls

__all__ = ["NLM_EPS", "DISTANCE_CLAMP", "MIN_CENTER_WEIGHT", "nlmeans_filter", "nlmeans_filter_shared", "as_planes", "exp_neg",
           "offset_distances", "scaled_planes"]

#: eps of the distance's denominator (0 / 0 on noise-free pixels); the reference implementation's value.
NLM_EPS = 1e-7
#: Pixel distances are clamped here (a huge outlier then counts as "very different", not as infinity).
DISTANCE_CLAMP = 1e4
#: Smallest centre weight: a pixel whose own patch distance is large still keeps part of itself.
MIN_CENTER_WEIGHT = 1e-4
#: Rows per band of the parallel kernels; results do not depend on it.
BAND = 16


@numba.njit(cache=True, nogil=True, error_model="numpy")
def exp_neg(t):
    """exp(-t) for t >= 0 (float64), vectorisable: 0 beyond t = 80, elsewhere within 1e-9 relative.

    ``math.exp`` is a libm call LLVM does not vectorise (no SVML here), and
    the weights take one exp per pixel pair and channel: the largest cost of
    the NL-means kernels once the rest is vectorised.  exp(-t) =
    exp(-t / 256)^256: a degree-9 Taylor polynomial on [0, 80 / 256]
    (truncation 2.4e-12 relative) then eight squarings (which double the
    relative error each: 6e-10).  A weight below exp(-80) = 1.8e-35 is
    negligible beside the centre weight (at least 1e-4), so it is 0.
    """
    u = min(t, 80.0) * (1.0 / 256.0)
    p = 1.0 + u * (-1.0 + u * (1.0 / 2.0 + u * (-1.0 / 6.0 + u * (1.0 / 24.0 + u * (
        -1.0 / 120.0 + u * (1.0 / 720.0 + u * (-1.0 / 5040.0 + u * (1.0 / 40320.0 + u * (-1.0 / 362880.0)))))))))
    for _ in range(8):
        p = p * p
    return p if t <= 80.0 else 0.0


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _box_rows(pd, r0, f, vs):
    """vs[j] = sum of pd[r0 .. r0 + 2f, j] in float64, left to right (as a sequential sum): the first row of a
    band; :func:`_slide` moves it down a row.

    The sum written as one expression per element for the usual patch radii: LLVM vectorises a loop,
    not a runtime-length inner loop, and one pass is 3x faster than adding row after row (measured)."""
    wp = vs.shape[0]
    if f == 0:
        p0 = pd[r0]
        for j in range(wp):
            vs[j] = np.float64(p0[j])
    elif f == 1:
        p0, p1, p2 = pd[r0], pd[r0 + 1], pd[r0 + 2]
        for j in range(wp):
            vs[j] = np.float64(p0[j]) + np.float64(p1[j]) + np.float64(p2[j])
    elif f == 2:
        p0, p1, p2, p3, p4 = pd[r0], pd[r0 + 1], pd[r0 + 2], pd[r0 + 3], pd[r0 + 4]
        for j in range(wp):
            vs[j] = np.float64(p0[j]) + np.float64(p1[j]) + np.float64(p2[j]) + np.float64(p3[j]) + np.float64(p4[j])
    elif f == 3:
        p0, p1, p2, p3, p4, p5, p6 = pd[r0], pd[r0 + 1], pd[r0 + 2], pd[r0 + 3], pd[r0 + 4], pd[r0 + 5], pd[r0 + 6]
        for j in range(wp):
            vs[j] = (np.float64(p0[j]) + np.float64(p1[j]) + np.float64(p2[j]) + np.float64(p3[j]) + np.float64(p4[j]) + np.float64(p5[j])
                     + np.float64(p6[j]))
    else:
        for j in range(wp):
            vs[j] = 0.0
        for b in range(2 * f + 1):
            src = pd[r0 + b]
            for j in range(wp):
                vs[j] += np.float64(src[j])


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _slide(vs, enter, leave, n):
    """vs[j] += enter[j] - leave[j] in float64 (the float32 rows exactly converted); the number of NaN
    sums (a NaN that left the patch stays in a running sum: the caller then sums the row afresh)."""
    bad = 0
    for j in range(n):
        v = vs[j] + (np.float64(enter[j]) - np.float64(leave[j]))
        vs[j] = v
        bad += v != v
    return bad


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _box_cols(v, n, f, inv_r, inv_cols, out):
    """out[t] = (sum of v[t .. t + 2f], left to right) * inv_r * inv_cols[t] for t < n, in float64, then
    rounded to out's type: the patch's row sums and its mean in one pass (no stored sums read back).
    The sum written as one expression per element for the usual patch radii (see :func:`_box_rows`)."""
    if f == 0:
        for t in range(n):
            out[t] = v[t] * inv_r * inv_cols[t]
    elif f == 1:
        a, b, c = v[0:n], v[1:n + 1], v[2:n + 2]
        for t in range(n):
            out[t] = (a[t] + b[t] + c[t]) * inv_r * inv_cols[t]
    elif f == 2:
        a, b, c, d, e = v[0:n], v[1:n + 1], v[2:n + 2], v[3:n + 3], v[4:n + 4]
        for t in range(n):
            out[t] = (a[t] + b[t] + c[t] + d[t] + e[t]) * inv_r * inv_cols[t]
    elif f == 3:
        a, b, c, d, e, g, k = v[0:n], v[1:n + 1], v[2:n + 2], v[3:n + 3], v[4:n + 4], v[5:n + 5], v[6:n + 6]
        for t in range(n):
            out[t] = (a[t] + b[t] + c[t] + d[t] + e[t] + g[t] + k[t]) * inv_r * inv_cols[t]
    else:
        for t in range(n):
            s = 0.0
            for b in range(2 * f + 1):
                s += v[t + b]
            out[t] = s * inv_r * inv_cols[t]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def offset_distances(guide, var, dy, dx, i0, i1, f, k2, eps, clamp, pd, vs, inv_cols, out):
    """Patch distances D_c(p, o) of offset o = (dy, dx) for the pixels p of rows [i0, i1).

    guide, var : (C, H, W) float32.  Scratch: pd (C, i1 - i0 + 2f, W + 2f) float32, the pixel distances
    d_c(s, s + o) of the rows s the patches cover, 0 where s or s + o is outside the image and in the f
    columns of padding each side; vs, inv_cols (W + 2f) float64.  out : (C, i1 - i0, W) float32, the patch-mean
    distance where q = p + o lies in the image (elsewhere left unspecified: the callers skip those pairs).
    Every loop runs along a row without a carried dependency (LLVM vectorises them): the pixel distances
    once per offset, then per patch the (2f + 1) rows and (2f + 1) columns summed directly, in float64
    (:func:`_box_rows`, :func:`_box_cols`).
    """
    c, h, w = guide.shape
    rows = i1 - i0 + 2 * f
    wp = w + 2 * f
    j0 = max(0, -dx)
    j1 = min(w, w - dx)
    for ch in range(c):
        for t in range(rows):
            s = i0 - f + t
            qs = s + dy
            row = pd[ch, t]
            for jj in range(wp):
                row[jj] = 0.0
            if 0 <= s < h and 0 <= qs < h:
                # slices indexed from 0: numba then knows the indices are not negative (no wraparound
                # test), which is what lets LLVM vectorise the loop
                gp, gq = guide[ch, s, j0:j1], guide[ch, qs, j0 + dx:j1 + dx]
                vp_, vq_ = var[ch, s, j0:j1], var[ch, qs, j0 + dx:j1 + dx]
                dst = row[j0 + f:j1 + f]
                for t2 in range(j1 - j0):
                    vp = vp_[t2]
                    vq = vq_[t2]
                    diff = gp[t2] - gq[t2]
                    d = (diff * diff - (vp + min(vp, vq))) / (eps + k2 * (vp + vq))
                    dst[t2] = min(d, clamp)
    for t2 in range(j1 - j0):  # 1 / the patch's columns s with s and s + dx inside the image
        j = j0 + t2
        inv_cols[t2] = 1.0 / (min(j + f + 1, j1) - max(j - f, j0))
    n = j1 - j0
    last = 2 * f + 1
    for ch in range(c):
        pc = pd[ch]
        for rr in range(i1 - i0):
            # the patch's column sums: the first row's directly, then running (the row entering the patch
            # added, the one leaving it subtracted: two operations per pixel whatever f)
            if rr == 0 or _slide(vs, pc[rr - 1 + last], pc[rr - 1], wp):
                _box_rows(pc, rr, f, vs)
            i = i0 + rr
            # rows s of the patch with s and s + dy inside the image
            nr = min(i + f + 1, h, h - dy) - max(i - f, 0, -dy)
            if nr <= 0:
                continue
            _box_cols(vs[j0:], n, f, 1.0 / nr, inv_cols, out[ch, rr, j0:j1])


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _nlm_band(imgs, guide, var, r, f, k2, eps, clamp, min_centre, i0, i1, num, den):
    """Rows [i0, i1) of the NL-means sums of every image of ``imgs`` (M, C, H, W) with the one set of weights
    of ``guide``: num (M, C, H, W) += w * image, den (C, H, W) += w.  The distances and each weight are
    computed once for all M images (each image's sums are the same operations in the same order as with
    M = 1)."""
    m_img, c, h, w = imgs.shape
    cg = guide.shape[0]
    pd = np.zeros((cg, i1 - i0 + 2 * f, w + 2 * f), np.float32)
    vs = np.zeros(w + 2 * f)
    ic = np.zeros(w + 2 * f)
    dist = np.zeros((cg, i1 - i0, w), np.float32)
    wrow = np.zeros(w)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            offset_distances(guide, var, dy, dx, i0, i1, f, k2, eps, clamp, pd, vs, ic, dist)
            j0 = max(0, -dx)
            j1 = min(w, w - dx)
            floor = min_centre if dy == 0 and dx == 0 else 0.0  # max(wt, 0) = wt: the same loop everywhere
            for rr in range(i1 - i0):
                i = i0 + rr
                qi = i + dy
                if qi < 0 or qi >= h:
                    continue
                for ch in range(c):
                    dd = dist[ch, rr, j0:j1]
                    wr = wrow[:j1 - j0]
                    de = den[ch, i, j0:j1]
                    for t2 in range(j1 - j0):
                        wt = max(exp_neg(max(float(dd[t2]), 0.0)), floor)
                        wr[t2] = wt
                        de[t2] += wt
                    for m in range(m_img):
                        src = imgs[m, ch, qi, j0 + dx:j1 + dx]
                        nu = num[m, ch, i, j0:j1]
                        for t2 in range(j1 - j0):
                            nu[t2] += wr[t2] * src[t2]


def as_planes(a, dtype=np.float64) -> np.ndarray:
    """(H, W, C) or (H, W) -> contiguous (C, H, W) planes (the kernels' inner loops run along rows)."""
    a = np.asarray(a, dtype=np.float64)
    if a.ndim == 2:
        a = a[..., None]
    return np.ascontiguousarray(np.moveaxis(a, 2, 0), dtype=dtype)


def scaled_planes(variance, scale) -> np.ndarray:
    """``variance`` (H, W, C) or (H, W) times ``scale``, as contiguous float32 planes (C, H, W): the product
    in float64, then rounded, one plane at a time (no float64 copy of the whole image)."""
    a = np.asarray(variance, dtype=np.float64)
    a = a[..., None] if a.ndim == 2 else a
    out = np.empty((a.shape[2],) + a.shape[:2], np.float32)
    for c in range(a.shape[2]):
        out[c] = a[..., c] * float(scale)
    return out


def nlmeans_filter(image, guide, variance, *, radius: int, patch: int, k: float, variance_scale: float = 1.0,
                   threads: int | None = None) -> np.ndarray:
    """NL-means of ``image`` with per-channel weights from ``guide``.

    Parameters
    ----------
    image, guide, variance : ndarray (H, W, C) or (H, W)
        The image filtered, the image the weights compare (channel c of
        the image takes channel c's weights) and the variance of the
        guide's pixel values (before ``variance_scale``).
    radius, patch : int
        Search window (2 radius + 1)^2, patch (2 patch + 1)^2.
    k : float
        Bandwidth: larger smooths more.
    variance_scale : float
        Factor on ``variance`` (2: the guide is a half buffer and
        ``variance`` that of the full buffer's mean).
    threads : int, optional
        Worker threads (:func:`mcrecon.filters.engine.n_threads`); the
        result does not depend on it.

    Returns
    -------
    ndarray, the shape of ``image``, float64
    """
    return nlmeans_filter_shared([image], guide, variance, radius=radius, patch=patch, k=k,
                                 variance_scale=variance_scale, threads=threads)[0]


def nlmeans_filter_shared(images, guide, variance, *, radius: int, patch: int, k: float,
                          variance_scale: float = 1.0, threads: int | None = None) -> list:
    """NL-means of several images with the one set of weights of ``guide``: the distances and weights are
    computed once for all of them.

    Each result is bit-identical to :func:`nlmeans_filter` of that image
    alone (the same weights, summed in the same order); the cost is that
    of one filter plus one multiply-add per image, pixel pair and channel.
    NFOR filters its bandwidths' MSE estimates this way (same guide, same
    parameters).

    Parameters
    ----------
    images : sequence of ndarray (H, W, C) or (H, W)
        The images filtered, each the shape of ``guide``.
    guide, variance, radius, patch, k, variance_scale, threads
        As :func:`nlmeans_filter`.

    Returns
    -------
    list of ndarray, each the shape of its image, float64
    """
    images = list(images)
    if not images:
        raise ValueError("nlmeans_filter_shared: no image")
    g = as_planes(guide, np.float32)
    imgs = np.empty((len(images),) + g.shape)
    for m, image in enumerate(images):
        a = np.asarray(image, dtype=np.float64)
        a = a[..., None] if a.ndim == 2 else a
        if a.shape[2:] + a.shape[:2] != g.shape:
            raise ValueError(f"nlmeans_filter: image {a.shape}, guide {g.shape} (C, H, W) differ")
        for c in range(a.shape[2]):
            imgs[m, c] = a[..., c]
    v = scaled_planes(variance, variance_scale)
    if v.shape != g.shape:
        raise ValueError(f"nlmeans_filter: guide {g.shape}, variance {v.shape} (C, H, W) differ")
    num = np.zeros(imgs.shape)
    den = np.zeros(g.shape)
    # bands of rows on the thread pool: each band writes its own rows of num and den
    h = g.shape[1]
    args = (imgs, g, v, int(radius), int(patch), np.float32(float(k) ** 2), np.float32(NLM_EPS),
            np.float32(DISTANCE_CLAMP), MIN_CENTER_WEIGHT)
    parallel_calls(_nlm_band, [(*args, i0, min(h, i0 + BAND), num, den) for i0 in range(0, h, BAND)], threads)
    del imgs
    out = []
    for m, image in enumerate(images):
        nm = num[m]
        nm /= den  # in place: no third image beside the sums
        res = np.moveaxis(nm, 0, 2)
        out.append(res[..., 0] if np.ndim(image) == 2 else res)
    return out

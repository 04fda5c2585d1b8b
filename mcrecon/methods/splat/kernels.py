"""The footprint of one sample (Suykens and Willems 2000, Eq. 3, 4): the Epanechnikov kernel and the scatter loops.

Discretisation (see ``docs/methods/splat.md``)
    The paper's *width* ``h`` is read as the kernel **diameter** in
    pixels (its numbers only agree that way: C' = 8 "gives a diameter of
    8-10 pixels", the minimum width is "one pixel wide"); the support
    radius is ``h / 2``.  The kernel is evaluated at the pixel centres
    ``(i + 1/2, j + 1/2)`` inside the support and the weights of one
    sample are divided by their sum, so each sample deposits exactly its
    energy (the constant ``2 / (pi r^2)`` of Eq. 4 cancels).  When no
    centre lies inside the support (possible only for ``r < 1/sqrt(2)``)
    the sample goes wholly to its own pixel, whose centre is always the
    nearest one; at the minimum width of one pixel every sample therefore
    lands in its own pixel, i.e. the method becomes the pixel mean.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ...errors import InputError
from ...filters.engine import parallel_calls
from ...core.samples import check_samples

__all__ = ["BOUNDARY_MODES", "epanechnikov", "splat"]

#: Boundary remedies (paper Sec. 5): ``mirror`` reflects the kernel weights
#: that fall outside the film back across the border (kernel mirroring),
#: ``renormalize`` normalises each footprint over the in-film centres only,
#: ``none`` normalises over the unbounded grid and drops what falls outside
#: (the paper's implementation: the border darkens).
BOUNDARY_MODES = ("mirror", "renormalize", "none")
_BOUNDARY_CODE = {"mirror": 0, "renormalize": 1, "none": 2}


def epanechnikov(x) -> np.ndarray:
    """Eq. 4: ``K(x) = (2/pi)(1 - |x|^2)`` for ``|x| < 1``, else 0 (2-D, integrates to 1).

    Parameters
    ----------
    x : array_like, shape (..., 2)
        Points in the plane (kernel coordinates).

    Returns
    -------
    ndarray, shape (...)
    """
    x = np.asarray(x, dtype=np.float64)
    q = np.sum(x * x, axis=-1)
    return np.where(q < 1.0, (2.0 / np.pi) * (1.0 - q), 0.0)


# ----------------------------------------------------------------------------
# numba scatter loops
# ----------------------------------------------------------------------------

@numba.njit(cache=True, nogil=True)
def _reflect(i, n):
    """Mirror index i into [0, n) about the film borders (repeatedly, for kernels wider than the film)."""
    period = 2 * n
    m = i % period
    if m < 0:
        m += period
    if m >= n:
        m = period - 1 - m
    return m


@numba.njit(cache=True, nogil=True, inline="always")
def _max_radius(radius):
    """The largest radius (0 for none or only non-positive ones)."""
    rmax = 0.0
    for k in range(radius.shape[0]):
        if radius[k] > rmax:
            rmax = radius[k]
    return rmax


@numba.njit(cache=True, nogil=True, inline="always")
def _scratch(radius):
    """Scratch buffers (weights, column and row indices) for the footprint of the widest sample."""
    side = 2 * int(math.ceil(_max_radius(radius))) + 2
    cap = side * side + 1  # + 1: the share a gated footprint keeps home
    return np.empty(cap), np.empty(cap, np.int64), np.empty(cap, np.int64)


@numba.njit(cache=True, nogil=True, inline="always")
def _film_index(i, n, mode, guided):
    """(index deposited to, index of the guide) of grid index i on a film of n: i itself on the film;
    off it, its mirror image (mode none deposits nothing: -1, and needs the mirror only for a guide)."""
    if 0 <= i < n:
        return i, i
    if mode == 2 and not guided:
        return -1, i
    m = _reflect(i, n)
    return (-1 if mode == 2 else m), m
@numba.njit(cache=True, nogil=True, inline="always")
def _same_pixel_stats(gs, fs, pj, pi, qj, qi, k2):
    """Whether neither the means nor the spreads of pixels p and q tell them apart, in every channel,
    nor their features.

    ``gs[..., c, :]`` holds (mean, squared standard error of the mean, log sample variance, its
    variance 2 / (n - 1)): the means must differ by at most k standard errors of their difference,
    and the log variances by at most k of theirs (the normal approximation of both).
    ``fs[..., c, :]`` holds (mean, sample variance + floor, slope along x, slope along y, squared
    standard error) of every feature component (none: a third axis of length 0 skips the test): the
    feature means must differ by at most k of the pixels' own feature spreads plus what the larger
    of their smooth slopes explains over the distance, and k standard errors of that
    (:func:`.consistent.feature_moments`); two pixels whose noise-free albedo (or normal, depth)
    jumps are on different surfaces."""
    if qj == pj and qi == pi:
        return True
    for c in range(gs.shape[2]):
        d = gs[qj, qi, c, 0] - gs[pj, pi, c, 0]
        if not d * d <= k2 * (gs[pj, pi, c, 1] + gs[qj, qi, c, 1]):
            return False
        d = gs[qj, qi, c, 2] - gs[pj, pi, c, 2]
        if not d * d <= k2 * (gs[pj, pi, c, 3] + gs[qj, qi, c, 3]):
            return False
    ax = abs(qi - pi)
    ay = abs(qj - pj)
    noise = k2 * (2.0 + 0.5 * (ax * ax + ay * ay))  # k^2 (variance of the difference and the slopes) / se^2
    for c in range(fs.shape[2]):
        d = fs[qj, qi, c, 0] - fs[pj, pi, c, 0]
        d2 = d * d
        spread = k2 * (fs[pj, pi, c, 1] + fs[qj, qi, c, 1])
        if d2 <= spread:  # within the spreads alone: passes whatever the slopes add (t^2 >= 0, never NaN)
            continue
        t = ax * max(abs(fs[pj, pi, c, 2]), abs(fs[qj, qi, c, 2])) + ay * max(abs(fs[pj, pi, c, 3]),
                                                                         abs(fs[qj, qi, c, 3]))
        t += math.sqrt(noise * max(fs[pj, pi, c, 4], fs[qj, qi, c, 4]))
        if not d2 <= spread + t * t:
            return False
    return True


@numba.njit(cache=True, nogil=True, inline="always")
def _centres(c, half, n, mode):
    """The indices j of the pixel centres j + 1/2 strictly within ``half`` of ``c`` (|j + 1/2 - c| < half
    <=> c - 1/2 - half < j < c - 1/2 + half), kept on the film (0 .. n - 1) under mode 1."""
    lo = int(math.floor(c - 0.5 - half)) + 1
    hi = int(math.ceil(c - 0.5 + half)) - 1
    if mode == 1:
        lo = max(lo, 0)
        hi = min(hi, n - 1)
    return lo, hi


@numba.njit(cache=True, nogil=True, inline="always")
def _footprint(x, y, r, h, w, mode, guide, guided, wbuf, ibuf, jbuf):
    """The pixel centres strictly inside the support of radius ``r`` around (x, y) and their weights.

    The weight of centre q is ``1 - |q - (x, y)|^2 / r^2``, times ``guide[q]`` when ``guided`` (then
    centres of weight <= 0 are left out; off-film centres use the guide of their mirror image).
    Film indices after the boundary mode go to ``ibuf``/``jbuf`` (-1: mode none, off the film).
    Returns (sum of the weights, number of entries).
    """
    r2 = r * r
    inv_r2 = 1.0 / r2
    jlo, jhi = _centres(y, r, h, mode)
    s = 0.0
    m = 0
    for j in range(jlo, jhi + 1):
        dy = j + 0.5 - y
        rem = r2 - dy * dy
        if rem <= 0.0:
            continue
        jj, jg = _film_index(j, h, mode, guided)
        half = math.sqrt(rem)
        ilo, ihi = _centres(x, half, w, mode)
        dy2 = dy * dy * inv_r2
        for i in range(ilo, ihi + 1):
            dx = i + 0.5 - x
            q = dx * dx * inv_r2 + dy2
            if q < 1.0:
                wt = 1.0 - q
                ii, ig = _film_index(i, w, mode, guided)
                if guided:
                    wt = wt * guide[jg, ig]
                    if not wt > 0.0:
                        continue
                s += wt
                wbuf[m] = wt
                ibuf[m] = ii
                jbuf[m] = jj
                m += 1
    return s, m


@numba.njit(cache=True, nogil=True, inline="always")
def _gated_footprint(x, y, r, h, w, mode, r_edge, wbuf, ibuf, jbuf, gs, fs, pj, pi, k2, seen, reach, key, gate_r):
    """The footprint of :func:`_footprint` (plain Epanechnikov weights, centred on the pixel (pj, pi)),
    gated: the weights still sum over the whole support, but a centre q receives
    ``1 - d^2 / min(r, r_edge[p], r_edge[q])^2`` only if its pixel passes :func:`_same_pixel_stats`
    against p (colour ``gs``, features ``fs``); the rest of its weight goes to p, as one last entry.
    Pair-symmetric: p sends q what q would send p.

    ``reach[t]`` holds, for the offset t = (j - pj, i - pi) within ``gate_r``, ``min(r_edge[p], r_edge[q])``
    where the gate passes and -1 where it refuses; it is valid where ``seen[t]`` holds ``key``, else it is
    computed here: the samples of one pixel (one ``key``, changed by the caller with the pixel) test each
    neighbour once.  Returns (sum of the weights, number of entries).
    """
    r2 = r * r
    inv_r2 = 1.0 / r2
    jlo, jhi = _centres(y, r, h, mode)
    side = 2 * gate_r + 1
    rp = r_edge[pj, pi]
    s = 0.0
    m = 0
    home = 0.0
    for j in range(jlo, jhi + 1):
        dy = j + 0.5 - y
        rem = r2 - dy * dy
        if rem <= 0.0:
            continue
        jj, jg = _film_index(j, h, mode, True)
        half = math.sqrt(rem)
        ilo, ihi = _centres(x, half, w, mode)
        dy2 = dy * dy * inv_r2
        trow = (j - pj + gate_r) * side + gate_r - pi
        for i in range(ilo, ihi + 1):
            dx = i + 0.5 - x
            q = dx * dx * inv_r2 + dy2
            if not q < 1.0:
                continue
            wt = 1.0 - q
            s += wt
            t = trow + i
            if seen[t] != key:
                seen[t] = key
                ig = i if 0 <= i < w else _reflect(i, w)
                reach[t] = min(rp, r_edge[jg, ig]) if _same_pixel_stats(gs, fs, pj, pi, jg, ig, k2) else -1.0
            re = reach[t]
            sent = 0.0
            if re > 0.0:
                d2 = q * r2
                if d2 < re * re:
                    sent = wt if re >= r else 1.0 - d2 / (re * re)
            home += wt - sent
            if not sent > 0.0:
                continue
            ii, _ = _film_index(i, w, mode, False)
            wbuf[m] = sent
            ibuf[m] = ii
            jbuf[m] = jj
            m += 1
    if home > 0.0:
        wbuf[m] = home
        ibuf[m] = pi
        jbuf[m] = pj
        m += 1
    return s, m


@numba.njit(cache=True, nogil=True, inline="always")
def _deposit_weights(out, v, e, wbuf, ibuf, jbuf, m, j0, j1):
    """Add ``v * (wbuf[t] * e)`` at each centre t of a footprint in the rows ``j0 <= j < j1`` of ``out``
    (a band of the film; mode none: off-film weight is lost)."""
    nc = out.shape[2]
    for t in range(m):
        ii = ibuf[t]
        jj = jbuf[t]
        if ii < 0 or not j0 <= jj < j1:
            continue
        wt = wbuf[t] * e
        for c in range(nc):
            out[jj, ii, c] += v[c] * wt


@numba.njit(cache=True, nogil=True, inline="always")
def _footprint_loop(pos, val, scale, radius, guide, guided, mode, out):
    """Deposit each sample's ``val * scale`` with a normalised (``guided``: guide-weighted) Epanechnikov
    footprint; the body of :func:`_splat_loop` and :func:`_splat_guided_loop`, inlined into each with
    ``guided`` a constant, so that each compiles only its own branches.

    ``radius[k] <= 0`` skips sample k (G = 0).  mode: 0 mirror,
    1 renormalise, 2 none (drop off-film weight).  Returns the number of
    samples that fell back to their own pixel (no centre covered, or only centres of guide 0).
    One pass computes the weights of the covered centres into a scratch
    buffer (with their film indices after mirroring), the second deposits
    them divided by their sum.
    """
    h, w, nc = out.shape
    wbuf, ibuf, jbuf = _scratch(radius)
    n_fallback = 0
    for k in range(pos.shape[0]):
        r = radius[k]
        if not r > 0.0:
            continue
        x = np.float64(pos[k, 0])
        y = np.float64(pos[k, 1])
        s, m = _footprint(x, y, r, h, w, mode, guide, guided, wbuf, ibuf, jbuf)
        if not s > 0.0:
            # No pixel centre inside the support (or none the guide lets in): the whole sample goes to
            # its own pixel (whose centre is the nearest one).
            n_fallback += 1
            px = min(max(int(math.floor(x)), 0), w - 1)
            py = min(max(int(math.floor(y)), 0), h - 1)
            e = scale[k]
            for c in range(nc):
                out[py, px, c] += val[k, c] * e
            continue
        e = scale[k] / s
        if nc == 3 and not guided:
            # the common RGB case, unrolled (about 1.3x faster)
            v0 = val[k, 0] * e
            v1 = val[k, 1] * e
            v2 = val[k, 2] * e
            for t in range(m):
                ii = ibuf[t]
                jj = jbuf[t]
                if ii < 0 or jj < 0:
                    continue  # mode none: weight outside the film is lost
                wt = wbuf[t]
                out[jj, ii, 0] += v0 * wt
                out[jj, ii, 1] += v1 * wt
                out[jj, ii, 2] += v2 * wt
            continue
        _deposit_weights(out, val[k], e, wbuf, ibuf, jbuf, m, 0, h)
    return n_fallback


@numba.njit(cache=True, nogil=True)
def _splat_loop(pos, val, scale, radius, mode, out):
    """Deposit each sample's ``val * scale`` with a normalised Epanechnikov footprint
    (:func:`_footprint_loop`)."""
    return _footprint_loop(pos, val, scale, radius, np.ones((1, 1)), False, mode, out)


#: Samples per call above which the scatter runs on _N_BLOCKS fixed blocks
#: in parallel, each into its own buffer, summed in block order: the result
#: depends on the inputs only (not on the thread count), as resuming needs.
_PARALLEL_MIN = 1 << 17
_N_BLOCKS = 2


def _scatter(pos, val, scale, radius, mode, out) -> int:
    """The scatter loop, on two cores for large batches (deterministic block split).

    Each block splats into its own buffer on the filters' thread pool (the
    loop is a ``nogil`` kernel; a ``parallel=True`` wrapper would cost a
    second compilation of it), and the buffers are added in block order.
    """
    n = pos.shape[0]
    if n < _PARALLEL_MIN:
        return int(_splat_loop(pos, val, scale, radius, mode, out))
    bufs = np.zeros((_N_BLOCKS,) + out.shape)
    cuts = [n * b // _N_BLOCKS for b in range(_N_BLOCKS + 1)]
    fb = parallel_calls(_splat_loop, [(pos[a:e], val[a:e], scale[a:e], radius[a:e], mode, bufs[b])
                                      for b, (a, e) in enumerate(zip(cuts[:-1], cuts[1:]))])
    for b in range(_N_BLOCKS):
        out += bufs[b]
    return int(sum(fb))


def splat(positions, values, widths, *, width: int, height: int, scale=1.0, boundary: str = "mirror",
          out: np.ndarray | None = None) -> np.ndarray:
    """Splat samples with normalised Epanechnikov footprints of the given diameters.

    Parameters
    ----------
    positions : array_like (N, 2)
        Film positions (x column, y row), inside [0, width) x [0, height).
    values : array_like (N, C)
    widths : array_like (N,) or scalar
        Kernel diameters in pixels (the paper's h); ``<= 0`` skips a sample.
    scale : array_like (N,) or scalar
        Energy multiplier per sample: sample k deposits ``values[k] * scale[k]`` in total.
    boundary : {'mirror', 'renormalize', 'none'}
        See :data:`BOUNDARY_MODES`.
    out : ndarray (H, W, C) float64, optional
        Accumulate into it (in place).

    Returns
    -------
    ndarray (H, W, C) float64
        With ``mirror`` or ``renormalize``, ``out.sum(axis=(0, 1))`` grows by
        exactly ``(values * scale).sum(axis=0)`` (up to rounding).

    Raises
    ------
    InputError
        Mis-shaped arrays, positions non-finite or off the film (the
        checks of :func:`mcrecon.core.samples.check_samples`), an unknown
        ``boundary``, an ``out`` of the wrong shape or dtype.  NaN or Inf
        *values* are splatted as given: apply a policy first
        (:func:`mcrecon.core.samples.apply_nonfinite`).
    """
    if boundary not in _BOUNDARY_CODE:
        raise InputError("splat", "boundary", f"{boundary!r}; valid: {', '.join(BOUNDARY_MODES)}")
    val = np.asarray(values)
    if val.ndim == 1:
        val = val[:, None]
    pos, val, _ = check_samples(positions, val, width=width, height=height,
                                n_channels=val.shape[1] if val.ndim == 2 else 1, where="splat")
    pos = np.ascontiguousarray(pos, dtype=np.float64)
    val = np.ascontiguousarray(val, dtype=np.float64)
    n = pos.shape[0]
    radius = np.ascontiguousarray(np.broadcast_to(np.asarray(widths, dtype=np.float64), (n,))) * 0.5
    sc = np.array(np.broadcast_to(np.asarray(scale, dtype=np.float64), (n,)))  # writable: one compiled signature
    if out is None:
        out = np.zeros((height, width, val.shape[1]))
    elif out.shape != (height, width, val.shape[1]) or out.dtype != np.float64:
        raise InputError("splat", "out", f"shape {out.shape} dtype {out.dtype}, expected "
                         f"{(height, width, val.shape[1])} float64")
    _scatter(pos, val, sc, radius, _BOUNDARY_CODE[boundary], out)
    return out


# ----------------------------------------------------------------------------
# Guided footprint (robust variant): Epanechnikov weights times a guide image
# ----------------------------------------------------------------------------

@numba.njit(cache=True, nogil=True)
def _splat_guided_loop(pos, val, scale, radius, guide, mode, out):
    """Like :func:`_splat_loop`, but the weight of centre q is ``(1 - |x|^2) * guide[q]``.

    Used by the robust variant for the *excess* of outlier samples, with
    the mean G of the 3x3 window around q as the guide: the energy goes
    where the neighbourhoods' samples say the image is bright, never into
    a pixel whose window saw only zeros (a caustic spike spreads along its
    ring rather than into the black beside it).  ``guide = 1`` gives plain
    Epanechnikov weights.  Weights are divided by their sum, so each sample deposits exactly
    ``val * scale``; when every covered centre has guide 0 the sample goes
    wholly to its own pixel.  Off-film centres use the guide of their
    mirror image; mode 1 (renormalise) clips the footprint, mode 2 (none)
    drops their share.
    """
    return _footprint_loop(pos, val, scale, radius, guide, True, mode, out)


@numba.njit(cache=True, nogil=True)
def _deposit_own_pixel(pos, val, scale, out):
    """Add ``val[k] * scale[k]`` to the pixel containing sample k (the one-pixel footprint)."""
    h = out.shape[0]
    w = out.shape[1]
    nc = out.shape[2]
    for k in range(pos.shape[0]):
        e = scale[k]
        if e == 0.0:
            continue
        px = min(max(int(math.floor(pos[k, 0])), 0), w - 1)
        py = min(max(int(math.floor(pos[k, 1])), 0), h - 1)
        for c in range(nc):
            out[py, px, c] += val[k, c] * e


@numba.njit(cache=True, nogil=True)
def _splat_gated_loop(pos, val, w_round, inv_counts, frac, radius, r_edge, gs, fs, k2, mode, out, k0, k1, j0, j1):
    """Like :func:`_splat_loop`, but a sample of pixel p reaches only the pixels q whose statistics ``gs``
    and features ``fs`` (third axis 0: none) do not tell them apart from p's at ``k = sqrt(k2)``
    (:func:`_same_pixel_stats`; off-film
    centres: their mirror image), and only within
    ``min(r_edge[p], r_edge[q])``; what the footprint would give elsewhere stays in p.  Normalised
    over the whole footprint, so each sample deposits exactly ``val * scale``, and pair-symmetric:
    a region of equal pixels keeps its values.  ``radius <= 0``: the sample goes to its own pixel.
    ``scale`` of sample k is ``w_round * inv_counts[p] * (1 - frac[k])`` (the share of the round that
    stays with the sample, not its outlier excess).  The gate's answer for a neighbour is computed once
    per run of consecutive samples of one pixel (a renderer's reply lists a pixel's samples together).

    Only the rows ``j0 <= j < j1`` of ``out`` receive deposits (a band; 0, H: the film), from the samples
    ``k0 <= k < k1`` (at least those that reach the band), and only the samples whose own pixel lies in
    them count as fallbacks (returned).  The samples are visited in order and every footprint is computed
    and normalised whole, so each pixel of the band receives the deposits the whole film's loop gives it,
    in the same order: bands run by separate threads (:func:`.bands.in_bands`) give the one-threaded
    image bit for bit.
    """
    h = out.shape[0]
    w = out.shape[1]
    nc = out.shape[2]
    wbuf, ibuf, jbuf = _scratch(radius)
    gate_r = int(math.ceil(_max_radius(radius))) + 1
    gate_seen = np.full((2 * gate_r + 1) ** 2, -1, np.int64)
    gate_reach = np.empty((2 * gate_r + 1) ** 2)
    gate_key = -1
    last = -1
    n_fallback = 0
    for k in range(k0, k1):
        px = min(max(int(math.floor(pos[k, 0])), 0), w - 1)
        py = min(max(int(math.floor(pos[k, 1])), 0), h - 1)
        r = radius[k]
        # rows from the pixel's to the band: a footprint reaches rows less than r away (mirroring folds
        # a row no further from the pixel), so a sample farther off gives the band nothing
        d = j0 - py if py < j0 else py - j1 + 1
        if d > 0 and not d < r:
            continue
        e = w_round * inv_counts[py, px] * (1.0 - frac[k])
        if e == 0.0:
            continue
        # Centred on the pixel centre, not the sample: normalised footprints of jittered positions are
        # no partition of unity (a flat field would come out noisy); footprints of one width centred
        # on the pixel grid are, so a stationary region keeps its expectation.
        x = px + 0.5
        y = py + 0.5
        s = 0.0
        m = 0
        if r > 0.0:
            if py * w + px != last:
                last = py * w + px
                gate_key += 1
            s, m = _gated_footprint(x, y, r, h, w, mode, r_edge, wbuf, ibuf, jbuf, gs, fs, py, px, k2, gate_seen,
                                    gate_reach, gate_key, gate_r)
        if not s > 0.0:
            if d <= 0:
                n_fallback += r > 0.0
                for c in range(nc):
                    out[py, px, c] += val[k, c] * e
            continue
        _deposit_weights(out, val[k], e / s, wbuf, ibuf, jbuf, m, j0, j1)
    return n_fallback


@numba.njit(cache=True, nogil=True, inline="always")
def _kernel_radius(radius, spread_radius, default_radius):
    """A sample's kernel radius as the width diagnostic counts it: ``radius`` where it is positive (an
    outlier's excess), else ``spread_radius`` where positive, else ``default_radius``."""
    if radius > 0.0:
        return radius
    return spread_radius if spread_radius > 0.0 else default_radius


@numba.njit(cache=True, nogil=True)
def _add_widths(pos, radius, spread_radius, default_radius, width_sum, width_n, k0, k1, j0, j1):
    """Add the kernel diameter of each sample ``k0 <= k < k1`` of the rows ``j0 <= j < j1`` to its pixel's sum
    (in sample order): ``radius`` where it is positive (an outlier's excess), else ``spread_radius`` where
    positive, else ``default_radius``."""
    h, w = width_sum.shape
    for k in range(k0, k1):
        py = min(max(int(math.floor(pos[k, 1])), 0), h - 1)
        if not j0 <= py < j1:
            continue
        r = _kernel_radius(radius[k], spread_radius[k], default_radius)
        if not r > 0.0:
            continue
        px = min(max(int(math.floor(pos[k, 0])), 0), w - 1)
        width_sum[py, px] += 2.0 * r
        width_n[py, px] += 1

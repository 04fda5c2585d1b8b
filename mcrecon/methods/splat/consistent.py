"""Splatting that filters (the default, ``spread="consistent"``): consistent samples spread too, never across an edge.

Every sample's part that is not an outlier's excess (:mod:`.outliers`) gets
Eq. 8's kernel, ``h = C N^-alpha (G / f)^(1/2)``, shrinking as its pixel's
sample count N grows, bounded twice by what the pixel statistics can see:

* **the gate**: a pixel q receives a share of a sample of pixel p only if,
  in every channel, ``|m_q - m_p| <= k sqrt(se_p^2 + se_q^2)`` (m the pixel
  means, se their standard errors) and ``|ln s_q^2 - ln s_p^2| <= k sqrt(2 /
  (n_p - 1) + 2 / (n_q - 1))`` (s^2 the sample variances): neither the means
  nor the spreads tell the two pixels apart.  For two pixels of the same
  distribution both standardised differences are about N(0, 1), so ``k``
  follows from a false-rejection rate (two-sided, Bonferroni over the two
  tests of every channel): :func:`gate_k`.  The spread test keeps a bright,
  noisy pixel (a caustic's) from exchanging with a dim, quiet neighbour
  whose mean its large standard error would not tell apart;
* **the gradient bound**: a sample of p reaches q only within
  ``min(r_p, r_q)``, ``r = k se / |grad m|`` (smallest over the channels,
  the gradient's own noise taken out: :func:`edge_radius`): spreading along
  the local colour gradient moves a sample's expectation by at most k
  standard errors of its pixel at the rim.  A pixel whose samples have no
  spread (se = 0) has no noise to remove and exchanges nothing;
* **the features** (when the samples carry them: albedo, normal, depth, any
  other): q also needs, in every feature component, ``(f_q - f_p)^2 <= k^2
  (s_p^2 + s_q^2)`` plus the change the feature's smooth slope explains over
  the distance (f the pixels' feature means, s^2 their feature sample
  variances: :func:`feature_moments`).  A feature is no noisy estimate to be
  averaged but what the pixel's samples hit: two pixels whose feature means
  lie further apart than their own spreads of it saw different surfaces (a
  texture edge the colour noise hides), while a feature that varies inside
  the pixels (an edge crossing one, defocus, motion) lets the colour decide.

The footprint is centred on the sample's pixel centre and normalised over
its whole support; what it would give a pixel the gate refuses, or beyond
the bound, stays in the sample's own pixel.  So a sample deposits exactly
its energy, and the exchange is pair-symmetric (p sends q the share q would
send p): a region of equal pixels keeps its values exactly.  (Centred on the
jittered sample position, normalised footprints are no partition of unity:
a flat field of 1 with 0.1 % noise came out with 5 % rms error at 32 spp.)
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import literal_unroll
from scipy.special import ndtri

from ...core.samples import one_float_dtype
from .bands import in_bands
from .outliers import _norm_of


def gate_k(rate: float, n_channels: int) -> float:
    """k of the gate: P(|z| > k) = rate / (2 n_channels) for z ~ N(0, 1) (two tests per channel)."""
    return float(ndtri(1.0 - rate / (4.0 * n_channels)))


def channel_sums(pos, val, width, height, sorted_rows=False):
    """Per pixel and channel the sums of the values and of their squares, (H, W, C) each (in sample order;
    in bands of rows on the filters' threads, :func:`.bands.in_bands`)."""
    s1 = np.zeros((height, width, val.shape[1]))
    s2 = np.zeros((height, width, val.shape[1]))
    in_bands(_add_channel_sums, one_float_dtype(pos, val) + (s1, s2), pos, height, sorted_rows=sorted_rows)
    return s1, s2


@numba.njit(cache=True, nogil=True)
def _add_channel_sums(pos, val, s1, s2, k0, k1, j0, j1):
    h, w, nc = s1.shape
    for k in range(k0, k1):
        py = min(max(int(math.floor(pos[k, 1])), 0), h - 1)
        if not j0 <= py < j1:
            continue
        px = min(max(int(math.floor(pos[k, 0])), 0), w - 1)
        for c in range(nc):
            v = np.float64(val[k, c])
            s1[py, px, c] += v
            s2[py, px, c] += v * v


class FeatureSums:
    """Cumulative per-pixel sums of every feature component and of its square (all rounds so far).

    The components of all features are stacked in the order first given (``names``, ``sizes``).
    Sums are of ``f - shift``, ``shift`` per pixel its first sample's value: a depth of 1000 +- 0.01
    keeps its spread (sums of squares of the raw values would cancel it away), and the sums of a
    pixel depend on its own samples only (a tile of the film sums them as the film does).
    """

    def __init__(self, width, height):
        self.width, self.height = int(width), int(height)
        self.names: tuple[str, ...] | None = None
        self.sizes: tuple[int, ...] = ()
        self.n = np.zeros((height, width))
        self.s1 = self.s2 = self.shift = None

    def add(self, pos, feats, where, sorted_rows=False):
        """Add the features (``{name: (N, k)}``, the rows of ``pos``) of one chunk (in bands of rows on the
        filters' threads, :func:`.bands.in_bands`)."""
        parts = self.parts(pos, feats, where)
        if not parts:
            return
        # each feature in its own precision (a renderer's float32 is widened exactly in the kernel),
        # not stacked: stacking the components was most of the cost
        pos = np.ascontiguousarray(pos)
        first = np.full(self.height * self.width, -1, np.int64)
        in_bands(_first_samples, (pos, self.n, first), pos, self.height, sorted_rows=sorted_rows)
        col = 0
        for x in parts:
            in_bands(_add_feature_sums, one_float_dtype(pos, x) + (col, first, self.shift, self.s1, self.s2), pos,
                     self.height, sorted_rows=sorted_rows)
            col += x.shape[1]

    def parts(self, pos, feats, where) -> list:
        """The features of a chunk checked against the earlier chunks' (names, components), each as an
        (N, k) array in its own precision ([] for none); the sums are allocated with the first."""
        from ...errors import InputError

        names = tuple(feats)
        if self.names is None:
            self.names = names
            self.sizes = tuple(int(np.shape(feats[k])[1]) if np.ndim(feats[k]) == 2 else 1 for k in names)
        elif names != self.names:
            raise InputError(where, "features", f"a round carries features {', '.join(names) or '(none)'}, "
                             f"earlier rounds {', '.join(self.names) or '(none)'}: every round must carry the same")
        if not names:
            return []
        parts = [np.asarray(feats[k]) for k in names]
        parts = [np.ascontiguousarray(x.reshape(len(pos), -1) if x.ndim != 2 else x) for x in parts]
        nf = sum(x.shape[1] for x in parts)
        if nf != sum(self.sizes):
            raise InputError(where, "features", f"{nf} components, earlier rounds {sum(self.sizes)}")
        if self.shift is None:
            self.shift = np.zeros((self.height * self.width, nf))
            self.s1 = np.zeros((self.height, self.width, nf))
            self.s2 = np.zeros((self.height, self.width, nf))
        return parts

    @property
    def any(self) -> bool:
        return self.s1 is not None


@numba.njit(cache=True, nogil=True)
def _first_samples(pos, n, first, k0, k1, j0, j1):
    """Count the samples ``k0 <= k < k1`` of each pixel of the rows ``j0 <= j < j1`` in ``n``; ``first[q]``: the
    index of the sample that sets pixel q's shift (its first sample ever, when it had none before), else
    left at -1."""
    h, w = n.shape
    for k in range(k0, k1):
        py = min(max(int(math.floor(pos[k, 1])), 0), h - 1)
        if not j0 <= py < j1:
            continue
        px = min(max(int(math.floor(pos[k, 0])), 0), w - 1)
        if n[py, px] == 0:
            first[py * w + px] = k
        n[py, px] += 1.0


@numba.njit(cache=True, nogil=True)
def _add_feature_sums(pos, f, col, first, shift, s1, s2, k0, k1, j0, j1):
    """Add one feature's components (columns ``col``... of the sums) of the samples ``k0 <= k < k1`` in sample
    order, to the pixels of the rows ``j0 <= j < j1``; a pixel's first sample sets its shift.  A non-finite
    component counts as 0 (a guide, not radiance, as check_features does)."""
    h, w = s1.shape[0], s1.shape[1]
    nf = f.shape[1]
    for k in range(k0, k1):
        py = min(max(int(math.floor(pos[k, 1])), 0), h - 1)
        if not j0 <= py < j1:
            continue
        px = min(max(int(math.floor(pos[k, 0])), 0), w - 1)
        q = py * w + px
        for c in range(nf):
            x = np.float64(f[k, c])
            if not math.isfinite(x):
                x = 0.0
            if first[q] == k:
                shift[q, col + c] = x
            d = x - shift[q, col + c]
            s1[py, px, col + c] += d
            s2[py, px, col + c] += d * d


def round_sums(pos, val, width, height, norm_code, weights, fsum, feats, where, sorted_rows=False):
    """The per-pixel sums of a round held in memory, in one pass over its samples (in bands of rows on the
    filters' threads, :func:`.bands.in_bands`): the round's counts and sums of G and G^2
    (:func:`.outliers._count_and_moments`), of every channel's values and squares (:func:`channel_sums`),
    and the features (``{name: (N, k)}``) added to ``fsum``'s cumulative sums (:meth:`FeatureSums.add`;
    ``fsum`` None: none kept).  Each sum receives the terms of the separate passes in the same order: the
    same bits, with a sample's pixel found once instead of once per pass and feature.

    Returns
    -------
    counts : ndarray (H, W) int64
    s1, s2 : ndarray (H, W)
        The round's sums of G and G^2.
    c1, c2 : ndarray (H, W, C)
        The round's sums of the channels' values and squares.
    """
    counts = np.zeros((height, width), np.int64)
    s1 = np.zeros((height, width))
    s2 = np.zeros((height, width))
    c1 = np.zeros((height, width, val.shape[1]))
    c2 = np.zeros((height, width, val.shape[1]))
    parts = tuple(fsum.parts(pos, feats, where)) if fsum is not None else ()
    if parts:
        ftail = (parts, fsum.n, fsum.shift, fsum.s1, fsum.s2)
    else:  # no feature: one empty component, never read
        ftail = ((np.zeros((1, 0)),), np.zeros((1, 1)), np.zeros((1, 0)), np.zeros((1, 1, 0)), np.zeros((1, 1, 0)))
    in_bands(_add_round_sums, (pos, val, norm_code, weights, counts, s1, s2, c1, c2) + ftail, pos, height,
             sorted_rows=sorted_rows)
    return counts, s1, s2, c1, c2


@numba.njit(cache=True, nogil=True)
def _add_round_sums(pos, val, norm_code, weights, counts, s1, s2, c1, c2, feats, fn, shift, fs1, fs2, k0, k1, j0,
                    j1):
    """:func:`round_sums`' pass over the samples ``k0 <= k < k1`` of the rows ``j0 <= j < j1``, in sample order:
    the terms of :func:`.outliers._count_and_moments`, :func:`_add_channel_sums`, :func:`_first_samples` and
    :func:`_add_feature_sums` (``feats`` a tuple of (N, k) arrays, columns stacked in their order; ``fs1``
    with no column: no feature).  A run of consecutive samples of one pixel (a renderer lists a pixel's
    samples together) is summed into locals, one sum at a time, and stored once: each sum receives the
    same terms in the same order, with the pixel found once per sample and each sum read and written
    once per run."""
    h, w = counts.shape
    nc = c1.shape[2]
    with_features = fs1.shape[2] > 0
    k = k0
    while k < k1:
        py = min(max(int(math.floor(pos[k, 1])), 0), h - 1)
        if not j0 <= py < j1:
            k += 1
            continue
        px = min(max(int(math.floor(pos[k, 0])), 0), w - 1)
        end = k + 1
        while end < k1 and min(max(int(math.floor(pos[end, 1])), 0), h - 1) == py \
                and min(max(int(math.floor(pos[end, 0])), 0), w - 1) == px:
            end += 1
        n = counts[py, px]
        a1 = s1[py, px]
        a2 = s2[py, px]
        for t in range(k, end):
            g = _norm_of(val, t, norm_code, weights)
            n += 1
            a1 += g
            a2 += g * g
        counts[py, px] = n
        s1[py, px] = a1
        s2[py, px] = a2
        for c in range(nc):
            a1 = c1[py, px, c]
            a2 = c2[py, px, c]
            for t in range(k, end):
                v = np.float64(val[t, c])
                a1 += v
                a2 += v * v
            c1[py, px, c] = a1
            c2[py, px, c] = a2
        if with_features:
            q = py * w + px
            first = fn[py, px] == 0  # the pixel's first sample ever sets its shift
            fn[py, px] += end - k
            col = 0
            for f in literal_unroll(feats):
                for c in range(f.shape[1]):
                    if first:
                        x = np.float64(f[k, c])
                        shift[q, col + c] = x if math.isfinite(x) else 0.0
                    sh = shift[q, col + c]
                    a1 = fs1[py, px, col + c]
                    a2 = fs2[py, px, col + c]
                    for t in range(k, end):
                        x = np.float64(f[t, c])
                        if not math.isfinite(x):
                            x = 0.0
                        d = x - sh
                        a1 += d
                        a2 += d * d
                    fs1[py, px, col + c] = a1
                    fs2[py, px, col + c] = a2
                col += f.shape[1]
        k = end


#: Relative floor of a feature's spread in the gate: means that agree to this many digits are equal
#: (sums of equal values differ in the last bits between pixels of different sample counts).
FEATURE_FLOOR = 1e-6


def feature_moments(fsum: FeatureSums | None) -> np.ndarray:
    """Per pixel and feature component (H, W, F, 5): the mean, the sample variance plus a floor
    ``(FEATURE_FLOOR |mean|)^2 + 1e-300``, the smooth slopes along x and y (:func:`_mc_slope`) and
    the squared standard error of the mean (that variance over n).

    The gate lets q receive from p, in every component, when ``(f_q - f_p)^2 <= k^2 (s_p^2 + s_q^2) +
    (t + k se sqrt(2 + (dx^2 + dy^2) / 2))^2``, ``t = |dx| max(|sx_p|, |sx_q|) + |dy| max(|sy_p|, |sy_q|)``
    ((dx, dy) = q - p, se the larger standard error): a slanted plane's depth or a curved surface's
    normal changes from pixel to pixel by its slope, which a pixel's own spread (``slope^2 / 12`` for a
    ramp) would explain only one pixel away; the standard-error term is the noise of the difference
    and of the slopes (central differences: variance se^2 / 2 each), so a noisy ramp passes too.  A
    noise-free step has spread, slopes and standard errors 0 beside it: refused.  Below two samples
    the variance is infinite (nothing known: the features pass).  No features: F = 0, the gate tests none.
    """
    if fsum is None or not fsum.any:
        return np.zeros((1, 1, 0, 5))
    h, w, nf = fsum.s1.shape
    out = np.empty((h, w, nf, 5))
    _feature_moments(fsum.n, fsum.s1, fsum.s2, fsum.shift.reshape(h, w, nf), FEATURE_FLOOR, out)
    return out


@numba.njit(cache=True, nogil=True)
def _mc_slope(a, b):
    """The smooth slope from the backward and forward differences a, b: the monotonised central
    difference, ``minmod((a + b) / 2, 2 a, 2 b)`` (minmod: the argument of least magnitude if all agree in
    sign, else 0).  A ramp has its slope (the central difference, the least noisy estimate); a step has
    slope 0 beside it (one of a, b is 0), so a slope never excuses a discontinuity.  At the film border
    the missing difference is 0.  (Measured and rejected: plain minmod(a, b), the smaller of two noisy
    differences, underestimates a ramp's slope whose pixel means carry the noise of random positions: a
    depth ramp then refused 7 % of the pairs two pixels apart at 16 spp.)"""
    if not a * b > 0:
        return 0.0
    c = 0.5 * (a + b)
    lim = min(min(abs(c), 2.0 * abs(a)), 2.0 * abs(b))
    return lim if c > 0 else -lim


@numba.njit(cache=True, nogil=True)
def _feature_moments(n, s1, s2, shift, floor, out):
    """:func:`feature_moments`, pixel by pixel: the moments, then the slopes of the means (:func:`_mc_slope`
    of the differences to the left and right, above and below); bit for bit the array expressions it
    replaced (tests/test_splat_consistent.py)."""
    h, w, nf = s1.shape
    for y in range(h):
        for x in range(w):
            nn = n[y, x]
            for c in range(nf):
                m0 = s1[y, x, c] / max(nn, 1.0) if nn > 0 else 0.0
                var = max(s2[y, x, c] / max(nn, 1.0) - m0 * m0, 0.0) * nn / max(nn - 1.0, 1.0)
                mean = m0 + shift[y, x, c]
                if nn >= 2:
                    fm = floor * mean
                    var = var + fm * fm + 1e-300
                else:
                    var = np.inf
                out[y, x, c, 0] = mean
                out[y, x, c, 1] = var
                out[y, x, c, 4] = var / max(nn, 1.0)
    for y in range(h):
        for x in range(w):
            for c in range(nf):
                m = out[y, x, c, 0]
                a = m - out[y, x - 1, c, 0] if x > 0 else 0.0
                b = out[y, x + 1, c, 0] - m if x < w - 1 else 0.0
                out[y, x, c, 2] = _mc_slope(a, b)
                a = m - out[y - 1, x, c, 0] if y > 0 else 0.0
                b = out[y + 1, x, c, 0] - m if y < h - 1 else 0.0
                out[y, x, c, 3] = _mc_slope(a, b)


def pixel_moments(counts, s1, s2):
    """Per pixel and channel (H, W, C, 4): the mean, the squared standard error of the mean, the log
    sample variance and its variance ``2 / (n - 1)`` (normal approximation).  Below two samples the
    standard error is infinite (nothing known); a variance of 0 has log -inf (only equal pixels match).
    One compiled pass (:func:`_pixel_moments`) and numpy's log of the variances: bit for bit the array
    expressions (tests/test_splat_stats_compiled.py).
    """
    h, w, nc = s1.shape
    out = np.empty((h, w, nc, 4))
    var = np.empty((h, w, nc))
    _pixel_moments(np.ascontiguousarray(counts), np.ascontiguousarray(s1, dtype=np.float64),
                   np.ascontiguousarray(s2, dtype=np.float64), out, var)
    ok = (counts >= 2)[:, :, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        out[..., 2] = np.where(ok, np.log(var), 0.0)
    return out


@numba.njit(cache=True, nogil=True)
def _pixel_moments(counts, s1, s2, out, var):
    """:func:`pixel_moments` but the log: ``out[..., 0, 1, 3]`` and the sample variances ``var`` (NaN kept as
    ``np.maximum`` keeps it)."""
    h, w, nc = s1.shape
    for y in range(h):
        for x in range(w):
            n = np.float64(counts[y, x])
            for c in range(nc):
                mean = s1[y, x, c] / max(n, 1.0) if n > 0 else 0.0
                d = s2[y, x, c] / max(n, 1.0) - mean * mean
                v = (d if not d < 0.0 else 0.0) * n / max(n - 1.0, 1.0)
                var[y, x, c] = v
                out[y, x, c, 0] = mean
                if n >= 2:
                    out[y, x, c, 1] = v / max(n, 1.0)
                    out[y, x, c, 3] = 2.0 / max(n - 1.0, 1.0)
                else:
                    out[y, x, c, 1] = np.inf
                    out[y, x, c, 3] = np.inf


def edge_radius(stats, k):
    """Largest support radius per pixel: ``k se / |grad m|``, the smallest over the channels.

    Spreading a sample over a radius r along a gradient g moves its expectation by up to ``|g| r``
    at the rim: no more than k standard errors of the pixel's mean, the gate's own tolerance (the
    gate accepts a neighbour whose mean differs by up to k standard errors of the difference).  The gradient is
    Sobel's (central differences smoothed 1-2-1 across, on the film mirrored at its borders), and
    its own noise is taken out: ``|g|^2 = max(0, gx^2 + gy^2 - var(gx) - var(gy))`` with the
    variances from the neighbours' standard errors, so pure noise does not pass for an edge.
    0 where se is 0 (nothing to remove) or unknown (fewer than two samples).  One compiled pass
    (:func:`_edge_radius`), bit for bit the array expressions (tests/test_splat_stats_compiled.py).
    """
    h, w = stats.shape[0], stats.shape[1]
    out = np.empty((h, w))
    _edge_radius(np.ascontiguousarray(stats), float(k), out)
    return out


@numba.njit(cache=True, nogil=True, inline="always")
def _sobel(m, v, y, x, c, h, w):
    """Sobel's gradient (gx, gy) of the means ``m`` at (y, x) on the film mirrored at its borders (an index
    one off the film reads the border pixel) and its noise ``var gx + var gy`` from the squared standard
    errors ``v``, with the additions in the order of the array expressions they replace."""
    ym = max(y - 1, 0)
    yp = min(y + 1, h - 1)
    xm = max(x - 1, 0)
    xp = min(x + 1, w - 1)
    gx = ((m[ym, xp, c, 0] - m[ym, xm, c, 0]) + 2.0 * (m[y, xp, c, 0] - m[y, xm, c, 0])
          + (m[yp, xp, c, 0] - m[yp, xm, c, 0])) / 8.0
    gy = ((m[yp, xm, c, 0] - m[ym, xm, c, 0]) + 2.0 * (m[yp, x, c, 0] - m[ym, x, c, 0])
          + (m[yp, xp, c, 0] - m[ym, xp, c, 0])) / 8.0
    var_g = (((((_fin(v[ym, xp, c, 1]) + _fin(v[ym, xm, c, 1])) + 4.0 * (_fin(v[y, xp, c, 1]) + _fin(v[y, xm, c, 1])))
               + (_fin(v[yp, xp, c, 1]) + _fin(v[yp, xm, c, 1])))
              + (_fin(v[yp, xm, c, 1]) + _fin(v[ym, xm, c, 1]))) + 4.0 * (_fin(v[yp, x, c, 1]) + _fin(v[ym, x, c, 1]))
             + (_fin(v[yp, xp, c, 1]) + _fin(v[ym, xp, c, 1]))) / 64.0
    return gx, gy, var_g


@numba.njit(cache=True, nogil=True, inline="always")
def _fin(a):
    """A squared standard error, 0 where it is not finite (fewer than two samples)."""
    return a if math.isfinite(a) else 0.0


@numba.njit(cache=True, nogil=True)
def _edge_radius(stats, k, out):
    """:func:`edge_radius` pixel by pixel."""
    h, w, nc = stats.shape[0], stats.shape[1], stats.shape[2]
    for y in range(h):
        for x in range(w):
            rmin = np.inf
            for c in range(nc):
                gx, gy, var_g = _sobel(stats, stats, y, x, c, h, w)
                se = math.sqrt(stats[y, x, c, 1])
                g = math.sqrt(max(gx * gx + gy * gy - var_g, 0.0))
                r = k * se / g if g > 0 else np.inf
                if not (math.isfinite(se) and se > 0):
                    r = 0.0
                if c == 0 or r < rmin:
                    rmin = r
            out[y, x] = rmin


def width_coefs(fref, nmap, c, alpha):
    """Per pixel the factors of Eq. 8's diameter ``d = C N^-alpha (G / f)^(1/2)`` that do not depend on the
    sample: ``(C N^-alpha, sqrt(f))`` (:func:`_width_coefs`), for :func:`_split_and_radii`."""
    coef = np.empty(fref.shape)
    sf = np.empty(fref.shape)
    _width_coefs(fref, nmap, float(c), float(alpha), coef, sf)
    return coef, sf


@numba.njit(cache=True, nogil=True)
def _width_coefs(fref, nmap, c, alpha, coef, sf):
    """``coef = C N^-alpha`` and ``sf = sqrt(f)`` of every pixel (``sf = 0`` where f is not positive and finite:
    nothing is known there, the width is the cap), so that a sample's diameter
    ``coef * (sqrt(G - t) / sf)`` costs a square root and a division, not a power: the expression of
    :func:`.outliers._excess_width`, bit for bit."""
    h, w = fref.shape
    for y in range(h):
        for x in range(w):
            f = fref[y, x]
            coef[y, x] = c * nmap[y, x] ** (-alpha)
            sf[y, x] = math.sqrt(f) if f > 0.0 and f < np.inf else 0.0


@numba.njit(cache=True, nogil=True, inline="always")
def _width_of(ex, coef, sf, max_w):
    """:func:`.outliers._excess_width` from the pixel's :func:`_width_coefs`: (diameter, capped)."""
    d = coef * (math.sqrt(ex) / sf) if sf > 0.0 else np.inf
    capped = d > max_w
    if d >= max_w:
        d = max_w
    return d, capped


@numba.njit(cache=True, nogil=True)
def _split_and_radii(pos, val, norm_code, weights, tau, coef, spread_coef, sf, min_w, max_w, r_edge, frac, radius,
                     krad, k0, k1):
    """The outlier split of :func:`.outliers._split_outliers` (``frac``, ``radius``; returns (outliers, capped))
    and, in the same pass over the samples ``k0 <= k < k1``, the support radius ``krad`` of each consistent
    sample (``frac = 0`` under a finite threshold ``tau``: the outlier test ran and passed it): Eq. 8 with
    ``spread_c``, ``spread_alpha`` against the window mean ``fref``; -1 for outliers, for samples no test
    could judge yet, and where the diameter, or the pixel's ``2 r_edge``, is at most ``min_w``.  One pass:
    the sample's G and pixel are found once for both.  ``coef``, ``spread_coef`` and ``sf``: the per-pixel
    factors of the two widths (:func:`width_coefs` of ``c, alpha`` and of ``spread_c, spread_alpha``), the
    same diameters as :func:`.outliers._excess_width` computes from ``fref`` and the counts."""
    h, w = tau.shape
    n_out = 0
    n_capped = 0
    for k in range(k0, k1):
        frac[k] = 0.0
        radius[k] = -1.0
        krad[k] = -1.0
        g = _norm_of(val, k, norm_code, weights)
        if not g > 0.0:
            continue
        px = min(max(int(math.floor(pos[k, 0])), 0), w - 1)
        py = min(max(int(math.floor(pos[k, 1])), 0), h - 1)
        t = tau[py, px]
        if g > t:
            d, cap = _width_of(g - t, coef[py, px], sf[py, px], max_w)
            n_capped += cap
            if d > min_w:  # an outlier: its excess is spread by the outlier rule, the rest stays
                n_out += 1
                frac[k] = (g - t) / g
                radius[k] = 0.5 * d
                continue
        if not t < np.inf:
            continue  # too few samples around for the outlier test: not known to be consistent
        d, _ = _width_of(g - 0.0, spread_coef[py, px], sf[py, px], max_w)
        if min(d, 2.0 * r_edge[py, px]) > min_w:  # else nothing would leave the pixel
            krad[k] = 0.5 * d
    return n_out, n_capped

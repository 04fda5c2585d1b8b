"""``splat``: progressive variable-width Epanechnikov splatting of individual samples.

Suykens and Willems (2000) filter *samples*, not pixels: every sample is
spread over the image with an Epanechnikov kernel whose width grows with
how "bad" the sample is compared with the current estimate of the image
(Eq. 8), and shrinks as the number of samples grows.  The images are
built progressively (Fig. 3): only the first batch is needed twice (for
the pilot estimate and the first variable-width estimate); every later
round scales the running image down and splats its samples with the
previous image as the width reference.

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

Energy per sample
    A sample of round j in pixel p carries ``F / n_pj`` (F its value,
    ``n_pj`` the samples of p in that round), which is Eq. 3's
    ``G / N`` for stratified sampling with N_j samples per pixel; rounds
    are combined with the weights ``N_j / N_total`` of Fig. 3's scale-down.

References
----------
.. [1] F. Suykens and Y. D. Willems, "Adaptive Filtering for Progressive
   Monte Carlo Image Rendering", WSCG 2000.
.. [2] I. S. Abramson, "On bandwidth variation in kernel estimates - a
   square root law", Annals of Statistics 10(4), 1982.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from typing import Callable, Iterable

import numba
import numpy as np

from ..errors import InputError, McreconWarning
from ..protocol import SampleBatch, SampleRequest
from ..samples import check_policy, source_name
from ..samples import NONFINITE_POLICIES
from .base import AdaptiveState, Method, MethodInputs, Option, Requirements, RunState

__all__ = ["SplatMethod", "ProgressiveSplatter", "epanechnikov", "kernel_width", "pilot_width",
           "sample_norm", "splat", "BOUNDARY_MODES", "NORMS", "LUMINANCE_WEIGHTS"]

#: Boundary remedies (paper Sec. 5): ``mirror`` reflects the kernel weights
#: that fall outside the film back across the border (kernel mirroring),
#: ``renormalize`` normalises each footprint over the in-film centres only,
#: ``none`` normalises over the unbounded grid and drops what falls outside
#: (the paper's implementation: the border darkens).
BOUNDARY_MODES = ("mirror", "renormalize", "none")
_BOUNDARY_CODE = {"mirror": 0, "renormalize": 1, "none": 2}

#: Scalar "value" G of a sample (and f of a pixel) used by Eq. 8 for
#: colour: ``luminance`` = Rec. 709 luminance of the absolute channel values
#: (1 channel: its absolute value), ``mean`` = mean absolute channel value,
#: ``max`` = largest absolute channel value.  Absolute values: a negative
#: sample is as "bad" as a positive one of the same magnitude, and G = 0
#: only for an all-zero sample.
NORMS = ("luminance", "mean", "max")
LUMINANCE_WEIGHTS = np.array([0.2126, 0.7152, 0.0722])


# ----------------------------------------------------------------------------
# Formulas (vectorised reference forms; the numba loops below are the fast path)
# ----------------------------------------------------------------------------

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


def kernel_width(g, f, n, *, c: float = 4.0, alpha: float = 0.3, min_width: float = 1.0,
                 max_width: float = 32.0) -> np.ndarray:
    """Eq. 8: kernel diameter ``h = C N^-alpha (G / f)^(1/2)``, clamped to [min_width, max_width].

    Parameters
    ----------
    g : array_like
        Sample values G (any sign: the magnitude is used).
    f : array_like
        Reference estimate f at the samples' positions (magnitude used).
        ``f = 0`` (or non-finite) gives the maximum width: nothing is known
        there, so the sample is spread as far as allowed.
    n : array_like
        Samples per pixel N (>= 1).

    Returns
    -------
    ndarray of float64
        Diameters in pixels.  ``G = 0`` gives ``min_width`` (such samples
        carry no energy; :func:`splat` skips them).

    References
    ----------
    .. [1] Suykens and Willems 2000, Eq. 8 (after Abramson's square-root law, Eq. 5).
    """
    g = np.abs(np.asarray(g, dtype=np.float64))
    f = np.abs(np.asarray(f, dtype=np.float64))
    n = np.asarray(n, dtype=np.float64)
    ok = np.isfinite(f) & (f > 0)
    fs = np.where(ok, f, 1.0)
    # sqrt(g)/sqrt(f) rather than sqrt(g/f): no overflow for f ~ 1e-300.
    h = np.where(ok, c * n ** (-alpha) * np.sqrt(g) / np.sqrt(fs), np.inf)
    return np.clip(h, min_width, max_width)


def pilot_width(n, *, c_prime: float = 8.0, min_width: float = 1.0, max_width: float = 32.0) -> np.ndarray:
    """Fig. 3's pilot: fixed diameter ``h' = C' N0^(-1/2)``, clamped to [min_width, max_width]."""
    n = np.asarray(n, dtype=np.float64)
    return np.clip(c_prime * n ** -0.5, min_width, max_width)


def sample_norm(values, norm: str = "luminance") -> np.ndarray:
    """The scalar G of samples (N, C) or pixels (H, W, C) under ``norm`` (see :data:`NORMS`)."""
    v = np.abs(np.asarray(values, dtype=np.float64))
    c = v.shape[-1]
    if norm == "luminance":
        if c == 1:
            return v[..., 0]
        if c != 3:
            raise InputError("method splat", "norm", f"'luminance' needs 1 or 3 (R, G, B) channels, "
                             f"got {c}; use norm='mean' or 'max'")
        return v @ LUMINANCE_WEIGHTS
    if norm == "mean":
        return v.mean(axis=-1)
    if norm == "max":
        return v.max(axis=-1)
    raise InputError("method splat", "norm", f"{norm!r}; valid: {', '.join(NORMS)}")


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


@numba.njit(cache=True, nogil=True)
def _splat_loop(pos, val, scale, radius, mode, out):
    """Deposit each sample's ``val * scale`` with a normalised Epanechnikov footprint.

    ``radius[k] <= 0`` skips sample k (G = 0).  mode: 0 mirror,
    1 renormalise, 2 none (drop off-film weight).  Returns the number of
    samples that fell back to their own pixel (no centre covered).
    One pass computes the weights of the covered centres into a scratch
    buffer (with their film indices after mirroring), the second deposits
    them divided by their sum.
    """
    h = out.shape[0]
    w = out.shape[1]
    nc = out.shape[2]
    n = pos.shape[0]
    rmax = 0.0
    for k in range(n):
        if radius[k] > rmax:
            rmax = radius[k]
    side = 2 * int(math.ceil(rmax)) + 2
    cap = side * side
    wbuf = np.empty(cap)
    ibuf = np.empty(cap, np.int64)
    jbuf = np.empty(cap, np.int64)
    vv = np.empty(nc)
    n_fallback = 0
    for k in range(n):
        r = radius[k]
        if not r > 0.0:
            continue
        x = np.float64(pos[k, 0])
        y = np.float64(pos[k, 1])
        for c in range(nc):
            vv[c] = val[k, c]
        r2 = r * r
        inv_r2 = 1.0 / r2
        # centres c = j + 1/2 with |c - y| < r  <=>  y - 1/2 - r < j < y - 1/2 + r
        jlo = int(math.floor(y - 0.5 - r)) + 1
        jhi = int(math.ceil(y - 0.5 + r)) - 1
        if mode == 1:
            jlo = max(jlo, 0)
            jhi = min(jhi, h - 1)
        s = 0.0
        m = 0
        for j in range(jlo, jhi + 1):
            dy = j + 0.5 - y
            rem = r2 - dy * dy
            if rem <= 0.0:
                continue
            jj = j
            if j < 0 or j >= h:
                jj = -1 if mode == 2 else _reflect(j, h)
            half = math.sqrt(rem)
            ilo = int(math.floor(x - 0.5 - half)) + 1
            ihi = int(math.ceil(x - 0.5 + half)) - 1
            if mode == 1:
                ilo = max(ilo, 0)
                ihi = min(ihi, w - 1)
            dy2 = dy * dy * inv_r2
            for i in range(ilo, ihi + 1):
                dx = i + 0.5 - x
                q = dx * dx * inv_r2 + dy2
                if q < 1.0:
                    wt = 1.0 - q
                    s += wt
                    ii = i
                    if i < 0 or i >= w:
                        ii = -1 if mode == 2 else _reflect(i, w)
                    wbuf[m] = wt
                    ibuf[m] = ii
                    jbuf[m] = jj
                    m += 1
        if not s > 0.0:
            # No pixel centre inside the support: the whole sample goes to its
            # own pixel (whose centre is the nearest one).
            n_fallback += 1
            px = min(max(int(math.floor(x)), 0), w - 1)
            py = min(max(int(math.floor(y)), 0), h - 1)
            e = scale[k]
            for c in range(nc):
                out[py, px, c] += vv[c] * e
            continue
        e = scale[k] / s
        if nc == 3:
            # the common RGB case, unrolled (about 1.3x faster)
            v0 = vv[0] * e
            v1 = vv[1] * e
            v2 = vv[2] * e
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
        for t in range(m):
            ii = ibuf[t]
            jj = jbuf[t]
            if ii < 0 or jj < 0:
                continue  # mode none: weight outside the film is lost
            wt = wbuf[t] * e
            for c in range(nc):
                out[jj, ii, c] += vv[c] * wt
    return n_fallback


#: Samples per call above which the scatter runs on _N_BLOCKS fixed blocks
#: in parallel, each into its own buffer, summed in block order: the result
#: depends on the inputs only (not on the thread count), as resuming needs.
_PARALLEL_MIN = 1 << 17
_N_BLOCKS = 2


@numba.njit(cache=True, nogil=True, parallel=True)
def _splat_blocks(pos, val, scale, radius, mode, out, n_blocks):
    n = pos.shape[0]
    h, w, nc = out.shape
    bufs = np.zeros((n_blocks, h, w, nc))
    fb = np.zeros(n_blocks, np.int64)
    for b in numba.prange(n_blocks):
        a = n * b // n_blocks
        e = n * (b + 1) // n_blocks
        fb[b] = _splat_loop(pos[a:e], val[a:e], scale[a:e], radius[a:e], mode, bufs[b])
    for b in range(n_blocks):
        out += bufs[b]
    return fb.sum()


def _scatter(pos, val, scale, radius, mode, out) -> int:
    """The scatter loop, on two cores for large batches (deterministic block split)."""
    if pos.shape[0] >= _PARALLEL_MIN:
        return int(_splat_blocks(pos, val, scale, radius, mode, out, _N_BLOCKS))
    return int(_splat_loop(pos, val, scale, radius, mode, out))


@numba.njit(cache=True, nogil=True)
def _norm_of(val, k, norm_code, weights):
    nc = val.shape[1]
    g = 0.0
    if norm_code == 0:  # weighted sum of |v| (luminance or mean)
        for c in range(nc):
            g += weights[c] * abs(np.float64(val[k, c]))
    else:  # max |v|
        for c in range(nc):
            a = abs(np.float64(val[k, c]))
            if a > g:
                g = a
    return g


@numba.njit(cache=True, nogil=True)
def _radii(pos, val, norm_code, weights, ref, nmap, pilot, c, alpha, c_prime, min_w, max_w, out):
    """Support radius (= diameter / 2) of every sample; -1 for G = 0 samples.

    pilot: fixed diameter C' N^-1/2; else Eq. 8 with ``ref`` (|f| of the
    sample's pixel under the same norm) and ``nmap`` (N of the sample's pixel).
    Returns the number of samples whose width hit ``max_w`` (capped).
    """
    h = nmap.shape[0]
    w = nmap.shape[1]
    n_capped = 0
    for k in range(pos.shape[0]):
        g = _norm_of(val, k, norm_code, weights)
        if g == 0.0:
            out[k] = -1.0
            continue
        px = min(max(int(math.floor(pos[k, 0])), 0), w - 1)
        py = min(max(int(math.floor(pos[k, 1])), 0), h - 1)
        n = nmap[py, px]
        if pilot:
            d = c_prime / math.sqrt(n)
        else:
            f = ref[py, px]
            if f > 0.0 and f < np.inf:
                d = c * n ** (-alpha) * (math.sqrt(g) / math.sqrt(f))
            else:
                d = np.inf  # nothing known here: spread as far as allowed
        if d >= max_w:
            if d > max_w:
                n_capped += 1
            d = max_w
        if d < min_w:
            d = min_w
        out[k] = 0.5 * d
    return n_capped


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
    """
    if boundary not in _BOUNDARY_CODE:
        raise InputError("splat", "boundary", f"{boundary!r}; valid: {', '.join(BOUNDARY_MODES)}")
    pos = np.ascontiguousarray(positions, dtype=np.float64)
    val = np.asarray(values, dtype=np.float64)
    if val.ndim == 1:
        val = val[:, None]
    val = np.ascontiguousarray(val)
    n = pos.shape[0]
    if pos.ndim != 2 or pos.shape[1] != 2 or val.shape[0] != n:
        raise InputError("splat", "positions/values", f"shapes {pos.shape} and {val.shape}, expected (N, 2) and (N, C)")
    if n and not (np.isfinite(pos).all() and pos[:, 0].min() >= 0 and pos[:, 1].min() >= 0
                  and pos[:, 0].max() < width and pos[:, 1].max() < height):
        raise InputError("splat", "positions", f"must be finite and inside the film [0, {width}) x [0, {height})")
    radius = np.ascontiguousarray(np.broadcast_to(np.asarray(widths, dtype=np.float64), (n,))) * 0.5
    sc = np.ascontiguousarray(np.broadcast_to(np.asarray(scale, dtype=np.float64), (n,)))
    if out is None:
        out = np.zeros((height, width, val.shape[1]))
    elif out.shape != (height, width, val.shape[1]) or out.dtype != np.float64:
        raise InputError("splat", "out", f"shape {out.shape} dtype {out.dtype}, expected "
                         f"{(height, width, val.shape[1])} float64")
    _scatter(pos, val, sc, radius, _BOUNDARY_CODE[boundary], out)
    return out


# ----------------------------------------------------------------------------
# The progressive algorithm (Fig. 3)
# ----------------------------------------------------------------------------

def _clean(pos, val, nonfinite, where):
    """Apply the non-finite value policy; returns float arrays (positions keep their dtype)."""
    pos = np.asarray(pos)
    val = np.asarray(val)
    if val.ndim == 1:
        val = val[:, None]
    bad = ~np.isfinite(val).all(axis=1)
    n_bad = int(bad.sum())
    if n_bad:
        if nonfinite == "raise":
            raise InputError(where, "values", f"{n_bad} sample(s) with NaN or Inf values; drop them with "
                             "nonfinite='drop' or fix the renderer")
        if nonfinite == "drop":
            pos, val = pos[~bad], val[~bad]
        else:
            val = np.where(np.isfinite(val), val, 0.0)
    return np.ascontiguousarray(pos), np.ascontiguousarray(val), n_bad


class ProgressiveSplatter:
    """Fig. 3 of Suykens and Willems (2000): the running image and its update rounds.

    Parameters
    ----------
    width, height, n_channels : int
        Film size and channels.
    c, alpha, c_prime, min_width, max_width, boundary, norm
        See :class:`SplatMethod`.

    Attributes
    ----------
    image : ndarray (H, W, C) float64
        The current estimate f_j (after the last round).
    pilot : ndarray or None
        f'_0, the fixed-width pilot estimate of the first round.
    spp_total : float
        N_total in samples per pixel (mean over the film).
    cum_counts : ndarray (H, W) int64
        Samples per pixel over all rounds (the N of Eq. 8 per pixel).
    rounds : list of dict
        Per round: spp, samples, capped (width hit max_width), fallback
        (no centre covered), empty_pixels.

    Notes
    -----
    Rounds are added with :meth:`add_round` (samples in memory) or
    :meth:`add_round_stream` (two passes over re-iterable chunks: counts,
    then splats).  Adding the same rounds in the same order gives the
    same image bit for bit (the scatter is sequential, or two fixed
    blocks summed in order: independent of the thread count).  Non-finite
    values are handled by ``nonfinite`` without a warning here; callers
    report it (:meth:`SplatMethod.reconstruct_log` warns).
    """

    def __init__(self, width: int, height: int, n_channels: int, *, c: float = 4.0, alpha: float = 0.3,
                 c_prime: float = 8.0, min_width: float = 1.0, max_width: float = 32.0,
                 boundary: str = "mirror", norm: str = "luminance"):
        self.width, self.height, self.n_channels = int(width), int(height), int(n_channels)
        self.c, self.alpha, self.c_prime = float(c), float(alpha), float(c_prime)
        self.min_width, self.max_width = float(min_width), float(max_width)
        if boundary not in _BOUNDARY_CODE:
            raise InputError("method splat", "boundary", f"{boundary!r}; valid: {', '.join(BOUNDARY_MODES)}")
        self.boundary = boundary
        self.norm = norm
        if norm == "luminance":
            if self.n_channels == 1:
                weights = np.ones(1)
            elif self.n_channels == 3:
                weights = LUMINANCE_WEIGHTS.copy()
            else:
                raise InputError("method splat", "norm", f"'luminance' needs 1 or 3 (R, G, B) channels, got "
                                 f"{self.n_channels}; use norm='mean' or 'max'")
            self._norm_code = 0
        elif norm == "mean":
            weights = np.full(self.n_channels, 1.0 / self.n_channels)
            self._norm_code = 0
        elif norm == "max":
            weights = np.ones(self.n_channels)
            self._norm_code = 1
        else:
            raise InputError("method splat", "norm", f"{norm!r}; valid: {', '.join(NORMS)}")
        self._weights = weights
        self.image = np.zeros((self.height, self.width, self.n_channels))
        self.pilot = None
        self.spp_total = 0.0
        self.cum_counts = np.zeros((self.height, self.width), np.int64)
        self.rounds: list[dict] = []
        self.last_widths = np.zeros((self.height, self.width))

    # ------------------------------------------------------------ helpers
    def _pixel_counts(self, pos) -> np.ndarray:
        w, h = self.width, self.height
        ix = np.clip(np.floor(pos[:, 0]).astype(np.int64), 0, w - 1)
        iy = np.clip(np.floor(pos[:, 1]).astype(np.int64), 0, h - 1)
        return np.bincount(iy * w + ix, minlength=w * h).reshape(h, w)

    def _check(self, pos, val, where):
        if pos.ndim != 2 or pos.shape[1] != 2 or val.ndim != 2 or val.shape != (pos.shape[0], self.n_channels):
            raise InputError(where, "positions/values", f"shapes {pos.shape} and {val.shape}, expected (N, 2) "
                             f"and (N, {self.n_channels})")
        if pos.shape[0] and not (np.isfinite(pos).all() and pos[:, 0].min() >= 0 and pos[:, 1].min() >= 0
                                 and pos[:, 0].max() < self.width and pos[:, 1].max() < self.height):
            raise InputError(where, "positions", f"must be finite and inside the film [0, {self.width}) x "
                             f"[0, {self.height})")

    def _ref_norm(self, img) -> np.ndarray:
        """|f| of every pixel under the norm (the reference of Eq. 8)."""
        return np.ascontiguousarray(sample_norm(img, self.norm))

    def _radii(self, pos, val, ref, pilot) -> tuple[np.ndarray, int]:
        out = np.empty(pos.shape[0])
        nmap = np.maximum(self.cum_counts, 1).astype(np.float64)
        capped = _radii(pos, val, self._norm_code, self._weights, ref, nmap, pilot, self.c, self.alpha,
                        self.c_prime, self.min_width, self.max_width, out)
        return out, int(capped)

    def _deposit(self, pos, val, scale, radius, out) -> int:
        return _scatter(pos, val, scale, radius, _BOUNDARY_CODE[self.boundary], out)

    def _record_widths(self, pos, radius):
        """Mean kernel diameter of the samples of each pixel (diagnostic), 0 where none splatted."""
        keep = radius > 0
        w, h = self.width, self.height
        ix = np.clip(np.floor(pos[keep, 0]).astype(np.int64), 0, w - 1)
        iy = np.clip(np.floor(pos[keep, 1]).astype(np.int64), 0, h - 1)
        idx = iy * w + ix
        s = np.bincount(idx, weights=2.0 * radius[keep], minlength=w * h)
        n = np.bincount(idx, minlength=w * h)
        self._width_sum += s
        self._width_n += n

    # ------------------------------------------------------------- rounds
    def add_round(self, positions, values, *, nonfinite: str = "drop", where: str = "samples") -> None:
        """Add one round held in memory (Fig. 3: the first round, or one loop iteration)."""
        pos, val, _ = _clean(positions, values, nonfinite, where)
        self.add_round_stream(lambda: iter([(pos, val)]), nonfinite=nonfinite, where=where)

    def add_round_stream(self, chunks: Callable[[], Iterable], *, nonfinite: str = "drop",
                         where: str = "samples") -> None:
        """Add one round given as re-iterable chunks: ``chunks()`` yields (positions, values).

        The first round is materialised (Fig. 3 stores the first batch: it
        is splatted twice); later rounds are streamed twice (counts per
        pixel, then the splat), so memory stays bounded by the image.
        """
        if nonfinite not in NONFINITE_POLICIES:
            raise InputError(where, "nonfinite", f"{nonfinite!r}; valid: {', '.join(NONFINITE_POLICIES)}")
        first = self.spp_total == 0.0
        if first:
            parts = []
            for p, v in chunks():
                p, v, _ = _clean(p, v, nonfinite, where)
                self._check(p, np.asarray(v), where)
                parts.append((p, np.asarray(v, dtype=np.float64)))
            if parts:
                pos = np.ascontiguousarray(np.concatenate([p for p, _ in parts]))
                val = np.ascontiguousarray(np.concatenate([v for _, v in parts]))
            else:
                pos, val = np.zeros((0, 2)), np.zeros((0, self.n_channels))
            chunk_iter = lambda: iter([(pos, val)])  # noqa: E731
            counts = self._pixel_counts(pos)
        else:
            chunk_iter = chunks
            counts = np.zeros((self.height, self.width), np.int64)
            for p, v in chunks():
                p, v, _ = _clean(p, v, nonfinite, where)
                self._check(p, v, where)
                counts += self._pixel_counts(p)
        n_round = int(counts.sum())
        if n_round == 0:
            return
        p_film = self.width * self.height
        n_j = n_round / p_film  # N_j: mean samples per pixel of this round
        self.cum_counts += counts
        # Energy per sample: F / n_pj, so that the round's image is the splat
        # of its pixel means (Eq. 3 with G / N for stratified sampling).
        inv_counts = np.where(counts > 0, 1.0 / np.maximum(counts, 1), 0.0)
        empty = counts == 0
        self._width_sum = np.zeros(p_film)
        self._width_n = np.zeros(p_film, np.int64)
        capped = fallback = 0
        if first:
            # f'_0: fixed-width density estimate of the stored first batch (C' N0^-1/2) ...
            scale = inv_counts[np.clip(np.floor(pos[:, 1]).astype(np.int64), 0, self.height - 1),
                               np.clip(np.floor(pos[:, 0]).astype(np.int64), 0, self.width - 1)]
            rad, _ = self._radii(pos, val, np.zeros((self.height, self.width)), True)
            pilot = np.zeros_like(self.image)
            self._deposit(pos, val, scale, rad, pilot)
            self.pilot = pilot
            # ... then f_0: Eq. 8 widths with f'_0 as the reference, same samples.
            rad, capped = self._radii(pos, val, self._ref_norm(pilot), False)
            img = np.zeros_like(self.image)
            fallback = self._deposit(pos, val, scale, rad, img)
            self._record_widths(pos, rad)
            self.image = img
            self.spp_total = n_j
        else:
            ref_img = self.image  # f_{j-1}: the reference for this round's widths
            ref = self._ref_norm(ref_img)
            total = self.spp_total + n_j
            # Scale down: f_j = (N_total - N_j) / N_total * f_{j-1}
            img = ref_img * (self.spp_total / total)
            w_round = n_j / total
            for p, v in chunk_iter():
                p, v, _ = _clean(p, v, nonfinite, where)
                v = np.ascontiguousarray(v, dtype=np.float64)
                p = np.ascontiguousarray(p)
                ix = np.clip(np.floor(p[:, 0]).astype(np.int64), 0, self.width - 1)
                iy = np.clip(np.floor(p[:, 1]).astype(np.int64), 0, self.height - 1)
                scale = w_round * inv_counts[iy, ix]
                rad, cap = self._radii(p, v, ref, False)
                capped += cap
                fallback += self._deposit(p, v, scale, rad, img)
                self._record_widths(p, rad)
            if empty.any():
                # A pixel this round did not sample keeps its previous estimate
                # for the round's share (not energy from samples: documented).
                img[empty] += w_round * ref_img[empty]
            self.image = img
            self.spp_total = total
        with np.errstate(invalid="ignore", divide="ignore"):
            self.last_widths = np.where(self._width_n > 0, self._width_sum / np.maximum(self._width_n, 1),
                                        0.0).reshape(self.height, self.width)
        n_empty = int(empty.sum())
        self.rounds.append({"spp": n_j, "samples": n_round, "capped": capped, "fallback": fallback,
                            "empty_pixels": n_empty})
        if n_empty:
            warnings.warn(f"{where}: splat round {len(self.rounds) - 1}: {n_empty} pixel(s) without samples in "
                          "this round" + (" keep their previous estimate for its share (Eq. 3 assumes every "
                                          "round samples every pixel)" if not first else
                                          " get only their neighbours' splats in the first round"),
                          McreconWarning, stacklevel=3)


# ----------------------------------------------------------------------------
# Round schedules
# ----------------------------------------------------------------------------

def doubling_schedule(total_spp: int, initial_spp: int = 1) -> list[int]:
    """Round sizes N_0 = initial_spp, N_j = 2 N_{j-1} (Fig. 3) summing to ``total_spp``.

    The last round absorbs the remainder when it is smaller than the next
    doubling (no round is smaller than its predecessor): 4 spp -> [1, 3],
    64 spp -> [1, 2, 4, 8, 16, 33].
    """
    total_spp = int(total_spp)
    out = []
    done = 0
    while done < total_spp:
        out.append(_next_round(total_spp - done, out[-1] if out else None, initial_spp))
        done += out[-1]
    return out


def _next_round(rem: int, prev, initial_spp: int) -> int:
    if prev is None:
        return min(int(initial_spp), rem)
    n = max(1, int(round(2 * prev)))
    if n >= rem or rem - n < 2 * n:
        return rem
    return n


@numba.njit(cache=True, nogil=True)
def _select_by_rank(pix, rank, lo, hi, mask):
    """Mark samples whose running per-pixel rank lies in [lo[p], hi[p]); advances rank."""
    for k in range(pix.shape[0]):
        p = pix[k]
        r = rank[p]
        mask[k] = r >= lo[p] and r < hi[p]
        rank[p] = r + 1


# ----------------------------------------------------------------------------
# The method
# ----------------------------------------------------------------------------

class SplatMethod(Method):
    """Progressive variable-width Epanechnikov splatting (Suykens and Willems 2000).

    Options
    -------
    alpha : float
        Exponent of N in Eq. 8 (default 1.5/5 = 0.3, the paper's Sec. 5); 0 < alpha <= 1.
    c : float
        C of Eq. 8, the reference diameter in pixels at N = 1, G/f = 1 (default 4).
    c_prime : float
        C' of the pilot estimate, diameter C' N0^-1/2 (default 8: 8 px at N0 = 1).
    initial_spp : int
        N_0, samples per pixel of the first (stored) round (default 1).
    min_width, max_width : float
        Clamp of the kernel diameter in pixels (default 1 = "one pixel" of
        the paper, and 32: the cap for huge G/f and f = 0).
    boundary : {'mirror', 'renormalize', 'none'}
        Boundary-bias remedy (Sec. 5); default mirror.
    norm : {'luminance', 'mean', 'max'}
        Scalar G of a colour sample (and f of a pixel) in Eq. 8.

    Notes
    -----
    The method declares ``requires.samples``: it filters individual
    samples.  Adaptive runs: ``plan`` asks every pixel for the same count
    each round, N_j = 2 N_{j-1} from ``initial_spp``, the last round
    absorbing the remainder; budgets below one sample per pixel are
    refused and a remainder of fewer samples than pixels is left unspent
    (Eq. 3 assumes an even sample density).  ``observe`` splats each
    committed round.  Offline (``inputs.samples``, a sample source such as
    a log): its rounds are replayed in order; a single-round source is
    split into doubling pseudo-rounds by each pixel's sample order.

    References
    ----------
    .. [1] F. Suykens and Y. D. Willems, "Adaptive Filtering for Progressive
       Monte Carlo Image Rendering", WSCG 2000 (Eqs. 3, 4, 8; Fig. 3; Sec. 5).
    """

    name = "splat"
    adaptive = False
    requires = Requirements(samples=True, statistics=False)
    options = (
        Option("alpha", float, 0.3, "exponent of N in the kernel width (Eq. 8), 0 < alpha <= 1",
               min=0.0, max=1.0, min_open=True,
               note="the paper uses 1.5/5; 1/5 and 1/2 are the classical extremes"),
        Option("c", float, 4.0, "kernel diameter constant C in pixels (Eq. 8)", min=0.0, min_open=True),
        Option("c_prime", float, 8.0, "pilot kernel diameter constant C' in pixels (C' N0^-1/2)",
               min=0.0, min_open=True),
        Option("initial_spp", int, 1, "samples per pixel of the first round N0", min=1),
        Option("min_width", float, 1.0, "smallest kernel diameter in pixels (>= 1)", min=1.0),
        Option("max_width", float, 32.0, "largest kernel diameter in pixels (cap for huge G/f; >= min_width)",
               min=1.0),
        Option("boundary", str, "mirror", "boundary-bias remedy", BOUNDARY_MODES),
        Option("norm", str, "luminance", "scalar value of a colour sample in Eq. 8", NORMS),
    )

    def _configure(self, params: dict) -> None:
        if params["max_width"] < params["min_width"]:
            raise InputError(self.where, "max_width", f"{params['max_width']!r}, expected >= min_width "
                             f"({params['min_width']!r})")

    def _new_splatter(self, width, height, n_channels) -> ProgressiveSplatter:
        p = self.params
        return ProgressiveSplatter(width, height, n_channels, c=p["c"], alpha=p["alpha"], c_prime=p["c_prime"],
                                   min_width=p["min_width"], max_width=p["max_width"],
                                   boundary=p["boundary"], norm=p["norm"])

    def start(self, width, height, channels=("R", "G", "B"), *, reference=None) -> "SplatRun":
        base = super().start(width, height, channels, reference=reference)
        return SplatRun(**dataclasses.asdict(base),
                        splatter=self._new_splatter(base.width, base.height, len(base.channels)))

    # ------------------------------------------------------------ offline
    def reconstruct_run(self, run: "SplatRun", inputs: MethodInputs) -> np.ndarray:
        """Replay the sample source's rounds in order through the progressive algorithm.

        A source with a single round (an offline render) is split into
        pseudo-rounds N_0 = initial_spp, N_j = 2 N_{j-1}: within each pixel,
        its samples are taken in source order and the k-th of the pixel's
        ``n_p`` samples goes to the round whose share of ``n_p`` contains k
        (the schedule is built for ``m = min_p n_p`` samples per pixel and
        scaled by ``n_p / m``, so every pseudo-round samples every pixel).
        A plain order split would put image rows, not samples per pixel,
        into rounds for logs sorted by pixel.  ``inputs.nonfinite`` applies
        to NaN/Inf values.
        """
        src = inputs.samples
        where = source_name(src)
        nonfinite = check_policy(inputs.nonfinite, where)
        if run.splatter.rounds:  # a reused run state starts over
            run.splatter = self._new_splatter(run.width, run.height, len(run.channels))
        sp = run.splatter
        rounds = [r for r, (a, b) in enumerate(src.round_slices()) if b > a]
        n_bad = [0]

        def counted(it):
            for ch in it:
                v = np.asarray(ch.values)
                if v.size:
                    n_bad[0] += int((~np.isfinite(v).all(axis=1)).sum())
                yield ch.positions, v

        if len(rounds) >= 2:
            for r in rounds:
                sp.add_round_stream(lambda r=r: counted(src.iter_chunks(rounds=[r], with_round=False)),
                                    nonfinite=nonfinite, where=where)
        elif rounds:
            self._replay_single_round(src, sp, counted, nonfinite, where)
        if n_bad[0] and nonfinite != "raise":
            # (samples are read in several passes, so no count is given)
            warnings.warn(f"{where}: values: sample(s) with NaN or Inf "
                          f"{'dropped' if nonfinite == 'drop' else 'set to 0'} (policy nonfinite={nonfinite!r})",
                          McreconWarning, stacklevel=2)
        self._set_diagnostics(run)
        if not rounds:
            warnings.warn(f"{where}: no samples at all; the image is 0", McreconWarning, stacklevel=2)
        return sp.image.copy()

    @staticmethod
    def _pixel_index(pos, width, height):
        ix = np.clip(np.floor(pos[:, 0]).astype(np.int64), 0, width - 1)
        iy = np.clip(np.floor(pos[:, 1]).astype(np.int64), 0, height - 1)
        return iy * width + ix

    def _replay_single_round(self, src, sp, counted, nonfinite, where):
        w, h = src.width, src.height
        n_p = np.zeros(w * h, np.int64)
        for ch in src.iter_chunks(with_round=False):
            n_p += np.bincount(self._pixel_index(np.asarray(ch.positions), w, h), minlength=w * h)
        m = int(n_p.min())
        if m == 0:
            # Some pixel has no sample at all: schedule for the mean count.
            m = max(1, int(n_p.sum() // (w * h)))
        sched = doubling_schedule(m, min(self.params["initial_spp"], m))
        ends = np.cumsum(sched)
        bounds = [np.zeros(w * h, np.int64)] + [(int(t) * n_p) // m for t in ends]
        bounds[-1] = n_p  # the last round takes every remaining sample of every pixel

        def pseudo_round(j):
            rank = np.zeros(w * h, np.int64)
            lo, hi = bounds[j], bounds[j + 1]
            for pos, val in counted(src.iter_chunks(with_round=False)):
                pos = np.asarray(pos)
                mask = np.empty(pos.shape[0], np.bool_)
                _select_by_rank(self._pixel_index(pos, w, h), rank, lo, hi, mask)
                if mask.any():
                    yield pos[mask], np.asarray(val)[mask]

        for j in range(len(sched)):
            sp.add_round_stream(lambda j=j: pseudo_round(j), nonfinite=nonfinite, where=where)

    # ----------------------------------------------------------- adaptive
    def plan(self, run: "SplatRun", state: AdaptiveState) -> SampleRequest | None:
        """Every pixel gets N_j samples: N_0 = initial_spp, N_j = 2 N_{j-1}, the last round absorbing the rest."""
        p_film = state.width * state.height
        total_spp = state.budget // p_film
        if total_spp < 1 and run.n_rounds_seen == 0:
            raise InputError(self.where, "spp", f"budget of {state.budget} samples is below one sample per "
                             f"pixel ({p_film} pixels): splatting rounds sample every pixel")
        rem = min(total_spp - int(round(run.spp_done)), state.remaining // p_film)
        if rem < 1:
            return None
        n = _next_round(rem, run.prev_spp, self.params["initial_spp"])
        return state.request(counts=np.full((state.height, state.width), n, np.int64))

    def observe(self, run: "SplatRun", batch: SampleBatch, round_index: int) -> None:
        """Splat a committed round.

        Non-finite values are dropped (the driver's statistics have already
        applied and reported its policy).
        """
        pos = np.asarray(batch.positions)
        val = np.asarray(batch.values)
        if val.ndim == 1:
            val = val[:, None]
        run.n_rounds_seen += 1
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", McreconWarning)
            run.splatter.add_round(pos, val, nonfinite="drop", where=self.where)
        run.prev_spp = pos.shape[0] / (run.width * run.height)
        run.spp_done += run.prev_spp

    def finish(self, run: "SplatRun", state: AdaptiveState) -> np.ndarray:
        """The running image f_J (a copy)."""
        self._set_diagnostics(run)
        if not run.splatter.rounds:
            warnings.warn("method splat: no round observed; the image is 0", McreconWarning, stacklevel=2)
        return run.splatter.image.copy()

    @staticmethod
    def _set_diagnostics(run: "SplatRun") -> None:
        run.diagnostics["kernel_width"] = run.splatter.last_widths.copy()


@dataclasses.dataclass(eq=False)
class SplatRun(RunState):
    """Per-run state of :class:`SplatMethod`: the progressive splatter and the round schedule so far."""

    splatter: ProgressiveSplatter | None = None
    prev_spp: float | None = None
    spp_done: float = 0.0
    n_rounds_seen: int = 0

"""``gem``: adaptive sampling and reconstruction by greedy error minimization.

Rousselle, Knaus and Zwicker (2011) pick, at every pixel, one filter out
of a fixed bank (the renderer's pixel filter and Gaussians at growing
scales) so that the pixel's MSE is minimal, and send new samples where
the *relative* MSE of the selected filters falls fastest.  This module
implements every element of the paper; ``docs/methods/gem.md`` maps each
equation and section to the function implementing it.

Pipeline (one call of :func:`gem_select`):

1. **Finest scale** (the pixel filter, unbiased): the pixel mean, with the
   variance of Sec. 6 (:func:`mean_variance_policy`, explicit policy for
   n < 2).
2. **Filter bank** (Sec. 6): Gaussian scales, each the pixel-level
   equivalent of "Gaussian on the 4 x 4 subpixel grid, then box-reduce"
   (:func:`pixel_kernel`, exact when subpixels are constant per pixel);
   scales below ``subpixel_exact_below`` px are filtered on the hole-filled
   subpixel grid itself (:func:`filled_subpixels`: empty subpixels take
   the pixel mean, the paper's "two-step pull-push";
   :func:`subpixel_gaussian_exact`).  Variances from the per-pixel mean
   variances filtered with the *squared* kernel (Eq. 2, Sec. 6),
   :func:`filter_bank`.
3. **Scale selector** S (Eq. 1) per pair of consecutive scales with the
   bias term weighted by rho = 1 - 1/|P| and z(gamma) (Sec. 4.3),
   :func:`scale_selector_terms`; binary stopping maps ``S > 0``.
4. **Outlier removal** (Sec. 4.4, Sec. 6) on each stopping map,
   :func:`remove_outliers`; the selected scale is the finest with stop = 1
   (:func:`select_from_stops`).
5. **Sample distribution** (Sec. 5): accumulated MSE estimates, relative
   MSE with eps = 0.001, priority relMSE * n / (n + n_s); the m best pixels
   each get n samples importance-sampled over their filter,
   :func:`estimate_mse`, :func:`sample_priority`, :func:`distribute_samples`.

References
----------
.. [1] F. Rousselle, C. Knaus, M. Zwicker, "Adaptive Sampling and
   Reconstruction using Greedy Error Minimization", ACM Trans. Graph.
   30(6) (SIGGRAPH Asia), 2011.
.. [2] B. W. Silverman, "Density Estimation for Statistics and Data
   Analysis", Chapman & Hall, 1986 (bias of kernel estimators ~ r^2).
.. [3] D. P. Mitchell, "Generating antialiased images at low sampling
   densities", SIGGRAPH 1987 (subpixel grid for non-uniform densities).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np
from scipy import ndimage

from ..errors import InputError
from ..stats import PixelStats
from .base import AdaptiveState, Method, MethodInputs, Option, Requirements, RunState

__all__ = [
    "GEMMethod",
    "GAMMA_MAX",
    "SAMPLING_EPS",
    "z_of_gamma",
    "check_gamma",
    "adaptive_sigmas",
    "final_sigmas",
    "gaussian_kernel",
    "pixel_kernel",
    "filled_subpixels",
    "subpixel_gaussian_exact",
    "mean_variance_policy",
    "FilterBank",
    "filter_bank",
    "bias_coefficient",
    "scale_selector_terms",
    "stopping_maps",
    "remove_outliers",
    "select_from_stops",
    "GEMSelection",
    "gem_select",
    "oracle_select",
    "estimate_mse",
    "sample_priority",
    "distribute_samples",
    "error_rate_experiment",
]

#: gamma must lie in (0, GAMMA_MAX): the paper's z(gamma) is "valid in the
#: range 0 < gamma < 0.4" (and undefined from 1.9 gamma >= 1, gamma ~ 0.526).
GAMMA_MAX = 0.4
#: Sec. 5: relative MSE for sampling divides by value^2 + 0.001.
SAMPLING_EPS = 1e-3
#: Relative MSE of the user's target (option ``target_rel_mse``): the same
#: eps as :func:`mcrecon.metrics.relative_mse`, so the target means what the
#: reported error means.
TARGET_EPS = 1e-2
#: Gaussian kernels are truncated at this many standard deviations (the
#: tails hold 0.27 % of the weight) and renormalised.
TRUNCATE = 3.0
#: Outlier-removal rules of the final reconstruction (see :func:`gem_select`).
OUTLIER_RULES = ("paper", "adaptive")

_WHERE = "method gem"


# ----------------------------------------------------------------------------
# Parameters
# ----------------------------------------------------------------------------

def check_gamma(gamma, where: str = _WHERE) -> float:
    """Validate the error-rate parameter: a real number with 0 < gamma < 0.4.

    Raises
    ------
    InputError
        Naming ``gamma`` and the valid range.
    """
    try:
        g = float(gamma)
    except (TypeError, ValueError):
        raise InputError(where, "gamma", f"{gamma!r} is not a number; expected 0 < gamma < {GAMMA_MAX} "
                         "(the target error rate of the scale selector, default 0.2)") from None
    if not (0.0 < g < GAMMA_MAX):
        raise InputError(where, "gamma", f"{gamma!r} is outside 0 < gamma < {GAMMA_MAX}: the paper's "
                         "z(gamma) = -log(1 - (1.9 gamma)^(1/sqrt 2)) is only calibrated there "
                         "(and undefined from gamma ~ 0.526); use e.g. 0.1 to 0.3, default 0.2")
    return g


def z_of_gamma(gamma) -> float:
    """Bias-term weight controlling the error rate (Sec. 4.3).

    ``z(gamma) = -log(1 - (1.9 gamma)^(1/sqrt(2)))``, valid for
    ``0 < gamma < 0.4``.

    References
    ----------
    .. [1] Rousselle et al. 2011, Sec. 4.3 "Intuitive Parameterization".
    """
    g = check_gamma(gamma)
    return -math.log(1.0 - (1.9 * g) ** (1.0 / math.sqrt(2.0)))


def adaptive_sigmas(n: int = 4) -> np.ndarray:
    """Gaussian scales of the adaptive phase: ``n`` dyadic scales from 1 px (Sec. 6)."""
    return 2.0 ** np.arange(int(n), dtype=np.float64)


def final_sigmas(n: int = 8) -> np.ndarray:
    """Gaussian scales of the final reconstruction: ``n`` scales sqrt(2) apart from sqrt(2) px (Sec. 6)."""
    return math.sqrt(2.0) ** np.arange(1, int(n) + 1, dtype=np.float64)


# ----------------------------------------------------------------------------
# Kernels
# ----------------------------------------------------------------------------

def gaussian_kernel(sigma: float, *, truncate: float = TRUNCATE) -> np.ndarray:
    """Sampled, normalised 1-D Gaussian on the integer lattice, radius ceil(truncate * sigma)."""
    sigma = float(sigma)
    r = max(1, int(math.ceil(truncate * sigma)))
    d = np.arange(-r, r + 1, dtype=np.float64)
    k = np.exp(-0.5 * (d / sigma) ** 2)
    return k / k.sum()


def pixel_kernel(sigma: float, subpixels: int = 4, *, truncate: float = TRUNCATE) -> np.ndarray:
    """Pixel-level 1-D kernel equivalent to subpixel Gaussian filtering + box reduction.

    Filtering an ``s x s`` subpixel grid with a sampled Gaussian of
    ``sigma * s`` subpixels and then averaging each pixel's subpixels
    equals, whenever the subpixel values are constant within each pixel,
    a pixel-level separable filter with the 1-D kernel

    ``k(d) = (1/s) * sum_{a,b=0}^{s-1} g_sub(s d + b - a)``

    (box (x) Gaussian (x) box, discretised exactly).  This is the kernel
    applied to the box-reduced finest scale (:func:`filter_bank`); the
    residual difference to filtering the raw subpixel grid is measured in
    ``tests/test_gem.py`` and documented in ``docs/methods/gem.md``.

    Parameters
    ----------
    sigma : float
        Standard deviation in pixels.
    subpixels : int
        Subpixels per pixel axis (1: a plain sampled Gaussian).
    """
    # the same few scales recur every round: each kernel is built once
    return _pixel_kernel_cached(float(sigma), max(1, int(subpixels)), float(truncate)).copy()


@functools.lru_cache(maxsize=64)
def _pixel_kernel_cached(sigma: float, s: int, truncate: float) -> np.ndarray:
    g = gaussian_kernel(sigma * s, truncate=truncate)
    rs = (g.size - 1) // 2
    # offsets j = s d + b - a for a, b in [0, s) reach |j| <= rs from pixel
    # offsets |d| <= floor((rs + s - 1) / s).
    rd = (rs + s - 1) // s
    k = np.zeros(2 * rd + 1)
    for a in range(s):
        for b in range(s):
            for di, d in enumerate(range(-rd, rd + 1)):
                j = s * d + b - a
                if -rs <= j <= rs:
                    k[di] += g[j + rs]
    k /= s
    return k / k.sum()


def _phase_kernels(sigma: float, s: int, truncate: float = TRUNCATE):
    """Polyphase pieces h_beta(d) = (1/s) sum_a g_sub(s d + beta - a), beta in [0, s)."""
    g = gaussian_kernel(sigma * s, truncate=truncate)
    rs = (g.size - 1) // 2
    rd = (rs + s - 1) // s
    h = np.zeros((s, 2 * rd + 1))
    for beta in range(s):
        for a in range(s):
            for di, d in enumerate(range(-rd, rd + 1)):
                j = s * d + beta - a
                if -rs <= j <= rs:
                    h[beta, di] += g[j + rs]
    return h / s


# ----------------------------------------------------------------------------
# Separable normalised filtering
# ----------------------------------------------------------------------------
#
# All separable filtering of the method (filter bank, outlier removal) goes
# through one compiled kernel that performs, term for term, the arithmetic of
# ``scipy.ndimage.correlate1d(mode="constant", cval=0)`` applied along axis 0
# and then axis 1 (symmetric odd kernel: ``k_0 x_0 + sum_j k_j (x_-j + x_j)``
# in double precision, outermost taps first, the first pass rounded to the
# array's dtype), so its results are bit-identical to that reference (tested).
# It fuses both passes row by row (no intermediate image), runs on contiguous
# rows the compiler vectorises (ndimage gathers strided lines along axis 0),
# folds in the normalisation by the weight sums, and releases the GIL, so the
# independent convolutions of a filter bank run on a small thread pool; each
# output element is computed by exactly one thread in a fixed order, so the
# result does not depend on the number of threads.

#: Worker threads for the filter bank and the outlier removal (None: the
#: usable cores, at most 8).  Results are identical for every value.
THREADS: int | None = None
#: Images smaller than this (pixels x channels) are filtered on the calling
#: thread: handing work to the pool costs more than it saves.
_PARALLEL_MIN = 1 << 15
_POOL = None
_POOL_SIZE = 0
_POOL_PID = 0
_POOL_LOCK = threading.Lock()


def _n_threads(threads: int | None = None) -> int:
    t = THREADS if threads is None else threads
    if t is None:
        try:
            t = len(os.sched_getaffinity(0))
        except (AttributeError, OSError):
            t = os.cpu_count() or 1
        t = min(t, 8)
    return max(1, int(t))


def _pool(n: int) -> ThreadPoolExecutor:
    global _POOL, _POOL_SIZE, _POOL_PID
    with _POOL_LOCK:
        # a forked child inherits the pool object but not its threads: new pool
        if _POOL is None or _POOL_SIZE != n or _POOL_PID != os.getpid():
            if _POOL is not None and _POOL_PID == os.getpid():
                _POOL.shutdown(wait=False)
            _POOL = ThreadPoolExecutor(max_workers=n, thread_name_prefix="mcrecon-gem")
            _POOL_SIZE, _POOL_PID = n, os.getpid()
        return _POOL


@numba.njit(cache=True, nogil=True)
def _add_pair(acc, a, b, kk):
    # acc += (a + b) * kk in double precision (ndimage's symmetric tap)
    for q in range(acc.size):
        acc[q] += (np.float64(a[q]) + np.float64(b[q])) * kk


@numba.njit(cache=True, nogil=True)
def _corr2_rows(x, k, c, den, mode, out, i0, i1):
    """Rows i0..i1-1 of the separable correlation of x (H, W*c) with k.

    mode 0: out = result (x's dtype); 1: out = result / den[i, j] where
    den > 0, else 0; 2: out = den[i, j] / result where result > 0, else 0
    (modes 1 and 2 read the result in x's dtype, as ``_safe_div`` of the
    ndimage output would).
    """
    h, n = x.shape
    r = k.size // 2
    pad = r * c
    zero = np.zeros(n, x.dtype)
    acc = np.empty(n, np.float64)
    rnd = np.empty(n, x.dtype)
    buf = np.zeros(n + 2 * pad, np.float64)
    k0 = k[r]
    w = n // c
    for i in range(i0, i1):
        # axis 0: rows outside the image are zeros (mode constant, cval 0)
        xi = x[i]
        for q in range(n):
            acc[q] = np.float64(xi[q]) * k0
        for jj in range(-r, 0):
            lo = i + jj
            hi = i - jj
            a = x[lo] if lo >= 0 else zero
            b = x[hi] if hi < h else zero
            _add_pair(acc, a, b, k[r + jj])
        rnd[:] = acc                      # ndimage stores the first pass in x's dtype
        # axis 1 on the zero-padded row, channel stride c
        for q in range(n):
            buf[pad + q] = rnd[q]
        for q in range(n):
            acc[q] = buf[pad + q] * k0
        for jj in range(-r, 0):
            d = -jj * c
            _add_pair(acc, buf[pad - d:pad - d + n], buf[pad + d:pad + d + n], k[r + jj])
        rnd[:] = acc
        if mode == 0:
            for q in range(n):
                out[i, q] = rnd[q]
        elif mode == 1:
            for j in range(w):
                dv = den[i, j]
                for ch in range(c):
                    q = j * c + ch
                    out[i, q] = np.float64(rnd[q]) / dv if dv > 0 else 0.0
        else:
            for j in range(w):
                for ch in range(c):
                    q = j * c + ch
                    v = np.float64(rnd[q])
                    out[i, q] = den[i, j] / v if v > 0 else 0.0


def _symmetric_odd(k: np.ndarray) -> bool:
    """ndimage's own test for its symmetric-kernel arithmetic."""
    r = k.size // 2
    eps = np.finfo(np.float64).eps
    return k.size % 2 == 1 and bool(np.all(np.abs(k[r + 1:] - k[r - 1::-1][:r]) <= eps))


def _correlate_jobs(jobs, threads: int | None = None) -> list:
    """Run separable correlations; ``jobs`` is a list of ``(x, k, den, mode)``.

    x : (H, W) or (H, W, C); k : 1-D kernel (used as float64, as ndimage
    does); den : (H, W) or None; mode 0 returns the correlation in x's
    dtype, mode 1 ``_safe_div(corr, den[..., None])`` and mode 2
    ``_safe_div(den[..., None], corr)`` (float64).  Independent jobs, and
    row blocks of large ones, run on the thread pool.
    """
    outs, tasks = [], []
    dummy = np.zeros((1, 1))
    for x, k, den, mode in jobs:
        k = np.asarray(k, dtype=np.float64)
        shape = x.shape
        if not _symmetric_odd(k):
            # (never for the method's Gaussian kernels) the reference path
            y = ndimage.correlate1d(x, k, axis=0, mode="constant", cval=0.0)
            y = ndimage.correlate1d(y, k, axis=1, mode="constant", cval=0.0)
            if mode == 1:
                y = _safe_div(y, den if y.ndim == 2 else den[..., None])
            elif mode == 2:
                y = _safe_div(den if y.ndim == 2 else den[..., None], y.astype(np.float64))
            outs.append(y)
            continue
        h, w = shape[0], shape[1]
        c = int(np.prod(shape[2:], dtype=np.int64)) if len(shape) > 2 else 1
        x2 = np.ascontiguousarray(x).reshape(h, w * c)
        out = np.empty(shape, dtype=x.dtype if mode == 0 else np.float64)
        d2 = dummy if den is None else np.ascontiguousarray(den, dtype=np.float64)
        outs.append(out)
        tasks.append((x2, k, c, d2, mode, out.reshape(h, w * c), h))
    n = _n_threads(threads)
    if n == 1 or sum(t[0].size for t in tasks) < _PARALLEL_MIN:
        for x2, k, c, d2, mode, o2, h in tasks:
            _corr2_rows(x2, k, c, d2, mode, o2, 0, h)
        return outs
    # large jobs are cut into row blocks (up to 2 per thread) so the threads
    # finish together; small ones stay whole (a task costs ~20 us)
    futs = []
    pool = _pool(n)
    for x2, k, c, d2, mode, o2, h in tasks:
        nb = max(1, min(h, 2 * n, x2.size // (4 * _PARALLEL_MIN)))
        edges = np.linspace(0, h, nb + 1).astype(np.int64)
        for a, b in zip(edges[:-1], edges[1:]):
            if b > a:
                futs.append(pool.submit(_corr2_rows, x2, k, c, d2, mode, o2, int(a), int(b)))
    for f in futs:
        f.result()
    return outs


def _corr2(x: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Separable correlation over axes 0 and 1 with zeros outside the image
    (bit-identical to ``ndimage.correlate1d`` along axis 0, then axis 1)."""
    return _correlate_jobs([(x, k, None, 0)])[0]


def _weights_1d(h: int, w: int, k: np.ndarray) -> np.ndarray:
    # mask all ones: the 2-D sum is the product of the 1-D border sums
    wy = ndimage.correlate1d(np.ones(h), k, mode="constant", cval=0.0)
    wx = ndimage.correlate1d(np.ones(w), k, mode="constant", cval=0.0)
    return np.multiply.outer(wy, wx)


def _weights(mask: np.ndarray, k: np.ndarray, full: bool) -> np.ndarray:
    """Sum of the kernel weights over valid pixels, W(p) = sum_q m_q K(p - q)."""
    h, w = mask.shape
    if full:
        return _weights_1d(h, w, k)
    return _corr2(mask.astype(np.float64), k)


def _safe_div(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    out = np.zeros(np.broadcast_shapes(num.shape, den.shape))
    np.divide(num, den, out=out, where=den > 0)
    return out


# ----------------------------------------------------------------------------
# Finest scale and variances
# ----------------------------------------------------------------------------

def mean_variance_policy(stats: PixelStats) -> np.ndarray:
    """Variance of each pixel's mean, ``s^2 / n`` (Sec. 6), with a policy for n < 2.

    Policy (documented in ``docs/methods/gem.md``): a pixel with a single
    sample has no sample variance of its own; it borrows the average sample
    variance of the pixels with n >= 2 in its 3 x 3 neighbourhood, else the
    image-wide average over pixels with n >= 2, else (no pixel has two
    samples, e.g. a 1-spp log) the variance of the pixel values in its 3 x 3
    neighbourhood (signal plus noise: conservative, it errs towards
    keeping detail).  Empty pixels get 0 (they are masked out).

    Returns
    -------
    ndarray (H, W, C) float64
    """
    n = stats.count
    var = stats.sample_variance(undefined=0.0)
    need = n == 1
    if need.any():
        ok = ((n >= 2) & ~need).astype(np.float64)
        if ok.any():
            num = ndimage.uniform_filter(var * ok[..., None], size=(3, 3, 1), mode="constant")
            den = ndimage.uniform_filter(ok, size=3, mode="constant")[..., None]
            local = _safe_div(num, den)
            glob = var[ok > 0].mean(axis=0)
            sub = np.where(den > 1e-12, local, glob)
        else:
            has = (n >= 1).astype(np.float64)
            m = stats.mean * has[..., None]
            den = ndimage.uniform_filter(has, size=3, mode="constant")[..., None]
            m1 = _safe_div(ndimage.uniform_filter(m, size=(3, 3, 1), mode="constant"), den)
            m2 = _safe_div(ndimage.uniform_filter(m * m, size=(3, 3, 1), mode="constant"), den)
            sub = np.maximum(m2 - m1 * m1, 0.0)
        var = np.where(need[..., None], sub, var)
    return var / np.maximum(n, 1)[..., None]


def filled_subpixels(stats: PixelStats) -> np.ndarray:
    """The hole-filled subpixel grid (sH, sW, C): subpixel means, empty ones the pixel mean,
    subpixels of empty pixels 0."""
    s = stats.subpixels
    if not s:
        raise InputError("filled_subpixels", "stats", "needs subpixel statistics (subpixels=4)")
    sub = stats.subpixel_means(fill="pixel")
    empty = stats.count == 0
    if empty.any():
        sub[np.repeat(np.repeat(empty, s, axis=0), s, axis=1)] = 0.0
    return sub


def subpixel_gaussian_exact(sub: np.ndarray, count: np.ndarray, sigma: float, *,
                            truncate: float = TRUNCATE) -> np.ndarray:
    """Gaussian on the filled subpixel grid, then box reduction (the paper's Sec. 6 filtering).

    The sampled Gaussian (``sigma * s`` subpixels) is applied to the
    ``sH x sW`` grid of subpixel means (:func:`filled_subpixels`;
    subpixels of empty pixels are excluded by normalisation) and each
    pixel takes the average of its subpixels.  Done in polyphase form
    (filter and decimate in one step): 10-20x the cost of the pixel-level
    path of :func:`filter_bank`.

    Parameters
    ----------
    sub : ndarray (sH, sW, C)
    count : ndarray (H, W)
    sigma : float

    Returns
    -------
    ndarray (H, W, C)
    """
    h, w = count.shape
    s = sub.shape[0] // h
    mask = count > 0
    ph = _phase_kernels(sigma, s, truncate)
    # x: (sH, sW, C) -> (sH, W, C)
    tx = ndimage.correlate1d(sub[:, 0::s], ph[0], axis=1, mode="constant", cval=0.0)
    for b in range(1, s):
        tx += ndimage.correlate1d(sub[:, b::s], ph[b], axis=1, mode="constant", cval=0.0)
    # y: (sH, W, C) -> (H, W, C)
    t = ndimage.correlate1d(tx[0::s], ph[0], axis=0, mode="constant", cval=0.0)
    for b in range(1, s):
        t += ndimage.correlate1d(tx[b::s], ph[b], axis=0, mode="constant", cval=0.0)
    k = pixel_kernel(sigma, s, truncate=truncate)
    wsum = _weights(mask, k, bool(mask.all()))
    return _safe_div(t, wsum[..., None])


# ----------------------------------------------------------------------------
# Filter bank
# ----------------------------------------------------------------------------

@dataclasses.dataclass(eq=False)
class FilterBank:
    """Filtered images of every scale (index 0: the pixel filter).

    Attributes
    ----------
    sigmas : ndarray (K,)
        Gaussian standard deviations (pixels) of scales 1..K.
    values : list of ndarray (H, W, C)
        Filtered values per scale.
    var : list of ndarray (H, W, C) or (H, W)
        Estimated variance of each filtered value (per channel, or summed
        over channels when built with ``per_channel=False``).
    weight : list of ndarray (H, W)
        Sum of kernel weights over pixels with samples (0: no data in the
        support).
    n_eff : list of ndarray (H, W) or None
        Effective sample count of each filter (see :func:`filter_bank`).
    """

    sigmas: np.ndarray
    values: list
    var: list
    weight: list
    n_eff: list | None
    #: sqrt of the second moment (pixels^2) of each scale's applied 2-D-separable
    #: pixel kernel (:func:`kernel_radius`); None: the nominal sigmas.
    radii: np.ndarray | None = None

    @property
    def n_scales(self) -> int:
        return len(self.values)


def filter_bank(base: np.ndarray, mean_var: np.ndarray, count: np.ndarray, sigmas, *,
                subpixels: int = 4, per_channel: bool = True, with_n_eff: bool = False,
                sub: np.ndarray | None = None, exact_below: float = 0.0,
                truncate: float = TRUNCATE, threads: int | None = None) -> FilterBank:
    """Filter the finest scale and its variances at every Gaussian scale (Sec. 6, Eq. 2).

    Values: ``c_k(p) = sum_q m_q K_k(p - q) base_q / W_k(p)`` with ``K_k``
    the separable :func:`pixel_kernel` of scale k, ``m`` the mask of pixels
    with samples and ``W_k(p) = sum_q m_q K_k(p - q)`` (weights renormalised
    at the border and around empty pixels, so no mirrored -- correlated --
    samples enter).  Variances with the squared weights (Eq. 2, valid
    because the per-pixel estimates share no samples):
    ``Var[c_k](p) = sum_q m_q K_k(p - q)^2 Var[p_q] / W_k(p)^2``.

    ``with_n_eff`` adds the effective sample count of each filter,
    ``n_s = 1 / sum_q w_q^2 / n_q`` (w the normalised weights): with a
    common per-sample variance the filter's variance is ``sigma^2 / n_s``,
    so adding n samples spread in proportion to w multiplies it by
    ``n_s / (n + n_s)`` (Sec. 5); for the pixel filter n_s = n.

    Parameters
    ----------
    base : ndarray (H, W, C)
        Finest scale: the pixel means (0 where empty).
    mean_var : ndarray (H, W, C)
        Variance of each pixel's value (:func:`mean_variance_policy`).
    count : ndarray (H, W)
        Samples per pixel (0 = masked out).
    sigmas : sequence of float
        Gaussian scales in pixels, fine to coarse.
    per_channel : bool
        Keep variances per channel (needed for relative MSE) or summed over
        channels (enough for the selection, one plane per scale).
    sub : ndarray (sH, sW, C), optional
        The filled subpixel grid (:func:`filled_subpixels`); with
        ``exact_below`` > 0 the values of scales with sigma < exact_below
        are computed on it exactly (:func:`subpixel_gaussian_exact`)
        instead of on the box-reduced finest scale.
    threads : int, optional
        Worker threads for the convolutions (default :data:`THREADS`);
        the result is bit-identical for any value.
    """
    sig = np.asarray(sigmas, dtype=np.float64)
    mask = count > 0
    full = bool(mask.all())
    mf = mask.astype(np.float64)
    v = mean_var if per_channel else _chan_sum(mean_var)
    if full:
        # x * 1.0 == x: masking is the identity, skip its copies (the product
        # was float64: so is the filtered array)
        mb, mv = np.asarray(base, dtype=np.float64), v
    else:
        mb = base * mf[..., None]
        mv = v * (mf[..., None] if per_channel else mf)
    values = [base]
    var = [v]
    weight = [mf]
    n_eff = None
    if with_n_eff:
        n_eff = [count.astype(np.float64)]
        inv_n = _safe_div(mf, count.astype(np.float64))
    # Variances and sample counts only weigh decisions: float32 halves their
    # filtering cost at 1e-7 relative precision (values stay float64).
    mv = mv.astype(np.float32)
    if with_n_eff:
        inv_n = inv_n.astype(np.float32)
    h, w_ = count.shape
    kernels = [pixel_kernel(s_, subpixels, truncate=truncate) for s_ in sig]
    # The weight sums first (separable products, or filtered masks), then every
    # convolution of every scale as independent jobs on the thread pool.
    if full:
        ws = [_weights_1d(h, w_, k) for k in kernels]
    else:
        ws = _correlate_jobs([(mf, k, None, 0) for k in kernels], threads)
    jobs = []
    for s_, k, w in zip(sig, kernels, ws):
        k2 = (k * k).astype(np.float32)
        w2 = w * w
        if not (sub is not None and s_ < exact_below):
            jobs.append((mb, k, w, 1))
        jobs.append((mv, k2, w2, 1))
        if with_n_eff:
            jobs.append((inv_n, k2, w2, 2))
    res = iter(_correlate_jobs(jobs, threads))
    for s_, w in zip(sig, ws):
        if sub is not None and s_ < exact_below:
            values.append(subpixel_gaussian_exact(sub, count, s_, truncate=truncate))
        else:
            values.append(next(res))
        var.append(next(res))
        weight.append(w)
        if with_n_eff:
            n_eff.append(next(res))
    radii = np.array([kernel_radius(s_, subpixels, truncate=truncate) for s_ in sig])
    return FilterBank(sig, values, var, weight, n_eff, radii)


# ----------------------------------------------------------------------------
# Scale selector (Eq. 1)
# ----------------------------------------------------------------------------

def bias_coefficient(r_f: float, r_c: float) -> float:
    """Factor of (c - f)^2 in the approximate bias term (Sec. 4.2).

    With ``Bias[c] = (r_c^2 / r_f^2) Bias[f]`` (quadratic image, kernels
    with vanishing first moments) and ``c - f = Bias[c] - Bias[f]``:
    ``Bias[c]^2 - Bias[f]^2 = (r_c^2 + r_f^2) / (r_c^2 - r_f^2) (c - f)^2``.
    The paper prints the denominator as ``r_f^2 - r_c^2``, which would make
    the bias term of a coarser scale negative; the derivation gives the
    positive form used here (5/3 for dyadic scales, 3 for sqrt(2) steps).
    ``r_f = 0`` (the pixel filter, unbiased) gives 1: the exact squared
    difference of Sec. 6.
    """
    r_f, r_c = float(r_f), float(r_c)
    if not r_c > r_f >= 0:
        raise InputError("bias_coefficient", "r_f, r_c", f"got {r_f}, {r_c}; expected 0 <= r_f < r_c")
    return (r_c * r_c + r_f * r_f) / (r_c * r_c - r_f * r_f)


def scale_selector_terms(f, c, var_f, var_c, *, r_f: float, r_c: float, n, gamma: float | None):
    """The scale selector S of Eq. 1 and its two terms.

    ``bias = rho * z(gamma) * coef(r_f, r_c) * (c - f)^2`` with
    ``rho = 1 - 1/|P|`` (Sec. 4.3), ``variance = Var[c] - Var[f]`` and
    ``S = bias + variance``.  ``S > 0`` means "stop at the fine scale".
    ``gamma=None`` leaves the bias unweighted (the plain MSE difference of
    Eq. 1, used for MSE accumulation and ground-truth experiments).
    ``r_f = 0`` denotes the pixel filter (exact squared difference).

    Parameters
    ----------
    f, c : array_like
        Fine and coarse filtered values (same shape).
    var_f, var_c : array_like
        Their variances.
    n : array_like or float
        Samples in the pixel, |P| (rho = 1 - 1/max(n, 1)).

    Returns
    -------
    bias, variance, S : ndarray
    """
    f = np.asarray(f, dtype=np.float64)
    c = np.asarray(c, dtype=np.float64)
    d = c - f
    bias = bias_coefficient(r_f, r_c) * d * d
    if gamma is not None:
        rho = 1.0 - 1.0 / np.maximum(np.asarray(n, dtype=np.float64), 1.0)
        bias = bias * (rho * z_of_gamma(gamma))
    variance = np.asarray(var_c, dtype=np.float64) - np.asarray(var_f, dtype=np.float64)
    return bias, variance, bias + variance


def kernel_radius(sigma: float, subpixels: int = 4, *, truncate: float = TRUNCATE) -> float:
    """Radius r of Sec. 4.2 for a scale: sqrt of the second moment of the applied kernel.

    ``Bias[c] = (r_c^2 / r_f^2) Bias[f]`` holds on quadratic images when r^2
    is the kernel's second moment.  The deployed :func:`pixel_kernel` is a
    truncated Gaussian convolved with the subpixel boxes, whose second
    moment exceeds sigma^2 (1.14 for sigma = 1, 62.5 for sigma = 8), so the
    nominal sigma would understate the bias term by 4-6 % on the first pairs.
    """
    return _kernel_radius_cached(float(sigma), max(1, int(subpixels)), float(truncate))


@functools.lru_cache(maxsize=64)
def _kernel_radius_cached(sigma: float, s: int, truncate: float) -> float:
    k = _pixel_kernel_cached(sigma, s, truncate)
    x = np.arange(k.size) - (k.size - 1) / 2.0
    return float(np.sqrt(np.sum(k * x * x) / np.sum(k)))


def _pair_radii(bank, k):
    """(r_f, r_c) of the pair (k, k+1); scale 0 is the pixel filter (r = 0)."""
    r = bank.sigmas if bank.radii is None else bank.radii
    return (0.0 if k == 0 else float(r[k - 1])), float(r[k])


def _chan_sum(v: np.ndarray) -> np.ndarray:
    """``v.sum(axis=2)`` (a 2-D ``v`` as is), bit for bit: numpy reduces a
    short axis left to right, which the compiled loop repeats in one pass
    instead of numpy's slow short-axis reduction (equality tested)."""
    if v.ndim == 2:
        return v
    if v.shape[2] > 4:
        return v.sum(axis=2)
    h, w, c = v.shape
    out = np.empty((h, w), dtype=v.dtype)
    _chan_sum_kernel(np.ascontiguousarray(v).reshape(h * w, c), out.reshape(-1))
    return out


@numba.njit(cache=True, nogil=True)
def _chan_sum_kernel(v, out):
    n, c = v.shape
    for p in range(n):
        s = v[p, 0]
        for ch in range(1, c):
            s += v[p, ch]
        out[p] = s


@numba.njit(cache=True, nogil=True)
def _stop_pair(e, coef, vsc, vsf, rho_z, weighted, delta, stop):
    # b = coef |c - f|^2, vterm = Var[c] - Var[f]; delta = b + vterm;
    # stop = (rho z b + vterm > 0), the arithmetic of the numpy expressions
    h, w = e.shape
    for i in range(h):
        for j in range(w):
            b = coef * e[i, j]
            vt = vsc[i, j] - vsf[i, j]
            d = b + vt
            delta[i, j] = d
            stop[i, j] = ((b * rho_z[i, j] + vt) if weighted else d) > 0


def stopping_maps(bank: FilterBank, count: np.ndarray, gamma: float | None):
    """Binary stopping maps ``S_k > 0`` for every pair (k, k+1), and the unweighted S_k.

    Channels are combined by summing S over channels (the total squared
    error of the pixel).  Returns ``stops`` (K, H, W) bool and ``delta``
    (K, H, W), the unweighted estimate of MSE[k+1] - MSE[k] summed over
    channels.
    """
    nk = bank.n_scales - 1
    h, w = count.shape
    stops = np.zeros((nk, h, w), bool)
    delta = np.zeros((nk, h, w))
    rho_z = np.zeros((1, 1))
    if gamma is not None:
        rho_z = (1.0 - 1.0 / np.maximum(count, 1)) * z_of_gamma(gamma)
    # channel sums of each scale's variance, once (each serves two pairs)
    vsum = [_chan_sum(v) for v in bank.var]
    dv = None
    for k in range(nk):
        r_f, r_c = _pair_radii(bank, k)
        dv = np.subtract(bank.values[k + 1], bank.values[k], out=dv)
        e = np.einsum("ijc,ijc->ij", dv, dv)
        _stop_pair(e, bias_coefficient(r_f, r_c), vsum[k + 1], vsum[k], rho_z, gamma is not None,
                   delta[k], stops[k])
    return stops, delta


# ----------------------------------------------------------------------------
# Outlier removal (Sec. 4.4, Sec. 6)
# ----------------------------------------------------------------------------

def remove_outliers(stops: np.ndarray, sigmas, *, final: bool = False, size_factor: float | None = None,
                    voters: np.ndarray | None = None, truncate: float = TRUNCATE,
                    threads: int | None = None) -> np.ndarray:
    """Filter each binary stopping map and round it back to binary (Sec. 4.4, Sec. 6).

    Map k (pair k -> k+1) is filtered with a sampled Gaussian of the
    coarse scale's sigma (``final``: twice that, Sec. 6) with the centre
    pixel's weight set to 0 ("we ignore the center pixel", Sec. 4.4),
    renormalised over the pixels that vote; the result is rounded
    (>= 0.5 -> 1).  With ``final`` only changes towards the coarser scale
    (1 -> 0) are accepted.  A pixel without voting neighbours in the
    support keeps its value.

    Parameters
    ----------
    stops : ndarray (K, H, W) bool
    sigmas : sequence of float (K,)
        Gaussian scales; the coarse scale of pair k is ``sigmas[k]``.
    final : bool
        The final-reconstruction rule of Sec. 6 (twice the size, coarser-only).
    size_factor : float, optional
        Override the size factor (default 1, or 2 with ``final``).
    voters : ndarray (H, W) bool, optional
        Pixels whose decisions count in the neighbourhood vote (default
        all).  :func:`gem_select` excludes pixels that skip the search
        (zero estimated variance, no samples): they did not decide anything.
    threads : int, optional
        Worker threads for the map filtering (bit-identical for any value).
    """
    factor = size_factor if size_factor is not None else (2.0 if final else 1.0)
    out = np.empty_like(stops)
    h, w = stops.shape[1:]
    vf = np.ones((h, w)) if voters is None else voters.astype(np.float64)
    full = voters is None or bool(voters.all())
    ks = [gaussian_kernel(factor * float(sigmas[k]), truncate=truncate) for k in range(stops.shape[0])]
    ms = [stops[k] * vf for k in range(stops.shape[0])]
    # every map's vote (and, with non-voters, every weight sum) is an
    # independent convolution: one batch on the thread pool
    jobs = [(m, g, None, 0) for m, g in zip(ms, ks)]
    if not full:
        jobs += [(vf, g, None, 0) for g in ks]
    conv = _correlate_jobs(jobs, threads)
    for k in range(stops.shape[0]):
        g = ks[k]
        g0 = g[(g.size - 1) // 2] ** 2             # centre weight of the 2-D kernel
        wsum = _weights_1d(h, w, g) if full else conv[stops.shape[0] + k]
        _vote(conv[k], ms[k], wsum, vf, g0, np.ascontiguousarray(stops[k]), bool(final), out[k])
    return out


@numba.njit(cache=True, nogil=True)
def _vote(conv, m, wsum, vf, g0, stop, final, out):
    # num = conv - g0 m and den = W - g0 v (the centre left out); the rounded
    # vote num / den >= 0.5, or the own decision where nobody else votes;
    # the final rule only accepts switches towards the coarser scale
    h, w = conv.shape
    for i in range(h):
        for j in range(w):
            num = conv[i, j] - g0 * m[i, j]
            den = wsum[i, j] - g0 * vf[i, j]
            f = stop[i, j] if den <= 1e-9 else (num / den) >= 0.5
            out[i, j] = (stop[i, j] and f) if final else f


def select_from_stops(stops: np.ndarray) -> np.ndarray:
    """Selected scale: the finest k with stop_k = 1, else the coarsest (K)."""
    nk = stops.shape[0]
    any_stop = stops.any(axis=0)
    first = np.argmax(stops, axis=0)
    return np.where(any_stop, first, nk).astype(np.int64)


# ----------------------------------------------------------------------------
# Whole selection
# ----------------------------------------------------------------------------

@dataclasses.dataclass(eq=False)
class GEMSelection:
    """Result of :func:`gem_select` / :func:`oracle_select`.

    Attributes
    ----------
    bank : FilterBank
    selected : ndarray (H, W) int
        Selected scale (0 = pixel filter).
    stops_raw, stops : ndarray (K, H, W) bool or None
        Stopping maps before and after outlier removal (None for the oracle).
    mse : ndarray (H, W, C)
        Estimated MSE of every pixel's selected filter, per channel.
    image : ndarray (H, W, C)
        Values of the selected scales.
    """

    bank: FilterBank
    selected: np.ndarray
    stops_raw: np.ndarray | None
    stops: np.ndarray | None
    mse: np.ndarray | None
    image: np.ndarray


def _pick(stack_list, selected):
    """Per pixel, the entry of the selected scale's array."""
    arrs = tuple(np.ascontiguousarray(a) for a in stack_list)
    if len({(a.dtype, a.shape) for a in arrs}) != 1:
        arrs = tuple(np.ascontiguousarray(a, dtype=np.result_type(*arrs)) for a in arrs)
    out = np.empty_like(arrs[0])
    sel = np.ascontiguousarray(selected, dtype=np.int64)
    h, w = sel.shape
    c = out.size // max(h * w, 1)
    _pick_kernel(tuple(a.reshape(h * w, c) for a in arrs), sel.reshape(-1), out.reshape(h * w, c))
    return out


@numba.njit(cache=True, nogil=True)
def _pick_kernel(arrs, sel, out):
    for p in range(sel.size):
        a = arrs[sel[p]]
        for c in range(out.shape[1]):
            out[p, c] = a[p, c]


def gem_select(base, mean_var, count, sigmas, *, gamma: float, final: bool, subpixels: int = 4,
               want_mse: bool = False, sub: np.ndarray | None = None, exact_below: float = 0.0,
               outlier_rule: str = "adaptive", zero_variance_votes: bool = False) -> GEMSelection:
    """Filter selection of Secs. 4 and 6 on pixel arrays (works for 1-D signals as 1 x N images).

    Stopping maps from Eq. 1 weighted by rho z(gamma); pixels without samples
    never stop at the pixel filter nor at a scale with no data in its
    support; outlier removal (adaptive or final rule); pixels with zero
    estimated variance in every channel take the pixel filter without a
    search (no filter can have a lower estimated MSE than 0).

    Parameters
    ----------
    base, mean_var : ndarray (H, W, C)
    count : ndarray (H, W)
    sigmas : sequence of float
    gamma : float
        0 < gamma < 0.4.
    final : bool
        Final reconstruction: use the final outlier rule.
    want_mse : bool
        Also estimate the selected filters' MSE per channel (for sampling).
    sub, exact_below : see :func:`filter_bank`.
    outlier_rule : {'paper', 'adaptive'}
        Rule of the final reconstruction: 'paper' (Sec. 6: outlier filter
        twice the coarse scale, only switches towards the coarser scale
        accepted) or 'adaptive' (the adaptive phase's rule: the coarse
        scale's size, both directions).  Ignored when not ``final``.
    zero_variance_votes : bool
        Whether pixels with zero estimated variance (which skip the search)
        vote in the outlier removal of their neighbours.  Their "stop" only
        reflects their own zero variance, not the local bias; see
        ``docs/methods/gem.md`` for the measured effect (off while sampling,
        on in the final reconstruction by default in :class:`GEMMethod`).

    Notes
    -----
    Channels are combined by summing S over channels (the pixel's total
    squared error), one scale per pixel.  z(gamma) was calibrated by the
    paper on one channel; with independent noise in three channels the
    realised error rate departs from gamma (measured in the tests).
    """
    count = np.asarray(count)
    if outlier_rule not in OUTLIER_RULES:
        raise InputError("gem_select", "outlier_rule", f"{outlier_rule!r}; valid: {', '.join(OUTLIER_RULES)}")
    bank = filter_bank(base, mean_var, count, sigmas, subpixels=subpixels, per_channel=want_mse,
                       with_n_eff=want_mse, sub=sub, exact_below=exact_below)
    stops_raw, _ = stopping_maps(bank, count, gamma)
    empty = count == 0
    for k in range(stops_raw.shape[0]):
        # no data of its own / in the fine scale's support: go coarser
        stops_raw[k] &= bank.weight[k] > 0
    zero_var = ~empty
    for c in range(mean_var.shape[2]):        # np.all(mean_var <= 0, axis=2), without the slow short axis
        zero_var &= mean_var[..., c] <= 0.0
    stops = remove_outliers(stops_raw, bank.sigmas, final=final and outlier_rule == "paper",
                            voters=~empty if zero_variance_votes else ~(empty | zero_var))
    for k in range(stops.shape[0]):
        stops[k] &= bank.weight[k] > 0
    stops[0] |= zero_var
    selected = select_from_stops(stops)
    image = _pick(bank.values, selected)
    mse = estimate_mse(bank, selected, count) if want_mse else None
    return GEMSelection(bank, selected, stops_raw, stops, mse, image)


def oracle_select(base, mean_var, count, sigmas, reference, *, subpixels: int = 4,
                  sub: np.ndarray | None = None, exact_below: float = 0.0) -> GEMSelection:
    """The paper's OUR-GRD selection: exhaustive argmin of bias^2 + Var with the true bias.

    The bias of scale k is ``K_k * reference - reference`` (the reference
    filtered exactly like the data, with the same mask); the pixel filter
    is unbiased.  The per-sample variance is a property of the renderer
    that a reference image does not carry, so the variances are the
    sample estimates (Eq. 2) -- the same ones GEM uses.  The MSE is summed
    over channels for the choice and kept per channel for sampling.
    """
    ref = np.asarray(reference, dtype=np.float64)
    count = np.asarray(count)
    bank = filter_bank(base, mean_var, count, sigmas, subpixels=subpixels, per_channel=True, with_n_eff=True,
                       sub=sub, exact_below=exact_below)
    rbank = filter_bank(ref, np.zeros_like(ref), count, sigmas, subpixels=subpixels, per_channel=False)
    mses = []
    for k in range(bank.n_scales):
        b = rbank.values[k] - ref
        m = b * b + bank.var[k]
        m = np.where((bank.weight[k] > 0)[..., None], m, np.inf)  # no data in the support
        mses.append(m)
    tot = np.stack([m.sum(axis=2) for m in mses])
    selected = np.argmin(tot, axis=0).astype(np.int64)
    image = _pick(bank.values, selected)
    mse = _pick(mses, selected)
    return GEMSelection(bank, selected, None, None, mse, image)


# ----------------------------------------------------------------------------
# Sample distribution (Sec. 5)
# ----------------------------------------------------------------------------

def estimate_mse(bank: FilterBank, selected: np.ndarray, count: np.ndarray) -> np.ndarray:
    """MSE of the selected filter per channel by accumulating Delta-MSE estimates (Sec. 5).

    ``MSE_0 = Var_0`` (the pixel filter is unbiased); ``MSE_{k+1} = MSE_k +
    bias_k + Var_{k+1} - Var_k`` with the unweighted approximate bias term
    of Eq. 1 (gamma only calibrates the decision).  An estimate below the
    selected filter's own variance is raised to it (MSE = bias^2 + Var >=
    Var).  Pixels without samples get +inf.
    """
    v0 = bank.values[0]
    if not (v0.ndim == 3 and all(v.shape == v0.shape for v in bank.var)):
        return _estimate_mse_numpy(bank, selected, count)
    h, w, c = v0.shape

    def flat(a):
        return np.ascontiguousarray(a, dtype=np.float64).reshape(h * w, c)

    sel = np.ascontiguousarray(selected, dtype=np.int64).reshape(-1)
    coefs = np.array([bias_coefficient(*_pair_radii(bank, k)) for k in range(bank.n_scales - 1)])
    out = np.empty((h * w, c))
    _mse_kernel(tuple(flat(v) for v in bank.values), tuple(flat(v) for v in bank.var), coefs, sel, out)
    out[np.asarray(count).reshape(-1) == 0] = np.inf
    return out.reshape(h, w, c)


@numba.njit(cache=True, nogil=True)
def _mse_kernel(values, var, coefs, sel, out):
    # MSE_0 = Var_0; MSE_{k+1} = MSE_k + coef_k (v_{k+1} - v_k)^2 + Var_{k+1} - Var_k,
    # accumulated only up to the pixel's selected scale s (the rest is never
    # read), in the order of the numpy in-place updates; out = max(MSE_s, Var_s)
    n, c = out.shape
    for p in range(n):
        s = sel[p]
        for ch in range(c):
            m = var[0][p, ch]
            for k in range(s):
                d = values[k + 1][p, ch] - values[k][p, ch]
                d = d * d
                d = d * coefs[k]
                m = m + d
                m = m + var[k + 1][p, ch]
                m = m - var[k][p, ch]
            out[p, ch] = m if s == 0 else max(m, var[s][p, ch])


def _estimate_mse_numpy(bank: FilterBank, selected: np.ndarray, count: np.ndarray) -> np.ndarray:
    # the reference formulation (any shapes numpy broadcasts)
    mse = bank.var[0].copy()
    out = mse.copy()
    for k in range(bank.n_scales - 1):
        r_f, r_c = _pair_radii(bank, k)
        dv = bank.values[k + 1] - bank.values[k]
        dv *= dv
        dv *= bias_coefficient(r_f, r_c)
        mse += dv
        mse += bank.var[k + 1]
        mse -= bank.var[k]
        sel = selected == k + 1
        out[sel] = np.maximum(mse[sel], bank.var[k + 1][sel])
    return np.where((count == 0)[..., None], np.inf, out)


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
                       n_per_pick: int, rng: np.random.Generator, *, subpixels: int = 4) -> np.ndarray:
    """Positions of ``n_total`` new samples (Sec. 5).

    The ``m = n_total // n_per_pick`` pixels of highest priority each get
    ``n_per_pick`` samples (the next one the remainder), placed in pixels
    drawn by importance sampling of their selected filter: the pixel
    filter keeps them in the pixel, a Gaussian scale draws the pixel
    offset from the separable pixel kernel (x and y independently), draws
    off the film are redrawn (the filter is renormalised there too).  Each
    sample lies uniformly at random inside its pixel.

    Returns
    -------
    ndarray (n_total, 2) float64
        Film positions (x = column, y = row).
    """
    h, w = selected.shape
    n_total = int(n_total)
    n_per_pick = max(1, int(n_per_pick))
    if n_total <= 0:
        return np.zeros((0, 2))
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
    pos = rng.random((n_all, 2))
    _place_in_pixels(pos, px, py, ox, oy)
    return pos


# ----------------------------------------------------------------------------
# Sec. 4.3 experiment (Figs. 4 and 5)
# ----------------------------------------------------------------------------

def error_rate_experiment(gamma: float | None, noise_var: float = 10.0, *, n_pixels: int = 1_000_000,
                          spp: int = 32, radius: float = 1.0, ratio: float = 2.0, seed: int = 0,
                          distribution: str = "normal") -> dict:
    """The paper's empirical analysis of S on a constant signal (Sec. 4.3).

    A 1-D signal of ``n_pixels`` pixels with value 0, ``spp`` samples per
    pixel of i.i.d. noise of variance ``noise_var``; fine and coarse
    Gaussians of sigma ``radius`` and ``ratio * radius`` applied to the
    pixel means (the samples carry no positions here, as in the paper);
    variances from the per-pixel sample variances (Eq. 3) through the
    squared kernels (Eq. 2).  The ideal decision is always "go coarser"
    (all biases are 0), so the error rate is the fraction of pixels with
    S > 0; the paper calibrates z(gamma) so that it is about gamma.

    Parameters
    ----------
    gamma : float or None
        None: unweighted S (Fig. 4).
    noise_var : float
        Variance of one sample.
    distribution : {'normal', 'uniform'}

    Returns
    -------
    dict
        ``bias``, ``variance``, ``S`` (arrays over the pixels, borders of
        4 * ratio * radius pixels dropped), ``error_rate`` (float),
        ``z``, ``rho`` and the parameters.
    """
    if gamma is not None:
        check_gamma(gamma, "error_rate_experiment")
    if not noise_var > 0:
        raise InputError("error_rate_experiment", "noise_var", f"got {noise_var!r}, expected > 0")
    if int(spp) < 2:
        raise InputError("error_rate_experiment", "spp", f"got {spp!r}, expected >= 2 (Eq. 3 needs two samples)")
    rng = np.random.default_rng(seed)
    n = int(n_pixels)
    if distribution == "normal":
        s = rng.normal(0.0, math.sqrt(noise_var), size=(n, int(spp)))
    elif distribution == "uniform":
        a = math.sqrt(3.0 * noise_var)
        s = rng.uniform(-a, a, size=(n, int(spp)))
    else:
        raise InputError("error_rate_experiment", "distribution", f"got {distribution!r}; valid: normal, uniform")
    mean = s.mean(axis=1)
    v = s.var(axis=1, ddof=1) / spp
    r_f, r_c = float(radius), float(ratio) * float(radius)
    kf, kc = gaussian_kernel(r_f), gaussian_kernel(r_c)
    f = ndimage.correlate1d(mean, kf, mode="wrap")
    c = ndimage.correlate1d(mean, kc, mode="wrap")
    vf = ndimage.correlate1d(v, kf * kf, mode="wrap")
    vc = ndimage.correlate1d(v, kc * kc, mode="wrap")
    cut = int(math.ceil(4 * r_c))
    sl = slice(cut, n - cut) if n > 2 * cut else slice(None)
    bias, variance, S = scale_selector_terms(f[sl], c[sl], vf[sl], vc[sl], r_f=r_f, r_c=r_c, n=spp, gamma=gamma)
    return {"bias": bias, "variance": variance, "S": S, "error_rate": float(np.mean(S > 0)),
            "z": None if gamma is None else z_of_gamma(gamma), "rho": 1.0 - 1.0 / spp,
            "gamma": gamma, "noise_var": float(noise_var), "spp": int(spp), "radius": r_f,
            "ratio": float(ratio), "n_pixels": n}


# ----------------------------------------------------------------------------
# The method
# ----------------------------------------------------------------------------

class GEMMethod(Method):
    """Greedy error minimization (Rousselle, Knaus, Zwicker 2011).

    Offline (``reconstruct``): the final-reconstruction filter selection
    (8 Gaussian scales sqrt(2) apart from sqrt(2) px, Sec. 6).  Adaptive
    (``plan``): ``initial_spp`` uniform, then ``iterations`` rounds that
    each select filters with 4 dyadic scales from 1 px and send
    ``(budget - initial) / iterations`` samples to the pixels whose
    relative MSE falls fastest (Sec. 5); ``finish`` is the final
    reconstruction.

    Parameters
    ----------
    gamma : float
        Target error rate of the scale selector, 0 < gamma < 0.4 (0.2).
    oracle : {0, 1}
        1: the paper's OUR-GRD -- selection and sampling from the true bias
        of the reference (needs one: ``adapt(..., reference=)`` or
        ``reconstruct(stats, reference=)``).
    target_rel_mse : float or None
        Stop sampling early once the estimated relative MSE (eps 0.01)
        averaged over the image is at most this.
    initial_spp, iterations : int
        Uniform initial pass (4) and adaptive iterations (8).
    samples_per_pick : int
        Samples each selected pixel distributes over its filter; 0 = the
        average spp of the budget (the paper's n).
    adaptive_scales, final_scales : int
        Gaussian scales of the adaptive phase (4 dyadic from 1 px) and of
        the final reconstruction (8, sqrt(2) apart from sqrt(2) px).
    final_outliers : {'paper', 'adaptive'}
        Outlier-removal rule of the final reconstruction (see
        :func:`gem_select`).
    subpixel_exact_below : float
        Gaussian scales with sigma below this (pixels) are computed on the
        4 x 4 subpixel grid itself (:func:`subpixel_gaussian_exact`); the
        others, and all by default (0), with the equivalent pixel kernel.

    References
    ----------
    .. [1] F. Rousselle, C. Knaus, M. Zwicker, "Adaptive Sampling and
       Reconstruction using Greedy Error Minimization", SIGGRAPH Asia 2011.
    """

    name = "gem"
    #: The paper's 4 x 4 subpixel grid.  The default filters emulate it exactly
    #: per pixel (:func:`pixel_kernel`), so the statistics keep the grid itself
    #: only when ``subpixel_exact_below > 0`` asks to filter on it (see __init__).
    grid = 4
    adaptive = True
    initial_spp = 4
    options = (
        Option("gamma", float, 0.2, "target error rate of the scale selector", min=0.0, max=GAMMA_MAX,
               min_open=True, max_open=True,
               note="the paper's z(gamma) = -log(1 - (1.9 gamma)^(1/sqrt 2)) is only calibrated there; "
                    "use e.g. 0.1 to 0.3, default 0.2"),
        Option("oracle", int, 0, "1: select and sample with the true bias from the reference (OUR-GRD)",
               choices=(0, 1)),
        Option("target_rel_mse", float, None, "stop early when the estimated relative MSE (eps 0.01) "
               "reaches this", min=0.0, min_open=True),
        Option("initial_spp", int, 4, "samples per pixel of the uniform initial pass", min=1),
        Option("iterations", int, 8, "adaptive iterations after the initial pass", min=1),
        Option("samples_per_pick", int, 0, "samples each selected pixel spreads over its filter "
               "(0: the average spp of the budget, as in the paper)", min=0),
        Option("adaptive_scales", int, 4, "dyadic Gaussian scales from 1 px used while sampling", min=1),
        Option("final_scales", int, 8, "Gaussian scales sqrt(2) apart from sqrt(2) px in the final image", min=1),
        Option("final_outliers", str, "adaptive", "final outlier removal: paper (2x size, coarser only) or "
               "adaptive (1x size, both ways)", choices=OUTLIER_RULES),
        Option("zero_variance_votes", int, 2, "stopping-map votes of pixels with zero variance: "
               "0 none, 1 adaptive phase, 2 final reconstruction, 3 both", choices=(0, 1, 2, 3)),
        Option("subpixel_exact_below", float, 0.0, "filter scales with sigma below this (px) on the 4x4 "
               "subpixel grid itself (slower; 0: pixel-level equivalent kernel)", min=0.0),
    )

    @property
    def requires(self) -> Requirements:
        # Work a run does not need is left out: 616 MB of subpixel sums at 1024^2
        # and the slowest ingestion path, unused by the pixel-level kernels.
        return Requirements(subpixels=self.grid if self.params["subpixel_exact_below"] > 0 else 0,
                            reference="required" if self.params["oracle"] else "none")

    # ---------------------------------------------------------------- core
    def start(self, width, height, channels=("R", "G", "B"), *, reference=None) -> "GEMRun":
        base = super().start(width, height, channels, reference=reference)
        if reference is not None:
            ref = np.asarray(reference, dtype=np.float64)
            if ref.ndim == 2:
                ref = ref[..., None]
            expect = (int(height), int(width), len(base.channels))
            if ref.shape != expect:
                raise InputError(_WHERE, "reference", f"shape {ref.shape}, expected {expect}")
            base.reference = ref
        return GEMRun(**dataclasses.asdict(base))

    def _select(self, run: "GEMRun", stats: PixelStats, *, final: bool, want_mse: bool = False) -> GEMSelection:
        p = self.params
        sig = final_sigmas(p["final_scales"]) if final else adaptive_sigmas(p["adaptive_scales"])
        base = stats.mean
        mv = mean_variance_policy(stats)
        count = stats.count
        s = self.grid
        eb = p["subpixel_exact_below"]
        sub = filled_subpixels(stats) if (eb > 0 and stats.subpixels and np.any(sig < eb)) else None
        if p["oracle"]:
            ref = run.reference
            if ref is None:
                raise InputError(_WHERE, "oracle", "oracle=1 needs a reference image (the run's "
                                 "reference, e.g. adapt(..., reference=...)); use oracle=0 without one")
            if ref.shape != base.shape:
                raise InputError(_WHERE, "reference", f"shape {ref.shape}, expected {base.shape}")
            sel = oracle_select(base, mv, count, sig, ref, subpixels=s, sub=sub, exact_below=eb)
        else:
            sel = gem_select(base, mv, count, sig, gamma=p["gamma"], final=final, subpixels=s,
                             want_mse=want_mse, sub=sub, exact_below=eb, outlier_rule=p["final_outliers"],
                             zero_variance_votes=bool(p["zero_variance_votes"] & (2 if final else 1)))
        # The maps are built when asked for (diagnostics()): a planning round
        # would otherwise spend ~5 % of its time on images nobody reads.
        run.diagnostics = {}
        run.pending = (sel.selected, sel.stops_raw, sel.stops, sel.mse, sel.image, stats.count.copy())
        return sel

    def diagnostics(self, run: "GEMRun"):
        """Maps of the run's last reconstruction or planning step: ``selected_scale``,
        ``sample_density``, ``stop_k`` / ``stop_raw_k`` (after / before outlier
        removal) and, when sampling, ``est_rel_mse``."""
        if run.pending is not None:
            selected, stops_raw, stops, mse, image, count = run.pending
            d = {"selected_scale": selected.astype(np.float64),
                 "sample_density": count.astype(np.float64)}
            if stops is not None:
                for k in range(stops.shape[0]):
                    d[f"stop_{k}"] = stops[k].astype(np.float64)
                    d[f"stop_raw_{k}"] = stops_raw[k].astype(np.float64)
            if mse is not None:
                rel, _ = sample_priority(mse, image, np.ones(selected.shape), 1)
                d["est_rel_mse"] = np.where(np.isfinite(rel), rel, np.nan)
            run.diagnostics = d
            run.pending = None
        return super().diagnostics(run)

    # ------------------------------------------------------------- offline
    def reconstruct_run(self, run: "GEMRun", inputs: MethodInputs) -> np.ndarray:
        """Final reconstruction (Sec. 6): (H, W, C) float64.

        Statistics without a subpixel grid work too (the default filters
        need only pixel means).  Pixels without a sample anywhere in the
        coarsest filter's support take their nearest sampled neighbour's
        value (:func:`mcrecon.methods.box.fill_empty_pixels`, with a warning).
        With ``oracle=1`` the run's reference (``inputs.reference`` or the
        one given to :meth:`start`) gives the true bias.
        """
        if run.reference is None and inputs.reference is not None:
            run.reference = self.start(run.width, run.height, run.channels, reference=inputs.reference).reference
        sel = self._select(run, inputs.stats, final=True)
        img = sel.image
        no_data = sel.bank.weight[-1] <= 0
        if no_data.any():
            from .box import fill_empty_pixels
            img = fill_empty_pixels(img, (~no_data).astype(np.int64), source=_WHERE)
        return np.asarray(img, dtype=np.float64)

    # ------------------------------------------------------------ adaptive
    def plan(self, run: "GEMRun", state: AdaptiveState):
        """Round 0: uniform ``initial_spp``; then one adaptive iteration per round (Secs. 5, 6).

        Iteration i (= round index) sends ``remaining // (iterations - i + 1)``
        samples, the last one everything left; beyond ``iterations`` rounds
        (a resumed or interrupted run) the rest goes in one round.  Returns
        None once the estimated relative MSE meets ``target_rel_mse``.
        """
        p = self.params
        remaining = state.remaining
        if remaining <= 0:
            return None
        npix = state.width * state.height
        if state.n_samples == 0:
            return state.uniform_request(p["initial_spp"])
        left = p["iterations"] - state.round_index + 1
        n_round = remaining if left <= 1 else max(1, remaining // left)
        n_pick = p["samples_per_pick"] or max(1, int(round(state.budget / npix)))
        sel = self._select(run, state.stats, final=False, want_mse=True)
        value = run.reference if p["oracle"] else sel.image
        if p["target_rel_mse"] is not None and np.isfinite(sel.mse).all():
            est = float(np.mean(sel.mse / (value * value + TARGET_EPS)))
            if est <= p["target_rel_mse"]:
                return None
        n_eff = _pick(sel.bank.n_eff, sel.selected)
        _, pri = sample_priority(sel.mse, value, n_eff, n_pick)
        pos = distribute_samples(pri, sel.selected, sel.bank.sigmas, n_round, n_pick, state.rng,
                                 subpixels=self.grid)
        return state.request(positions=pos)


@dataclasses.dataclass(eq=False)
class GEMRun(RunState):
    """Per-run state of :class:`GEMMethod`: the last selection, kept until its diagnostics are asked for."""

    pending: tuple | None = None

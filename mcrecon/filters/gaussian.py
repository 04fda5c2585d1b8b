"""The one Gaussian kernel and its pixel-level equivalent of a subpixel grid; scale ladders.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from ..errors import InputError

__all__ = ['TRUNCATE', 'adaptive_sigmas', 'final_sigmas', 'gaussian_kernel', 'pixel_kernel', 'kernel_radius', 'phase_kernels',
           'check_filter_inputs']

#: Gaussian kernels are truncated at this many standard deviations (the
#: tails hold 0.27 % of the weight) and renormalised.
TRUNCATE = 3.0


# ----------------------------------------------------------------------------
# Scales and kernels
# ----------------------------------------------------------------------------

def adaptive_sigmas(n: int = 4) -> np.ndarray:
    """Gaussian scales of the adaptive phase: ``n`` dyadic scales from 1 px (Sec. 6)."""
    return 2.0 ** np.arange(int(n), dtype=np.float64)


def final_sigmas(n: int = 8) -> np.ndarray:
    """Gaussian scales of the final reconstruction: ``n`` scales sqrt(2) apart from sqrt(2) px (Sec. 6)."""
    return math.sqrt(2.0) ** np.arange(1, int(n) + 1, dtype=np.float64)


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


def phase_kernels(sigma: float, s: int, truncate: float = TRUNCATE):
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


def check_filter_inputs(where: str, base, mean_var, count: np.ndarray, *, sub=None, reference=None) -> None:
    """Refuse mismatched shapes, NaN or Inf in the value arrays and negative counts."""
    if count.ndim != 2:
        raise InputError(where, "count", f"shape {count.shape}, expected (H, W): samples per pixel")
    h, w = count.shape
    for name, a in (("base", base), ("mean_var", mean_var)):
        if np.shape(a)[:2] != count.shape:
            raise InputError(where, name, f"shape {np.shape(a)}, expected ({h}, {w}, C): the shape of "
                             f"count {count.shape} and a channel axis")
    if reference is not None and np.shape(reference) != np.shape(base):
        raise InputError(where, "reference", f"shape {np.shape(reference)}, expected {np.shape(base)} "
                         "(the shape of base)")
    inexact = count.dtype.kind in "fc"
    if count.size and (count.min() < 0 or (inexact and not np.isfinite(count).all())):
        bad = (count < 0) | ~np.isfinite(count) if inexact else count < 0
        raise InputError(where, "count", f"{_where_bad(bad)} negative or not finite; expected samples "
                         "per pixel >= 0 (0: the pixel has no sample)")
    fix = {"base": "pass finite pixel means (PixelStats drops non-finite samples by default, "
                   "nonfinite='drop'; 'zero' keeps them as 0)",
           "mean_var": "pass finite variances (mean_variance_policy(stats) gives them for finite "
                       "statistics; an Inf comes from sample values whose square overflows)",
           "reference": "pass a finite reference image",
           "sub": "pass the filled subpixel grid of finite statistics (filled_subpixels(stats))"}
    for name, a in (("base", base), ("mean_var", mean_var), ("reference", reference), ("sub", sub)):
        if a is None:
            continue
        a = np.asarray(a)
        if a.dtype.kind not in "fc":
            continue
        ok = np.isfinite(a)
        if ok.all():
            continue
        bad = ~ok
        if bad.ndim > 2:
            bad = bad.reshape(bad.shape[0], bad.shape[1], -1).any(axis=2)
        unit = "subpixel" if name == "sub" else "pixel"
        raise InputError(where, name, f"{_where_bad(bad, unit)} NaN or Inf; each would spread over the "
                         f"support of every filter around it; {fix[name]}")


def _where_bad(bad: np.ndarray, unit: str = "pixel") -> str:
    """'N pixels (the first at row i, column j) are' for a 2-D mask with at least one True."""
    n = int(np.count_nonzero(bad))
    i, j = np.unravel_index(int(np.argmax(bad)), bad.shape)
    if n == 1:
        return f"1 {unit} (row {i}, column {j}) is"
    return f"{n} {unit}s (the first at row {i}, column {j}) are"

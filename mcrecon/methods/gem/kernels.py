"""Kernels and the filter bank of ``gem`` (Rousselle et al. 2011, Sec. 6, Eq. 2).

The Gaussian scales (:func:`adaptive_sigmas`, :func:`final_sigmas`), the
sampled kernels (:func:`gaussian_kernel`, the pixel-level equivalent of
subpixel filtering :func:`pixel_kernel`, its second moment
:func:`kernel_radius`), the hole-filled subpixel grid and its exact
filtering (:func:`filled_subpixels`, :func:`subpixel_gaussian_exact`), and
:func:`filter_bank`: every scale's filtered values, variances (squared
kernels, Eq. 2), weight sums and effective sample counts.  The
convolutions run on the shared engine :mod:`mcrecon.filters.engine`
(bit-identical to ``scipy.ndimage``, threaded).
"""

from __future__ import annotations

import dataclasses

import numba
import numpy as np
from scipy import ndimage

from ...filters.engine import correlate_jobs, mask_weights, safe_div, separable_weights
from ...errors import InputError
from ...core.stats import PixelStats
from ...filters.gaussian import TRUNCATE, check_filter_inputs, phase_kernels, kernel_radius, pixel_kernel

__all__ = ['filled_subpixels', 'subpixel_gaussian_exact', 'FilterBank', 'filter_bank', 'pending_n_eff']

# ----------------------------------------------------------------------------
# Subpixel grid
# ----------------------------------------------------------------------------

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
    ph = phase_kernels(sigma, s, truncate)
    # x: (sH, sW, C) -> (sH, W, C)
    tx = ndimage.correlate1d(sub[:, 0::s], ph[0], axis=1, mode="constant", cval=0.0)
    for b in range(1, s):
        tx += ndimage.correlate1d(sub[:, b::s], ph[b], axis=1, mode="constant", cval=0.0)
    # y: (sH, W, C) -> (H, W, C)
    t = ndimage.correlate1d(tx[0::s], ph[0], axis=0, mode="constant", cval=0.0)
    for b in range(1, s):
        t += ndimage.correlate1d(tx[b::s], ph[b], axis=0, mode="constant", cval=0.0)
    k = pixel_kernel(sigma, s, truncate=truncate)
    wsum = mask_weights(mask, k, bool(mask.all()))
    return safe_div(t, wsum[..., None])


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
        Worker threads for the convolutions (default
        :func:`mcrecon.filters.engine.n_threads`: ``$MCRECON_THREADS``, else the
        usable cores); the result is bit-identical for any value.

    Raises
    ------
    InputError
        NaN or Inf in ``base``, ``mean_var`` or the used ``sub``, a negative
        ``count``, or shapes that do not match (naming the argument and
        the number of bad pixels).
    """
    count = np.asarray(count)
    check_filter_inputs("filter_bank", base, mean_var, count, sub=sub if _uses_sub(sub, sigmas, exact_below) else None)
    return _filter_bank(base, mean_var, count, sigmas, subpixels=subpixels, per_channel=per_channel,
                        with_n_eff=with_n_eff, sub=sub, exact_below=exact_below, truncate=truncate,
                        threads=threads)


def _filter_bank(base, mean_var, count, sigmas, *, subpixels, per_channel, with_n_eff, sub, exact_below,
                 truncate, threads=None) -> FilterBank:
    # filter_bank on validated inputs (gem_select and oracle_select validate once)
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
        inv_n = safe_div(mf, count.astype(np.float64))
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
        ws = [separable_weights(h, w_, k) for k in kernels]
    else:
        ws = correlate_jobs([(mf, k, None, 0) for k in kernels], threads)
    jobs = []
    for s_, k, w in zip(sig, kernels, ws):
        k2 = (k * k).astype(np.float32)
        w2 = w * w
        if not (sub is not None and s_ < exact_below):
            jobs.append((mb, k, w, 1))
        jobs.append((mv, k2, w2, 1))
        if with_n_eff:
            jobs.append((inv_n, k2, w2, 2))
    res = iter(correlate_jobs(jobs, threads))
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


def pending_n_eff(count: np.ndarray, pending: np.ndarray, sigmas, *, subpixels: int = 4,
                  truncate: float = TRUNCATE, threads: int | None = None) -> list:
    """Effective sample counts of every scale (as :func:`filter_bank`'s ``n_eff``) with
    ``pending`` samples per pixel added to ``count``.

    The weights stay those of the pixels that hold samples now (the filter
    bank's mask); ``1 / n_q`` becomes ``1 / (n_q + pending_q)``.  Used by a
    pipelined ``gem`` plan for the round in flight.
    """
    count = np.asarray(count)
    mask = count > 0
    mf = mask.astype(np.float64)
    tot = count.astype(np.float64) + np.asarray(pending, dtype=np.float64)
    inv_n = safe_div(mf, tot).astype(np.float32)
    h, w_ = count.shape
    kernels = [pixel_kernel(s_, subpixels, truncate=truncate) for s_ in np.asarray(sigmas, dtype=np.float64)]
    if bool(mask.all()):
        ws = [separable_weights(h, w_, k) for k in kernels]
    else:
        ws = correlate_jobs([(mf, k, None, 0) for k in kernels], threads)
    jobs = [(inv_n, (k * k).astype(np.float32), w * w, 2) for k, w in zip(kernels, ws)]
    return [np.where(mask, tot, 0.0)] + list(correlate_jobs(jobs, threads))


# ----------------------------------------------------------------------------
# Input validation of the public array functions
# ----------------------------------------------------------------------------
#
# One NaN or Inf pixel would spread over the support of every filter (over a
# hundred pixels at the final scales) and decide the scales around it; the
# public array functions refuse them up front, naming the argument.

def _uses_sub(sub, sigmas, exact_below) -> bool:
    """Whether the filter bank reads the subpixel grid (a scale below ``exact_below``)."""
    return sub is not None and bool(np.any(np.asarray(sigmas, dtype=np.float64) < exact_below))


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

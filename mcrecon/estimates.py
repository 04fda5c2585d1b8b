"""Per-pixel error estimates for any reconstruction, without a reference.

Two unbiased estimators (``docs/methods/auto.md`` derives each one):

*Stein's unbiased risk estimate* (SURE) of a linear filter
    For pixel means ``y`` with ``E[y] = mu`` (per pixel and channel), the
    variance of the mean ``v_i`` (sample variance / count), independent
    between pixels, and a filter ``(F y)_i = sum_j w_ij y_j``::

        SURE_i = (F y - y)_i^2 - v_i + 2 w_ii v_i,    E[SURE_i] = E[(F y - mu)_i^2]

    because ``E[(Fy - y)_i^2] = MSE_i + v_i - 2 Cov((Fy)_i, y_i)`` and
    ``Cov((Fy)_i, y_i) = w_ii v_i``.  No Gaussian assumption is needed for a
    linear filter (Stein's lemma reduces to this covariance identity), and
    since the estimate is linear in ``v`` an unbiased ``v`` (s^2 / n) keeps it
    unbiased.  ``w_ii`` is the filter's centre weight *after* GEM's masking
    and renormalisation, computed from the same kernels
    (:func:`gaussian_centre_weights`): ``m_i k_c^2 / W_i`` with ``k_c`` the
    centre tap of the separable :func:`~mcrecon.methods.gem.pixel_kernel`
    and ``W_i`` the masked weight sum.  The pixel filter (box) has
    ``w_ii = 1``: its SURE is ``v_i``.  References: C. Stein, "Estimation of
    the mean of a multivariate normal distribution", Ann. Statist. 9(6),
    1981; T.-M. Li, Y.-T. Wu, Y.-Y. Chuang, "SURE-based optimization for
    adaptive sampling and reconstruction", ACM TOG 31(6), 2012.

*Dual-buffer cross-validation* for black boxes
    The samples of every pixel are split into two independent halves
    (:func:`split_halves`), with pixel means ``y_A``, ``y_B`` and variances of
    the means ``v_A``, ``v_B``.  A black box reconstructs ``A`` from half A and
    ``B`` from half B; the output is ``(A + B) / 2``.  Since ``A`` and ``y_B``
    are independent and ``E[y_B] = mu``::

        E[(A - y_B)^2] = MSE(A) + Var(y_B)   =>   CV_A = (A - y_B)^2 - v_B

    is unbiased for ``MSE(A)`` -- bias included.  The algebraic identity
    ``((A+B)/2 - mu)^2 = ((A-mu)^2 + (B-mu)^2) / 2 - (A-B)^2 / 4`` then gives
    an unbiased estimate of the output's MSE::

        MSE_hat((A+B)/2) = (CV_A + CV_B) / 2 - (A - B)^2 / 4.

    The *variance part* alone: when ``E[A] = E[B]`` (same method, halves of
    equal size), ``E[(A - B)^2] = Var A + Var B``, so ``(A - B)^2 / 4`` is
    unbiased for ``Var((A + B) / 2)``; and if the variance of the method
    falls as 1/n, also for the variance of the full-sample result ``F``.
    It cannot see the bias ``E[F] - mu`` (the squared bias is what
    ``CV`` adds).  References: F. Rousselle, C. Knaus, M. Zwicker, "Adaptive
    rendering with non-local means filtering", ACM TOG 31(6), 2012;
    B. Bitterli et al., "Nonlinearly weighted first-order regression for
    denoising Monte Carlo renderings", CGF 35(4), 2016.

Relative versions divide by a reference-free denominator
(:func:`relative_denominator`): the 3 x 3 median of ``max(y^2 - v, 0)``
plus eps.  Not ``y_i^2 + eps``: ``E[y_i^2] = mu_i^2 + v_i``, so a noisy
square under-weights exactly the noisiest pixels; and not a smoothed y^2,
which borrows the brightness of an edge's other side.
"""

from __future__ import annotations

import dataclasses
import warnings

import numba
import numpy as np
from scipy import ndimage

from ._filtering import safe_div
from .errors import InputError
from .stats import PixelStats

__all__ = ["sure", "gaussian_centre_weights", "SureBank", "sure_filter_bank", "relative_denominator",
           "relative", "split_labels", "split_halves", "Halves", "cross_validation_mse", "dual_buffer_variance",
           "dual_buffer_mse", "DEFAULT_EPS"]

#: eps of the relative estimates: that of :func:`mcrecon.metrics.relative_mse`.
DEFAULT_EPS = 1e-2


# ----------------------------------------------------------------------------
# SURE for linear filters
# ----------------------------------------------------------------------------

def sure(y: np.ndarray, v: np.ndarray, filtered: np.ndarray, centre_weight) -> np.ndarray:
    """Stein's unbiased risk estimate of a linear filter, per pixel and channel.

    ``SURE = (filtered - y)^2 - v + 2 w_ii v``.

    Parameters
    ----------
    y : ndarray (H, W, C)
        The pixel means the filter was applied to.
    v : ndarray (H, W, C)
        Variance of each pixel mean.
    filtered : ndarray (H, W, C)
        ``F y``.
    centre_weight : ndarray (H, W) or (H, W, C), or a number
        ``w_ii``, the weight of pixel i itself in ``(F y)_i``.
    """
    w = np.asarray(centre_weight, dtype=np.float64)
    if w.ndim == 2:
        w = w[..., None]
    d = filtered - y
    return d * d + (2.0 * w - 1.0) * v


def gaussian_centre_weights(count: np.ndarray, sigmas, *, subpixels: int = 4, weights=None) -> list:
    """Exact centre weights ``w_ii`` of GEM's masked, renormalised Gaussian scales.

    Scale k filters with the separable :func:`~mcrecon.methods.gem.pixel_kernel`
    ``K = k k^T`` over the pixels with samples (mask m) and divides by
    ``W_i = sum_j m_j K(i - j)`` (:func:`~mcrecon.methods.gem.filter_bank`),
    so the weight of pixel i on itself is ``m_i k_c^2 / W_i`` (``k_c``: the
    1-D kernel's centre tap); 0 where ``W_i = 0``.

    Parameters
    ----------
    count : ndarray (H, W)
    sigmas : sequence of float
    weights : list of ndarray (H, W), optional
        ``W`` per scale (``FilterBank.weight[1:]``), to avoid recomputing it.

    Returns
    -------
    list of ndarray (H, W), one per sigma
    """
    from ._filtering import correlate_jobs, separable_weights
    from .methods.gem import pixel_kernel

    count = np.asarray(count)
    mask = count > 0
    mf = mask.astype(np.float64)
    h, w = count.shape
    out = []
    kernels = [pixel_kernel(s, subpixels) for s in np.asarray(sigmas, dtype=np.float64)]
    if weights is None:
        if mask.all():
            weights = [separable_weights(h, w, k) for k in kernels]
        else:
            weights = correlate_jobs([(mf, k, None, 0) for k in kernels])
    for k, wsum in zip(kernels, weights):
        kc = k[(k.size - 1) // 2]
        out.append(safe_div(mf * (kc * kc), np.asarray(wsum, dtype=np.float64)))
    return out


@dataclasses.dataclass(eq=False)
class SureBank:
    """Candidates of the Gaussian filter bank and their SURE maps.

    Attributes
    ----------
    sigmas : ndarray (K,)
        Gaussian scales (pixels); index 0 of the lists is the pixel filter.
    values : list of ndarray (H, W, C)
    sure : list of ndarray (H, W, C)
        Unbiased per-pixel MSE estimate of each candidate (may be negative).
    centre_weight : list of ndarray (H, W)
    weight : list of ndarray (H, W)
        Masked weight sums (0: no data in the support).
    """

    sigmas: np.ndarray
    values: list
    sure: list
    centre_weight: list
    weight: list


def sure_filter_bank(y: np.ndarray, v: np.ndarray, count: np.ndarray, sigmas, *, subpixels: int = 4) -> SureBank:
    """Every scale of GEM's filter bank (:func:`~mcrecon.methods.gem.filter_bank`) with its SURE map.

    Index 0 is the pixel filter (SURE = v); index k the Gaussian of
    ``sigmas[k-1]`` with GEM's pixel kernel, masking and normalisation.
    Scales whose support holds no sample get +inf; a pixel without
    samples otherwise NaN (its own y is no measurement: undefined).
    """
    from .methods.gem import filter_bank

    count = np.asarray(count)
    bank = filter_bank(y, v, count, sigmas, subpixels=subpixels, per_channel=False)
    cw = [np.where(count > 0, 1.0, 0.0)] + gaussian_centre_weights(count, bank.sigmas, subpixels=subpixels,
                                                                   weights=bank.weight[1:])
    empty = (count == 0)[..., None]
    sures = []
    for k in range(bank.n_scales):
        s = sure(y, v, bank.values[k], cw[k])
        # no sample in the support: no estimate at all (+inf); an empty pixel's
        # own y is not a measurement, so its SURE is undefined (NaN: callers
        # fill it from neighbours, as auto's smoothing does)
        s = np.where((bank.weight[k] <= 0)[..., None], np.inf, np.where(empty, np.nan, s))
        sures.append(s)
    return SureBank(bank.sigmas, list(bank.values), sures, cw, list(bank.weight))


# ----------------------------------------------------------------------------
# Relative versions
# ----------------------------------------------------------------------------

def relative_denominator(y: np.ndarray, v: np.ndarray, count: np.ndarray | None = None, *,
                         eps: float = DEFAULT_EPS) -> np.ndarray:
    """A reference-free ``mu^2 + eps`` per pixel and channel.

    ``q_i = max(y_i^2 - v_i, 0)`` is unbiased for ``mu_i^2`` before the
    clamp (``E[y^2] = mu^2 + v``); the denominator is the median of q over
    the 3 x 3 neighbourhood (pixels with samples), plus eps.  The median
    keeps edges (a pixel beside an edge has at most 3 or 5 of its 9
    neighbours on the other side: a box would give a dark pixel beside a
    light of 500 about 500^2 / 9 -- measured: 10^6 x its true mu^2 on the
    ``hdr`` scene, which made light leaking into it look free) and ignores
    isolated fireflies; on skewed low-light noise it errs low, i.e. towards
    larger relative errors and less filtering.
    """
    if not eps > 0:
        raise InputError("relative_denominator", "eps", f"got {eps}, expected > 0")
    q = np.maximum(y * y - v, 0.0)
    if count is not None:
        has = np.asarray(count) > 0
        if not has.all():
            # empty pixels take no part: give them NaN and use the nan-aware median
            q = np.where(has[..., None], q, np.nan)
            pad = np.pad(q, ((1, 1), (1, 1), (0, 0)), mode="constant", constant_values=np.nan)
            h, w = has.shape
            stack = np.stack([pad[i:i + h, j:j + w] for i in range(3) for j in range(3)])
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                med = np.nanmedian(stack, axis=0)
            med = np.where(np.isfinite(med), med, 0.0)
            return np.maximum(med, np.where(np.isfinite(q), q, 0.0)) + eps
    return np.maximum(ndimage.median_filter(q, size=(3, 3, 1), mode="nearest"), q) + eps


def relative(mse: np.ndarray, denominator: np.ndarray) -> np.ndarray:
    """Relative MSE per pixel: mean over channels of ``mse / denominator`` (H, W)."""
    return np.mean(mse / denominator, axis=2)


# ----------------------------------------------------------------------------
# Dual buffers
# ----------------------------------------------------------------------------

@numba.njit(cache=True, nogil=True)
def _labels_kernel(pix, counter, out):
    # the k-th sample of pixel p goes to half (k + salt(p)) & 1; salt from a
    # multiplicative hash of p, so which half gets a pixel's odd sample varies
    for i in range(pix.size):
        p = pix[i]
        k = counter[p]
        counter[p] = k + 1
        salt = ((p * 2654435761) >> 16) & 1
        out[i] = (k + salt) & 1


def split_labels(positions: np.ndarray, width: int, height: int, counter: np.ndarray) -> np.ndarray:
    """Half (0 or 1) of each sample: alternating within each pixel, by (pixel, index within pixel).

    ``counter`` (H*W int64, updated in place) holds how many samples each
    pixel has had so far, so a stream split chunk by chunk or round by
    round gets the same labels as the whole stream.  Every pixel's halves
    differ by at most one sample.  Positions outside the film are counted
    in the nearest border pixel (they are dropped later by the statistics).
    """
    pos = np.asarray(positions)
    if pos.shape[0] == 0:
        return np.zeros(0, np.int8)
    ix = np.clip(np.floor(np.nan_to_num(pos[:, 0], nan=0.0)), 0, width - 1).astype(np.int64)
    iy = np.clip(np.floor(np.nan_to_num(pos[:, 1], nan=0.0)), 0, height - 1).astype(np.int64)
    out = np.empty(pos.shape[0], np.int8)
    _labels_kernel(iy * width + ix, counter, out)
    return out


@dataclasses.dataclass(eq=False)
class Halves:
    """Statistics of the two halves of every pixel's samples (:func:`split_halves`)."""

    a: PixelStats
    b: PixelStats
    counter: np.ndarray

    def add(self, positions, values, *, nonfinite: str = "drop", source: str = "samples") -> None:
        """Split a batch (in stream order) and add each half to its statistics."""
        pos = np.asarray(positions)
        val = np.asarray(values)
        if val.ndim == 1:
            val = val[:, None]
        lab = split_labels(pos, self.a.width, self.a.height, self.counter)
        for half, st in ((0, self.a), (1, self.b)):
            sel = lab == half
            if sel.any():
                st.add(pos[sel], val[sel], nonfinite=nonfinite, source=source)

    @classmethod
    def empty(cls, width: int, height: int, channels) -> "Halves":
        return cls(PixelStats(width, height, channels), PixelStats(width, height, channels),
                   np.zeros(int(width) * int(height), np.int64))


def split_halves(source, *, nonfinite: str = "drop") -> Halves:
    """Two independent halves of a sample source (log or SampleSet), rounds in order."""
    h = Halves.empty(source.width, source.height, tuple(source.channels))
    for ch in source.iter_chunks(with_round=False):
        h.add(ch.positions, ch.values, nonfinite=nonfinite, source="samples")
    return h


def cross_validation_mse(a: np.ndarray, y_other: np.ndarray, v_other: np.ndarray) -> np.ndarray:
    """``(a - y_other)^2 - v_other``: unbiased for MSE(a) when a is independent of the other half."""
    d = a - y_other
    return d * d - v_other


def dual_buffer_variance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(a - b)^2 / 4``: the variance part of the MSE of ``(a + b) / 2`` (bias unseen)."""
    d = a - b
    return 0.25 * d * d


def dual_buffer_mse(a, b, est_a, est_b) -> np.ndarray:
    """Unbiased MSE of ``(a + b) / 2`` from unbiased MSE estimates of a and b (exact identity).

    ``((a+b)/2 - mu)^2 = ((a - mu)^2 + (b - mu)^2) / 2 - (a - b)^2 / 4``.
    """
    return 0.5 * (est_a + est_b) - dual_buffer_variance(a, b)

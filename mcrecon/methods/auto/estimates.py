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

from ...filters.engine import parallel_rows, safe_div
from ...filters.order import median9, neighbour_medians8
from ...errors import InputError
from ...core.metrics import DEFAULT_EPS

__all__ = ['sure', 'gaussian_centre_weights', 'SureBank', 'sure_filter_bank', 'relative_denominator',
           'relative_denominator_loo', 'relative', 'cross_validation_mse', 'dual_buffer_variance',
           'dual_buffer_mse']

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
    from ...filters.engine import correlate_jobs, separable_weights
    from ...filters.gaussian import pixel_kernel

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
    from ...filters.engine import correlate_jobs, separable_weights
    from ...filters.gaussian import pixel_kernel
    from ...filters.gaussian import check_filter_inputs

    # GEM's filter bank (mcrecon.methods.gem.filter_bank) restricted to what SURE
    # needs -- the filtered values and the weight sums, by the same jobs on the
    # same engine, so bit-identical to its values and weights (tested) -- and
    # the SURE maps of all scales in one compiled pass
    count = np.asarray(count)
    y = np.asarray(y, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    check_filter_inputs("sure_filter_bank", y, v, count)
    sig = np.asarray(sigmas, dtype=np.float64)
    mask = count > 0
    full = bool(mask.all())
    mf = mask.astype(np.float64)
    mb = y if full else y * mf[..., None]
    h, w = count.shape
    kernels = [pixel_kernel(s_, subpixels) for s_ in sig]
    if full:
        ws = [separable_weights(h, w, k) for k in kernels]
    else:
        ws = correlate_jobs([(mf, k, None, 0) for k in kernels])
    values = [y] + correlate_jobs([(mb, k, wk, 1) for k, wk in zip(kernels, ws)])
    weight = [mf] + list(ws)
    cw = [np.where(count > 0, 1.0, 0.0)] + gaussian_centre_weights(count, sig, subpixels=subpixels, weights=ws)
    yc = np.ascontiguousarray(y)
    vc = np.ascontiguousarray(v)
    sures = []
    for k in range(len(values)):
        # no sample in the support: no estimate at all (+inf); an empty pixel's
        # own y is not a measurement, so its SURE is undefined (NaN: callers
        # fill it from neighbours, as auto's smoothing does)
        out = np.empty(y.shape)
        _sure_masked(yc, vc, np.ascontiguousarray(values[k], dtype=np.float64),
                     np.ascontiguousarray(cw[k], dtype=np.float64), np.ascontiguousarray(weight[k], dtype=np.float64),
                     mask, out)
        sures.append(out)
    return SureBank(sig, values, sures, cw, weight)


@numba.njit(cache=True, nogil=True)
def _sure_masked(y, v, fy, cw, weight, has, out):
    # sure(y, v, fy, cw), +inf where weight <= 0, else NaN where the pixel is empty
    # (the arithmetic of :func:`sure`: d * d + (2 w - 1) v)
    h, w, c = y.shape
    for i in range(h):
        for j in range(w):
            t = 2.0 * cw[i, j] - 1.0
            for ch in range(c):
                if weight[i, j] <= 0:
                    out[i, j, ch] = np.inf
                elif not has[i, j]:
                    out[i, j, ch] = np.nan
                else:
                    d = fy[i, j, ch] - y[i, j, ch]
                    out[i, j, ch] = d * d + t * v[i, j, ch]


# ----------------------------------------------------------------------------
# Relative versions
# ----------------------------------------------------------------------------

def _excess_square(y: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``np.maximum(y * y - v, 0.0)`` in one compiled pass (no full-image temporaries)."""
    y = np.ascontiguousarray(y, dtype=np.float64)
    q = np.empty(y.shape)
    parallel_rows(_excess_square_rows, (y.reshape(y.shape[0], -1), np.ascontiguousarray(v, dtype=np.float64)
                                        .reshape(y.shape[0], -1), q.reshape(y.shape[0], -1)), y.shape[0])
    return q


@numba.njit(cache=True, nogil=True)
def _excess_square_rows(y, v, q, i0, i1):
    # np.maximum: NaN stays NaN, and a tie with 0 gives the second operand
    for i in range(i0, i1):
        for k in range(y.shape[1]):
            x = y[i, k] * y[i, k] - v[i, k]
            q[i, k] = x if (x > 0.0 or x != x) else 0.0


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
    q = _excess_square(y, v)
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
    out = np.empty(q.shape)
    parallel_rows(_median3_max_plus, (np.ascontiguousarray(q), float(eps), out), q.shape[0])
    return out


@numba.njit(cache=True, nogil=True)
def _median3_max_plus(q, eps, out, r0, r1):
    # rows [r0, r1): max(3 x 3 median of q (edge pixels repeated, as ndimage's mode "nearest"), q) + eps
    # per channel; q finite (the median of 9 numbers is exact: bit-identical to
    # np.maximum(ndimage.median_filter(q, size=(3, 3, 1), mode="nearest"), q) + eps).  The pixels
    # between the first and last column in one loop over equal-length slices of the three rows
    # (vectorised), the network's arguments in the same order as at the edges.
    h, w, c = q.shape
    n = w * c
    m = max(n - 2 * c, 0)
    for i in range(r0, r1):
        ra, rb, rd = q[max(i - 1, 0)].reshape(n), q[i].reshape(n), q[min(i + 1, h - 1)].reshape(n)
        a0, a1, a2 = ra[:m], ra[c:c + m], ra[2 * c:2 * c + m]
        b0, b1, b2 = rb[:m], rb[c:c + m], rb[2 * c:2 * c + m]
        d0, d1, d2 = rd[:m], rd[c:c + m], rd[2 * c:2 * c + m]
        o1 = out[i].reshape(n)[c:c + m]
        for k in range(m):
            md = median9(a0[k], a1[k], a2[k], b0[k], b1[k], b2[k], d0[k], d1[k], d2[k])
            qq = b1[k]
            o1[k] = (md if md >= qq else qq) + eps
        for j in (0, w - 1):
            i0 = max(i - 1, 0)
            i2 = min(i + 1, h - 1)
            j0 = max(j - 1, 0)
            j2 = min(j + 1, w - 1)
            for ch in range(c):
                md = median9(q[i0, j0, ch], q[i0, j, ch], q[i0, j2, ch], q[i, j0, ch], q[i, j, ch], q[i, j2, ch],
                             q[i2, j0, ch], q[i2, j, ch], q[i2, j2, ch])
                qq = q[i, j, ch]
                out[i, j, ch] = (md if md >= qq else qq) + eps


def relative_denominator_loo(y: np.ndarray, v: np.ndarray, count: np.ndarray | None = None, *,
                             eps: float = DEFAULT_EPS) -> np.ndarray:
    """A reference-free ``mu^2 + eps`` that does not depend on the pixel's own samples.

    The median of ``q = max(y^2 - v, 0)`` over the 8 neighbours (edge
    pixels repeated; pixels without samples left out; 0 if none), plus
    eps.  :func:`relative_denominator` includes the pixel itself (and its
    own q as a floor), so it is larger exactly where the pixel's noise is:
    a relative SURE divided by it is biased low, by more for the scales that
    average the noise away (measured on a flat field at 8 spp: the summed
    relative SURE of every Gaussian scale came out -0.008 +- 0.0004 of
    box-relative error while the true values fell from 0.006 to 5e-5).  A
    denominator independent of pixel i keeps ``E[SURE_i / den_i] =
    E[SURE_i] / den_i`` (up to the small correlation of SURE_i with its
    neighbours' samples through the filter's weights on them).
    """
    if not eps > 0:
        raise InputError("relative_denominator_loo", "eps", f"got {eps}, expected > 0")
    q = _excess_square(y, v)
    has = np.ones(q.shape[:2], bool) if count is None else np.asarray(count) > 0
    out = np.empty(q.shape)
    parallel_rows(_median8_plus, (np.ascontiguousarray(q, dtype=np.float64), np.ascontiguousarray(has), float(eps),
                                  out), q.shape[0])
    return out


@numba.njit(cache=True, nogil=True, inline="always")
def sorted_neighbours8(q, has, i, j, ch, buf):
    """The 8 neighbours of pixel (i, j) in channel ch, edge-repeated, where ``has``: sorted into ``buf``.

    Insertion sort (stable; a NaN stops no comparison, so it stays where it
    arrived).  Returns how many were taken (0..8).
    """
    h, w, _ = q.shape
    n = 0
    for di in range(-1, 2):
        ii = min(max(i + di, 0), h - 1)
        for dj in range(-1, 2):
            if di == 0 and dj == 0:
                continue
            jj = min(max(j + dj, 0), w - 1)
            if not has[ii, jj]:
                continue
            x = q[ii, jj, ch]
            k = n
            while k > 0 and buf[k - 1] > x:
                buf[k] = buf[k - 1]
                k -= 1
            buf[k] = x
            n += 1
    return n


@numba.njit(cache=True, nogil=True)
def _median8_plus(q, has, eps, out, i0, i1):
    # rows [i0, i1) of relative_denominator_loo.  Where the 3 x 3 neighbourhood has samples and no NaN
    # (nearly every pixel) the median of the middle pair from the network, the same two elements the
    # sort gives, for whole rows at once (neighbour_medians8); the rest take the sort.
    h, w, c = q.shape
    buf = np.empty(8)
    col = np.empty(w, np.bool_)  # column j of the three rows has samples
    med = np.empty(max(w * c - 2 * c, 0))
    for i in range(i0, i1):
        ia = max(i - 1, 0)
        ib = min(i + 1, h - 1)
        nan = neighbour_medians8(q, i, med)
        o1 = out[i].reshape(w * c)[c:c + med.size]
        for k in range(med.size):
            o1[k] = med[k] + eps
        every = True
        for j in range(w):
            col[j] = has[ia, j] and has[i, j] and has[ib, j]
            every = every and col[j]
        for j in range(w):
            if every and nan == 0 and 0 < j < w - 1:
                continue
            full = 0 < j < w - 1 and col[j - 1] and col[j] and col[j + 1]
            for ch in range(c):
                if full and med[(j - 1) * c + ch] == med[(j - 1) * c + ch]:
                    continue  # (a NaN among them: the network does not order it as the sort does)
                nb = sorted_neighbours8(q, has, i, j, ch, buf)
                if nb == 0:
                    md = 0.0
                elif nb % 2 == 1:
                    md = buf[nb // 2]
                else:
                    md = 0.5 * (buf[nb // 2 - 1] + buf[nb // 2])
                out[i, j, ch] = md + eps


def relative(mse: np.ndarray, denominator: np.ndarray) -> np.ndarray:
    """Relative MSE per pixel: mean over channels of ``mse / denominator`` (H, W)."""
    return np.mean(mse / denominator, axis=2)


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

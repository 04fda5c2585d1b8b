"""Feature-guided cross-bilateral filter after Rousselle, Manzi, Zwicker 2013 (RDFC).

"Robust denoising using feature and color information" (CGF 32(7))
weights the pixels q of a (2r+1)^2 window around p by

    w(p, q) = min(w_c, w_f) = exp(-max(0, d_c(p, q), d_f(p, q)))

with the colour distance (variance-cancelled and normalised, per pixel:
the patch of NL-means reduced to one pixel)

    d_c = mean_i ((u_i(p) - u_i(q))^2 - (V_i(p) + min(V_i(p), V_i(q)))) / (eps + k_c^2 (V_i(p) + V_i(q)))

and the feature distance, the largest over the feature channels j,

    d_f = max_j ((f_j(p) - f_j(q))^2 - (S_j(p) + min(S_j(p), S_j(q)))) / (k_f^2 max(tau, S_j(p), |grad f_j(p)|^2))

(``S_j`` the variance of feature j's mean, ``grad`` central differences):
a feature difference counts in units of the feature's own noise, or of its
local gradient where it varies.  Unlike RDFC this filter does not prefilter
the features, nor select among candidate bandwidths: it is the
cross-bilateral baseline feature-guided regression (NFOR) is measured
against, and an array-level candidate (:func:`cross_bilateral`).
"""

from __future__ import annotations

import numba
import numpy as np

from .engine import parallel_rows
from .nlmeans import exp_neg

__all__ = ["cross_bilateral", "feature_gradient2"]

#: eps of the colour distance's denominator (0 / 0 on noise-free pixels).
_EPS = 1e-10


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _row(img, var, feat, fvar, fden, r, kc2, kf2, use_colour, i, num, den):
    """Row i of the filter, offset by offset: for each window row qi and column offset dx the distances of
    every pixel of the row at once (loops along the row on 0-based slices: LLVM vectorises them), then its
    weight and contribution.  Each pixel sums its window's pixels in the window's row-major order and each
    distance term in the order of the formula; the weight is :func:`~.nlmeans.exp_neg` (vectorisable,
    within 1e-9 relative of ``exp(-d)``; a NaN distance weighs 0): 4x the pixel-by-pixel loop's speed."""
    c, h, w = img.shape
    nf = feat.shape[0]
    inv_c = 1.0 / c
    dist = np.empty(w)
    for qi in range(max(0, i - r), min(h, i + r + 1)):
        for dx in range(-r, r + 1):
            j0 = max(0, -dx)
            j1 = min(w, w - dx)
            n = j1 - j0
            if n <= 0:
                continue
            d = dist[:n]
            for t in range(n):
                d[t] = 0.0
            if use_colour:
                for ch in range(c):
                    up, uq = img[ch, i, j0:j1], img[ch, qi, j0 + dx:j1 + dx]
                    vp_, vq_ = var[ch, i, j0:j1], var[ch, qi, j0 + dx:j1 + dx]
                    for t in range(n):
                        vp = vp_[t]
                        vq = vq_[t]
                        diff = up[t] - uq[t]
                        d[t] += (diff * diff - (vp + min(vp, vq))) / (_EPS + kc2 * (vp + vq))
                for t in range(n):
                    d[t] = max(0.0, d[t] * inv_c)
            for m in range(nf):
                fp, fq = feat[m, i, j0:j1], feat[m, qi, j0 + dx:j1 + dx]
                sp_, sq_, fd = fvar[m, i, j0:j1], fvar[m, qi, j0 + dx:j1 + dx], fden[m, i, j0:j1]
                for t in range(n):
                    sp = sp_[t]
                    sq = sq_[t]
                    diff = fp[t] - fq[t]
                    d[t] = max(d[t], (diff * diff - (sp + min(sp, sq))) / (kf2 * fd[t]))
            dn = den[i, j0:j1]
            for t in range(n):
                wt = exp_neg(d[t])
                d[t] = wt
                dn[t] += wt
            for ch in range(c):
                nu, src = num[ch, i, j0:j1], img[ch, qi, j0 + dx:j1 + dx]
                for t in range(n):
                    nu[t] += d[t] * src[t]


@numba.njit(cache=True, nogil=True)
def _rows(img, var, feat, fvar, fden, r, kc2, kf2, use_colour, num, den, i0, i1):
    """Rows ``[i0, i1)``: each row writes only its own outputs, so blocks of rows run on separate threads."""
    for i in range(i0, i1):
        _row(img, var, feat, fvar, fden, r, kc2, kf2, use_colour, i, num, den)


def feature_gradient2(features) -> np.ndarray:
    """|grad f|^2 of each feature channel (H, W, D), central differences (one-sided at the border)."""
    f = np.asarray(features, dtype=np.float64)
    if f.shape[0] < 2 or f.shape[1] < 2:
        return np.zeros_like(f)
    gy, gx = np.gradient(f, axis=(0, 1))
    return gx * gx + gy * gy


def cross_bilateral(image, variance, features, feature_variance, *, radius: int = 10, k_colour: float | None = 0.45,
                    k_feature: float = 0.6, tau: float = 1e-3, threads: int | None = None,
                    return_weights: bool = False):
    """RDFC-style cross-bilateral filter of a noisy image guided by its features.

    Parameters
    ----------
    image : ndarray (H, W, C)
        Pixel means (HDR: never clipped).
    variance : ndarray (H, W, C)
        Variance of the pixel means.
    features : ndarray (H, W, D)
        Feature channels (albedo, normal, depth components), their pixel means.
    feature_variance : ndarray (H, W, D)
        Variance of the features' pixel means.
    radius : int
        Window (2 radius + 1)^2 (RDFC: 10).
    k_colour : float or None
        Bandwidth of the colour term (None: features only).
    k_feature : float
        Bandwidth of the feature term (RDFC's candidates: 0.6 and 1.0 among others).
    tau : float
        Floor of the feature distance's normaliser (RDFC: 1e-3).
    threads : int, optional
        Worker threads (the result does not depend on them).
    return_weights : bool
        Also return each pixel's weight sum (H, W); its own weight is 1, so
        ``1 / sum`` is the filter's centre weight ``w_ii`` (with
        ``k_colour=None`` the filter is linear in the image: SURE applies).

    Returns
    -------
    ndarray (H, W, C) float64 (and (H, W) weight sums with ``return_weights``)
    """
    valid = {"radius": radius >= 0, "k_feature": k_feature > 0, "tau": tau > 0,
             "k_colour": k_colour is None or k_colour > 0}
    bad = [n for n, ok in valid.items() if not ok]
    if bad:
        raise ValueError(f"cross_bilateral: {bad[0]} out of range (radius >= 0; k_feature, tau, k_colour > 0 "
                         "or k_colour None)")
    img = np.asarray(image, dtype=np.float64)
    feat = np.asarray(features, dtype=np.float64)
    if feat.ndim == 2:
        feat = feat[..., None]
    fvar = np.asarray(feature_variance, dtype=np.float64).reshape(feat.shape)
    var = np.asarray(variance, dtype=np.float64)
    if var.shape != img.shape or feat.shape[:2] != img.shape[:2]:
        raise ValueError(f"cross_bilateral: image {img.shape}, variance {var.shape}, features {feat.shape} differ")
    fden = np.maximum(np.maximum(fvar, feature_gradient2(feat)), float(tau))
    planes = [np.ascontiguousarray(np.moveaxis(a, 2, 0)) for a in (img, var, feat, fvar, fden)]
    c, h, w = planes[0].shape
    num = np.zeros((c, h, w))
    den = np.zeros((h, w))
    kc = 1.0 if k_colour is None else float(k_colour)
    parallel_rows(_rows, (*planes, int(radius), kc * kc, float(k_feature) ** 2, k_colour is not None, num, den),
                  h, threads)
    out = np.moveaxis(num / den, 0, 2)
    return (out, den) if return_weights else out

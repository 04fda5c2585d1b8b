"""The NFOR pipeline on arrays (Bitterli et al. 2016, Sec. 5), stage by stage.

1. **Feature prefiltering** (Sec. 5.1): each feature channel of half A is
   NL-means filtered with weights from the same channel of half B and vice
   versa (patch 3, window 5, k = 0.5, variance x 2: the halves').
2. **Regression** (Sec. 5.2): for each bandwidth k (0.5, 1.0), half A's
   colour is regressed on half B's prefiltered features with NL-means
   weights from half B's colour (and B on A's): the cross-buffer weights
   and features carry none of the noise of the colour they filter
   (:func:`.regression.collaborative_regression`, window 9, patch 3).
3. **MSE estimate and selection** (Sec. 5.3): with the halves independent,
   ``E[(y_B - F_A)^2] = MSE(F_A) + Var(y_B)``, so the MSE of the average of
   the two filtered halves is estimated per channel by
   ``((y_B - F_A)^2 - 2V + (y_A - F_B)^2 - 2V) / 2 - (F_A - F_B)^2 / 4``
   (V: the variance of the full buffer's mean, 2V a half's), NL-means
   filtered (patch 1, window 9, k = 1, guided by the full buffer); the
   binary map "k = 1.0 has the lower estimate" is filtered the same way and
   blends the two candidates of each half.
4. **Second pass** (Sec. 5.4): the halves' results are averaged, their
   squared half difference / 4 the variance of that average; the features
   averaged likewise and NL-means filtered once more (patch 3, window 2,
   k = 0.5); one last collaborative regression (k = 1) of the average,
   guided by itself, gives the image.

The parameters are those of the reference implementation (Tungsten's
``src/denoiser/denoiser.cpp``); the paper text could not be consulted here
(docs/methods/nfor.md).
"""

from __future__ import annotations

import numpy as np

from ...filters.nlmeans import nlmeans_filter, nlmeans_filter_shared
from ...filters.regression import (MIN_COVER_WEIGHT, RIDGE, collaborative_regression, collaborative_regressions,
                                   feature_scale)

__all__ = ["nfor_denoise", "denoise_planes", "prefilter_features", "cross_regression", "estimate_mse",
           "film_feature_scales", "PAPER"]

#: The reference implementation's parameters.
PAPER = dict(feature_radius=5, feature_patch=3, feature_k=0.5, radius=9, patch=3, bandwidths=(0.5, 1.0),
             mse_radius=9, mse_patch=1, mse_k=1.0, final_feature_radius=2, final_feature_patch=3,
             final_feature_k=0.5, final_k=1.0, second_pass=True)


def estimate_mse(y_a, y_b, f_a, f_b, variance) -> np.ndarray:
    """Dual-buffer estimate of the MSE of ``(f_a + f_b) / 2`` (unfiltered; may be negative).

    ``f_a`` filters half A with weights and features from half B only
    (and vice versa), so y_B is independent of f_A: ``E[(y_B - f_A)^2] =
    MSE(f_A) + 2 variance`` (``variance``: of the full buffer's mean).
    The MSE of the average is the average MSE minus the spread of the two
    around it, ``(f_A - f_B)^2 / 4``.
    """
    mse_a = (y_b - f_a) ** 2 - 2.0 * variance
    mse_b = (y_a - f_b) ** 2 - 2.0 * variance
    return 0.5 * (mse_a + mse_b) - 0.25 * (f_b - f_a) ** 2


def prefilter_features(feat_a, feat_b, feat_variance, *, radius=5, patch=3, k=0.5, threads=None):
    """Sec. 5.1: each half's features NL-means filtered with the *other* half's weights (per channel).

    ``feat_variance`` is the variance of the full buffer's feature mean
    (doubled here for a half).  Returns ``(pf_a, pf_b)``, (H, W, D) each.
    """
    if not np.shape(feat_a)[2]:
        return feat_a, feat_b
    pf_a = nlmeans_filter(feat_a, feat_b, feat_variance, radius=radius, patch=patch, k=k, variance_scale=2.0,
                          threads=threads)
    pf_b = nlmeans_filter(feat_b, feat_a, feat_variance, radius=radius, patch=patch, k=k, variance_scale=2.0,
                          threads=threads)
    return pf_a, pf_b


def cross_regression(y_a, y_b, variance, pf_a, pf_b, *, radius=9, patch=3, k=1.0, ridge=RIDGE, threads=None,
                     stride=1, min_weight=MIN_COVER_WEIGHT, scales_a=None, scales_b=None):
    """Sec. 5.2 for one bandwidth: half A regressed on half B's features with weights from B's colour, and
    B on A's.  ``F_A`` is then a linear function of ``y_A`` whose weights and design carry none of ``y_A``'s
    noise (nor of A's features), which the MSE estimate (:func:`estimate_mse`) relies on.
    Returns ``(F_A, F_B)``; with ``k`` a sequence of bandwidths, ``([F_A per k], [F_B per k])``, each
    half's bandwidths in one pass (:func:`.regression.collaborative_regressions`, bit-identical to one
    call per bandwidth).  ``stride``, ``min_weight``: windows fitted on a grid only
    (:func:`.regression.collaborative_regression`); ``scales_a``, ``scales_b``: the standardisation of
    ``pf_a``'s and ``pf_b``'s planes when not their own (a tile's: the film's, :func:`film_feature_scales`)."""
    ks = tuple(k) if np.ndim(k) else (k,)
    c_a = collaborative_regressions(y_a, y_b, variance, pf_b, ks=ks, radius=radius, patch=patch,
                                    variance_scale=2.0, ridge=ridge, threads=threads, stride=stride,
                                    min_weight=min_weight, feature_scales=scales_b)
    c_b = collaborative_regressions(y_b, y_a, variance, pf_a, ks=ks, radius=radius, patch=patch,
                                    variance_scale=2.0, ridge=ridge, threads=threads, stride=stride,
                                    min_weight=min_weight, feature_scales=scales_a)
    return (c_a, c_b) if np.ndim(k) else (c_a[0], c_b[0])


def nfor_denoise(y_a, y_b, variance, feat_a, feat_b, feat_variance, *, feature_radius=5, feature_patch=3,
                 feature_k=0.5, radius=9, patch=3, bandwidths=(0.5, 1.0), mse_radius=9, mse_patch=1, mse_k=1.0,
                 final_feature_radius=2, final_feature_patch=3, final_feature_k=0.5, final_k=1.0,
                 second_pass=True, ridge=RIDGE, threads=None, stride=1, min_weight=MIN_COVER_WEIGHT,
                 diagnostics=None) -> np.ndarray:
    """NFOR on two half buffers with per-pixel features.

    Parameters
    ----------
    y_a, y_b : ndarray (H, W, C)
        The halves' pixel means (independent halves of the samples).
    variance : ndarray (H, W, C)
        Variance of the mean of *all* the samples (a half's mean has twice it).
    feat_a, feat_b : ndarray (H, W, D)
        The halves' feature means, one channel per feature component.
    feat_variance : ndarray (H, W, D)
        Variance of the features' mean of all the samples.
    bandwidths : sequence of one or two floats
        The candidates' NL-means bandwidths k of the regression; with two,
        the filtered selection map blends them (the paper: 0.5 and 1.0).
    second_pass : bool
        Sec. 5.4's second regression of the averaged result; without it the
        image is the average of the two halves' results.
    stride, min_weight : int, float
        Every regression fits windows at every ``stride``-th pixel and row
        only, and at the pixels those windows leave with a total weight
        below ``min_weight`` (1: every pixel, the paper;
        :func:`mcrecon.filters.regression.collaborative_regression`).
    diagnostics : dict, optional
        Receives ``selection`` (H, W): the filtered selection map averaged
        over channels (0: the first bandwidth), ``estimated_mse`` (H, W)
        of the selection's best candidate, and ``half_results``: the two
        halves' first-pass results ``(r_A, r_B)`` (H, W, C) before the
        second pass (with ``second_pass=False`` the image is their mean:
        a caller can cross-validate them against the other half).
    (the other parameters: see :data:`PAPER` and the module's stages)

    Returns
    -------
    ndarray (H, W, C) float64
    """
    if len(bandwidths) not in (1, 2):
        raise ValueError(f"nfor_denoise: bandwidths {bandwidths!r}: one or two values")
    return denoise_planes([y_a, y_b, variance, feat_a, feat_b, feat_variance], feature_radius=feature_radius,
                          feature_patch=feature_patch, feature_k=feature_k, radius=radius, patch=patch,
                          bandwidths=bandwidths, mse_radius=mse_radius, mse_patch=mse_patch, mse_k=mse_k,
                          final_feature_radius=final_feature_radius, final_feature_patch=final_feature_patch,
                          final_feature_k=final_feature_k, final_k=final_k, second_pass=second_pass, ridge=ridge,
                          threads=threads, stride=stride, min_weight=min_weight, diagnostics=diagnostics)


def denoise_planes(planes: list, *, feature_radius, feature_patch, feature_k, radius, patch, bandwidths, mse_radius,
                   mse_patch, mse_k, final_feature_radius, final_feature_patch, final_feature_k, final_k, second_pass,
                   ridge, threads, stride, min_weight, diagnostics, feature_scales=None) -> np.ndarray:
    """:func:`nfor_denoise` of ``planes`` = ``[y_a, y_b, variance, feat_a, feat_b, feat_variance]``, a list it
    empties: a caller that keeps no other reference to a plane lets it go once its stage is done (the
    unfiltered features after the prefilter, the halves' colours after the MSE estimate; at 1920 x 1080
    with seven feature components, 0.35 and 0.1 GB that the later stages' buffers do not sit beside).

    ``feature_scales``: ``(scales_a, scales_b, scales_final)`` (:func:`film_feature_scales`), by which the
    regressions standardise the prefiltered features of each half and the second pass's features,
    instead of these planes' own means and deviations: the one decision of NFOR that reads the whole
    image, made once for a film and handed to its tiles."""
    y_a, y_b, var, fa, fb, fv = (np.asarray(x, dtype=np.float64) for x in planes)
    planes.clear()
    y = 0.5 * (y_a + y_b)
    # 1. feature prefiltering, cross-buffer (A's features with B's weights)
    pf_a, pf_b = prefilter_features(fa, fb, fv, radius=feature_radius, patch=feature_patch, k=feature_k,
                                    threads=threads)
    has_features = bool(fa.shape[2])
    del fa, fb, fv
    # 2. regression per bandwidth, cross-buffer (A's colour: B's weights and B's features)
    # (every bandwidth of a half in one pass: they share its guide, design and colour)
    sc_a, sc_b, sc_final = (None, None, None) if feature_scales is None else feature_scales
    halves = list(zip(*cross_regression(y_a, y_b, var, pf_a, pf_b, radius=radius, patch=patch, k=bandwidths,
                                        ridge=ridge, threads=threads, stride=stride, min_weight=min_weight,
                                        scales_a=sc_a, scales_b=sc_b)))
    # the MSE estimates of every bandwidth share one guide and one set of parameters: one set of weights
    mses = nlmeans_filter_shared([estimate_mse(y_a, y_b, c_a, c_b, var) for c_a, c_b in halves], y, var,
                                 radius=mse_radius, patch=mse_patch, k=mse_k, threads=threads)
    del y_a, y_b
    # 3. selection, per channel: the binary map "the second bandwidth's estimate is not larger", filtered.
    # Each intermediate is dropped once used: at 1080p every (H, W, 3) plane set is 50 MB.
    if len(halves) == 1:
        (r_a, r_b), mse_best = halves[0], mses[0].mean(axis=2)
        sel = np.zeros(y.shape[:2])
        del halves, mses
    else:
        ((a0, b0), (a1, b1)), (m0, m1) = halves, mses
        del halves, mses
        s = nlmeans_filter((m0 >= m1).astype(np.float64), y, var, radius=mse_radius, patch=mse_patch, k=mse_k,
                           threads=threads)
        mse_best = np.minimum(m0, m1).mean(axis=2)
        del m0, m1
        r_a = a0 + s * (a1 - a0)
        del a0, a1
        r_b = b0 + s * (b1 - b0)
        del b0, b1
        sel = s.mean(axis=2)
        del s
    del y
    # 4. second pass on the averages
    res = 0.5 * (r_a + r_b)
    if second_pass:
        res_var = 0.25 * (r_b - r_a) ** 2
        if has_features:
            feat = 0.5 * (pf_a + pf_b)
            feat_var = 0.25 * (pf_b - pf_a) ** 2
            del pf_a, pf_b
            feat = nlmeans_filter(feat, feat, feat_var, radius=final_feature_radius, patch=final_feature_patch,
                                  k=final_feature_k, threads=threads)
            del feat_var
        else:
            feat = pf_a  # (H, W, 0): no feature
        res = collaborative_regression(res, res, res_var, feat, radius=radius, patch=patch, k=final_k,
                                       variance_scale=2.0, ridge=ridge, threads=threads, stride=stride,
                                       min_weight=min_weight, feature_scales=sc_final)
    if diagnostics is not None:
        diagnostics["selection"] = sel
        diagnostics["estimated_mse"] = mse_best
        diagnostics["half_results"] = (r_a, r_b)
    return res


def film_feature_scales(components, *, feature_radius, feature_patch, feature_k, final_feature_radius,
                        final_feature_patch, final_feature_k, second_pass, threads=None) -> tuple:
    """The means and deviations by which :func:`denoise_planes` standardises the features of a whole film:
    ``(scales_a, scales_b, scales_final)``, each a tuple of ``(mean, deviation)`` per feature component
    (:func:`mcrecon.filters.regression.feature_scale`; ``scales_final`` empty without the second pass).

    ``components`` yields each feature component's film planes ``(feat_a, feat_b, feat_variance)`` (H, W)
    in :func:`denoise_planes`'s order.  Each is prefiltered (and averaged and filtered for the second
    pass) on its own: the NL-means filters weigh every channel by its own distances, so a component's
    planes are those the untiled pipeline makes of all of them at once, bit for bit, and their means
    and deviations are the untiled regression's.  A handful of planes of the film at a time, not the
    features' (H, W, D) arrays; the cost is the untiled prefilter's once more.
    """
    sc_a, sc_b, sc_final = [], [], []
    for fa, fb, fv in components:
        pf_a, pf_b = prefilter_features(fa[..., None], fb[..., None], fv[..., None], radius=feature_radius,
                                        patch=feature_patch, k=feature_k, threads=threads)
        del fa, fb, fv
        sc_a.append(feature_scale(pf_a[..., 0]))
        sc_b.append(feature_scale(pf_b[..., 0]))
        if second_pass:  # as denoise_planes' step 4
            feat = 0.5 * (pf_a + pf_b)
            feat_var = 0.25 * (pf_b - pf_a) ** 2
            del pf_a, pf_b
            feat = nlmeans_filter(feat, feat, feat_var, radius=final_feature_radius, patch=final_feature_patch,
                                  k=final_feature_k, threads=threads)
            sc_final.append(feature_scale(feat[..., 0]))
    return tuple(sc_a), tuple(sc_b), tuple(sc_final)

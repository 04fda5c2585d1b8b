"""``awr``: adaptive wavelet rendering (Overbeck, Donner and Ramamoorthi 2009).

Two stages that can be used together or apart (paper Fig. 10):

Reconstruction (§4.2)
    The pixel means are analysed with a biorthogonal wavelet (CDF 9/7 by
    default); every wavelet coefficient is shrunk towards zero by its
    estimated standard deviation ``Delta`` (Eq. 10, 11), then the image is
    synthesised.  ``Delta`` comes from a per-pixel variance image
    ``sigma^2(B) = sigma^2(F) / N`` (Eq. 6) propagated through the
    transform with squared basis functions (Eq. 9, 10).

Adaptive sampling (§4.1)
    Scale coefficients of levels 0..5 are ranked by the priority
    ``P = sigma^2(S) - mean(W^2)`` (Eq. 8); each selected coefficient
    receives ``64 * 2**k`` samples importance-sampled from ``|Phi|``
    (separable 1-D CDF tables, Fig. 5).

Boundary handling and variance propagation
    Images of any size are transformed with PyWavelets' ``symmetric``
    extension (half-sample symmetric; default) or ``periodization``.
    Mirrored or wrapped samples are *the same* random variables as the
    pixels they copy, so the paper's shortcut (a DWT cascade with squared
    filter taps) is wrong at borders and also at levels >= 2 where
    overlapping filters correlate intermediate scale coefficients (the
    paper notes the bias).  We evaluate Eq. 9/10 literally instead: each
    coefficient is an exact linear function of the pixels, ``c = A B``
    with ``A`` the Kronecker product of two 1-D analysis matrices (built
    by running PyWavelets on the identity, so the boundary folding is the
    transform's own), and ``Var(c) = (A o A) sigma^2(B)`` (Eq. 13-15 with
    independent pixels).  The paper's cascade is available as
    ``propagation="cascade"`` for comparison.

Normalisation
    PyWavelets' ``bior4.4`` is CDF 9/7 with the paper's scaling (low-pass
    taps sum to sqrt 2, Appendix A).  The paper renormalises the squared
    filters of its cascade to sum to ``r`` (1.05 for sampling, 2^-1/2 for
    reconstruction).  Scaling a squared 1-D filter from its sum ``s`` to
    ``r`` multiplies every variance that passes through it by ``r / s``,
    so a level-``k`` coefficient's variance is multiplied by
    ``prod_axes (r/s_lo)^(k-1) (r/s_last)`` with ``s_last`` the sum of the
    squared low- or high-pass filter the coefficient ends with on that
    axis.  We apply exactly these factors to the exact variances.

See ``docs/methods/awr.md`` for the equation-to-function map.

References
----------
.. [1] R. S. Overbeck, C. Donner, R. Ramamoorthi, "Adaptive Wavelet
   Rendering", ACM Trans. Graph. 28(5), 140 (SIGGRAPH Asia 2009).
.. [2] D. P. Mitchell, "Generating antialiased images at low sampling
   densities", SIGGRAPH 1987 (the contrast metric, Eq. 5).
.. [3] F. Rousselle, C. Knaus, M. Zwicker, "Adaptive Sampling and
   Reconstruction using Greedy Error Minimization", SIGGRAPH Asia 2011
   (the 1-D two-box comparison, Fig. 6).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Sequence

import numba
import numpy as np
import pywt
import scipy.sparse as sp
from scipy import ndimage

from ..errors import InputError
from ..protocol import SampleRequest
from ..stats import PixelStats
from .base import AdaptiveState, Method, MethodInputs, Option, RunState
from .box import fill_empty_pixels

__all__ = [
    "WAVELETS", "BOUNDARY_MODES", "VARIANCE_ESTIMATORS", "PROPAGATIONS",
    "SAMPLING_RENORM", "RECONSTRUCTION_RENORM",
    "get_wavelet", "default_levels", "functional_variance", "pixel_variance",
    "analysis_matrices", "analyze", "synthesize", "coefficient_variances",
    "renormalisation_factor", "equivalent_filter_norms", "soft_threshold", "awr_reconstruct", "scale_priorities",
    "sample_scale_functions", "plan_awr_positions", "AWRMethod",
]

#: Registry of wavelet bases: our name -> PyWavelets name.  ``bior4.4`` is
#: CDF (Daubechies) 9/7 and ``bior2.2`` LeGall 5/3, both with the paper's
#: Appendix A scaling (analysis low-pass sums to sqrt 2).
WAVELETS = {"cdf97": "bior4.4", "legall53": "bior2.2", "haar": "haar"}
#: Boundary extensions (PyWavelets modes) we support.
BOUNDARY_MODES = ("symmetric", "periodization")
#: sigma^2(F) estimators: (Imax-Imin)^2 (paper, reconstruction), Mitchell's
#: squared contrast (paper Eq. 5, sampling), unbiased sample variance.
VARIANCE_ESTIMATORS = ("range", "contrast", "sample")
#: Variance propagation: exact inner products with squared basis functions
#: (Eq. 9/10 as written) or the paper's DWT cascade with squared taps.
PROPAGATIONS = ("exact", "cascade")
#: Sum the squared filters are renormalised to (paper §4.1 and §4.2).
SAMPLING_RENORM = 1.05
RECONSTRUCTION_RENORM = 2.0 ** -0.5

_MAX_LEVELS = 12


# --------------------------------------------------------------------------
# Bases
# --------------------------------------------------------------------------

def get_wavelet(name: str) -> pywt.Wavelet:
    """The PyWavelets wavelet registered as ``name`` (see :data:`WAVELETS`).

    Raises
    ------
    InputError
        For an unknown name, listing the valid ones.
    """
    if not isinstance(name, str) or name not in WAVELETS:
        raise InputError("awr", "wavelet", f"unknown wavelet {name!r}; valid: {', '.join(WAVELETS)}")
    return pywt.Wavelet(WAVELETS[name])


def _check_mode(mode: str) -> str:
    if mode not in BOUNDARY_MODES:
        raise InputError("awr", "boundary", f"unknown boundary mode {mode!r}; valid: {', '.join(BOUNDARY_MODES)}")
    return mode


def default_levels(shape: Sequence[int]) -> int:
    """Decomposition depth used when ``levels`` is not given.

    ``floor(log2(min side)) - 2``, capped at 6: 6 levels at 1024 and above
    (the paper's "full DWT" of 1024^2 images with 9/7 filters, PyWavelets'
    ``dwt_max_level``), 5 at 128, 4 at 64; 0 (no transform) for sides < 8.
    """
    m = min(int(s) for s in shape)
    if m < 8:
        return 0
    return int(min(6, max(0, math.floor(math.log2(m)) - 2)))


# --------------------------------------------------------------------------
# Variance image (Eq. 5, 6)
# --------------------------------------------------------------------------

def functional_variance(stats: PixelStats, estimator: str = "range") -> np.ndarray:
    """Per-pixel, per-channel estimate of the sample variance sigma^2(F).

    Parameters
    ----------
    stats : PixelStats
    estimator : {'range', 'contrast', 'sample'}
        ``range``: ``(Imax - Imin)^2`` (paper §4.2, reconstruction);
        ``contrast``: Mitchell's squared contrast
        ``(Imax - Imin)^2 / (Imax + Imin)^2`` (Eq. 5, sampling), with
        ``|Imax| + |Imin|`` in the denominator so that signed inputs stay in
        [0, 1] and 0 where both are 0 (an all-black pixel has no contrast);
        ``sample``: the unbiased sample variance ``m2 / (n - 1)``.

    Returns
    -------
    ndarray (H, W, C)
        Finite and >= 0.  Policy for pixels with ``n <= 1`` (no spread
        measurable): they take the average of ``sigma^2(F)`` over the
        pixels with ``n >= 2`` in their 3x3 neighbourhood, else the
        channel's average over all pixels with ``n >= 2``, else 0 (then the
        reconstruction does not smooth).

    References
    ----------
    .. [1] Overbeck et al. 2009, Eq. 5 and §4.2; Mitchell 1987.
    """
    if estimator not in VARIANCE_ESTIMATORS:
        raise InputError("awr", "variance", f"unknown estimator {estimator!r}; valid: {', '.join(VARIANCE_ESTIMATORS)}")
    n = stats.count
    ok = n >= 2
    okc = np.broadcast_to(ok[..., None], stats.mean.shape)
    out = np.zeros(stats.mean.shape)
    if estimator == "sample":
        np.divide(np.maximum(stats.m2, 0.0), np.maximum(n - 1, 1)[..., None], out=out, where=okc)
    else:
        _range_kernel(n, stats.min, stats.max, estimator == "contrast", out)
    if not ok.all():
        out = _fill_undefined(out, ok)
    return out


@numba.njit(cache=True, nogil=True)
def _range_kernel(count, vmin, vmax, contrast, out):
    """(Imax - Imin)^2, or divided by (|Imax| + |Imin|)^2 (Eq. 5), where n >= 2 (one pass)."""
    h, w, c = out.shape
    for j in range(h):
        for i in range(w):
            if count[j, i] < 2:
                continue
            for k in range(c):
                hi = vmax[j, i, k]
                lo = vmin[j, i, k]
                d2 = (hi - lo) * (hi - lo)
                if contrast:
                    den = abs(hi) + abs(lo)
                    out[j, i, k] = d2 / (den * den) if den > 0 else 0.0
                else:
                    out[j, i, k] = d2


def _fill_undefined(var: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Fill pixels without a variance estimate (see :func:`functional_variance`)."""
    if not ok.any():
        return np.zeros_like(var)
    w = ok.astype(np.float64)
    wsum = ndimage.uniform_filter(w, size=3, mode="nearest")
    out = var.copy()
    glob = var[ok].mean(axis=0)
    for c in range(var.shape[2]):
        vsum = ndimage.uniform_filter(var[..., c] * w, size=3, mode="nearest")
        local = np.divide(vsum, wsum, out=np.full_like(vsum, glob[c]), where=wsum > 1e-12)
        out[..., c] = np.where(ok, var[..., c], np.maximum(local, 0.0))
    return out


def pixel_variance(stats: PixelStats, estimator: str = "range") -> np.ndarray:
    """Variance of the pixel means, ``sigma^2(B) = sigma^2(F) / N`` (Eq. 6).

    Empty pixels count as ``N = 1`` (their value is filled from a
    neighbour, which is one sample's worth of information at best).

    References
    ----------
    .. [1] Overbeck et al. 2009, Eq. 6.
    """
    f = functional_variance(stats, estimator)
    return f / np.maximum(stats.count, 1)[..., None]


# --------------------------------------------------------------------------
# Transforms as matrices (exact Eq. 9/10 at every boundary)
# --------------------------------------------------------------------------

@functools.lru_cache(maxsize=32)
def analysis_matrices(n: int, wavelet: str, mode: str, levels: int):
    """1-D analysis operators of every level, as sparse matrices.

    Parameters
    ----------
    n : int
        Signal length.
    wavelet : str
        Registered name (:data:`WAVELETS`).
    mode : str
        Boundary mode (:data:`BOUNDARY_MODES`).
    levels : int

    Returns
    -------
    lo, hi : list of scipy.sparse.csr_matrix
        ``lo[k-1]`` (n_k x n) maps a signal to its level-``k`` scale
        coefficients, ``hi[k-1]`` to its level-``k`` wavelet coefficients,
        exactly as the cascaded ``pywt.dwt`` computes them (so the rows
        are the discrete, boundary-folded basis functions Phi_k and
        Psi_k).  Built by transforming the identity; cached.
    """
    w = get_wavelet(wavelet)
    a = np.eye(n)
    lo, hi = [], []
    for _ in range(levels):
        a, d = pywt.dwt(a, w, mode=mode, axis=0)
        lo.append(_csr(a))
        hi.append(_csr(d))
    return lo, hi


def _csr(m: np.ndarray) -> sp.csr_matrix:
    # pywt's products with zero padding are exact zeros; drop round-off
    # dust far below the taps (1e-300 would otherwise bloat the rows).
    m = np.where(np.abs(m) > 1e-14 * max(np.abs(m).max(), 1e-300), m, 0.0)
    out = sp.csr_matrix(m)
    out.eliminate_zeros()
    return out


@functools.lru_cache(maxsize=32)
def _squared_matrices(n: int, wavelet: str, mode: str, levels: int):
    lo, hi = analysis_matrices(n, wavelet, mode, levels)
    return [m.multiply(m).tocsr() for m in lo], [m.multiply(m).tocsr() for m in hi]


def _apply(mat: sp.csr_matrix, x: np.ndarray, axis: int) -> np.ndarray:
    """``mat`` applied along ``axis`` of ``x``."""
    xm = np.moveaxis(x, axis, 0)
    shp = xm.shape
    y = mat @ xm.reshape(shp[0], -1)
    return np.moveaxis(np.asarray(y).reshape((mat.shape[0],) + shp[1:]), 0, axis)


def analyze(x: np.ndarray, wavelet: str = "cdf97", levels: int = 1, *, mode: str = "symmetric",
            axes: Sequence[int] = (0, 1)):
    """Multi-level non-standard DWT (paper §3, Eq. 1, 2, 7).

    Returns
    -------
    approx : ndarray
        Scale coefficients of the coarsest level.
    details : list of dict
        ``details[k-1]`` maps a PyWavelets key (one ``'a'``/``'d'`` per
        axis, not all ``'a'``) to the level-``k`` wavelet coefficients.
    shapes : list of tuple
        Shape of the approximation entering each level (for cropping on
        synthesis, which makes odd sizes exact).
    scales : list of ndarray
        Scale coefficients of every level 1..levels.
    """
    w = get_wavelet(wavelet)
    _check_mode(mode)
    a = np.asarray(x)
    if a.dtype not in (np.float32, np.float64):
        a = a.astype(np.float64)
    details, shapes, scales = [], [], []
    key_a = "a" * len(axes)
    for _ in range(levels):
        shapes.append(a.shape)
        c = pywt.dwtn(a, w, mode=mode, axes=axes)
        a = c.pop(key_a)
        details.append(c)
        scales.append(a)
    return a, details, shapes, scales


def synthesize(approx: np.ndarray, details, shapes, wavelet: str = "cdf97", *, mode: str = "symmetric",
               axes: Sequence[int] = (0, 1)) -> np.ndarray:
    """Inverse of :func:`analyze` (cropping each level to its analysed shape)."""
    w = get_wavelet(wavelet)
    a = approx
    key_a = "a" * len(axes)
    for det, shp in zip(reversed(details), reversed(shapes)):
        c = dict(det)
        c[key_a] = a
        a = pywt.idwtn(c, w, mode=mode, axes=axes)
        a = a[tuple(slice(0, s) for s in shp)]
    return a


def _filter_sums(wavelet: str) -> tuple[float, float]:
    w = get_wavelet(wavelet)
    return float(np.sum(np.square(w.dec_lo))), float(np.sum(np.square(w.dec_hi)))


@functools.lru_cache(maxsize=64)
def equivalent_filter_norms(wavelet: str, level: int) -> tuple[float, float]:
    """Squared norms of the level-``k`` 1-D scale and wavelet functions.

    The equivalent analysis filters of the cascade are
    ``phi_k = h(z) h(z^2) ... h(z^(2^(k-1)))`` and
    ``psi_k = h(z) ... h(z^(2^(k-2))) g(z^(2^(k-1)))``; their squared
    norms are what Eq. 9/10 give for a unit variance image away from the
    borders.
    """
    w = get_wavelet(wavelet)
    h = np.asarray(w.dec_lo, dtype=np.float64)
    g = np.asarray(w.dec_hi, dtype=np.float64)

    def up(f, m):
        out = np.zeros((len(f) - 1) * m + 1)
        out[::m] = f
        return out

    lo = np.array([1.0])
    for j in range(level - 1):
        lo = np.convolve(lo, up(h, 2 ** j))
    phi = np.convolve(lo, up(h, 2 ** (level - 1)))
    psi = np.convolve(lo, up(g, 2 ** (level - 1)))
    return float(np.sum(phi ** 2)), float(np.sum(psi ** 2))


def renormalisation_factor(wavelet: str, level: int, key: str, renorm: float | None) -> float:
    """Factor that renormalises the squared basis functions of Eq. 9/10.

    The paper renormalises its squared analysis *filters* to sum to
    ``renorm`` (1.05 for sampling, 2^-1/2 for reconstruction); a level-``k``
    coefficient passes ``k`` of them per axis, so a unit variance image
    gets the variance ``renorm^k`` per axis.  We renormalise each squared
    level-``k`` basis function the same way: per axis the factor is
    ``renorm^k / ||f_k||^2`` with ``f_k`` the level-``k`` scale function
    (``'a'``) or wavelet (``'d'``) (:func:`equivalent_filter_norms`).  A
    constant variance image then gets exactly the paper's values
    (``v renorm^(2k)`` in 2-D), while borders and spatial variation keep
    the exact propagation.

    Parameters
    ----------
    key : str
        One ``'a'``/``'d'`` per axis (PyWavelets' key).
    renorm : float or None
        None: 1 (plain Eq. 9/10).
    """
    if renorm is None:
        return 1.0
    n_lo, n_hi = equivalent_filter_norms(wavelet, level)
    f = 1.0
    for ch in key:
        f *= renorm ** level / (n_lo if ch == "a" else n_hi)
    return f


def coefficient_variances(var: np.ndarray, wavelet: str = "cdf97", levels: int = 1, *,
                          mode: str = "symmetric", axes: Sequence[int] = (0, 1),
                          propagation: str = "exact", renorm: float | None = None,
                          which: str = "details"):
    """Propagate a pixel variance image to coefficient variances (Eq. 9, 10).

    ``Var(<B, Phi_k>) = <sigma^2(B), Phi_k^2>`` for independent pixels
    (Appendix B).  ``exact`` evaluates it with the boundary-folded basis
    functions (two sparse products per level and key); ``cascade`` is the
    paper's shortcut, a DWT with the squared filter taps (biased where
    filters overlap and at mirrored borders).

    Parameters
    ----------
    var : ndarray
        Pixel variances, same layout as the transformed image.
    renorm : float or None
        Renormalisation of the squared filters (1.05 sampling, 2^-1/2
        reconstruction in the paper); None leaves Eq. 9/10 unscaled.
    which : {'details', 'scales'}
        Wavelet-coefficient variances (list of dicts per level, like
        :func:`analyze`) or scale-coefficient variances (list of arrays,
        levels 1..levels).

    References
    ----------
    .. [1] Overbeck et al. 2009, Eq. 9, 10 and Appendix B.
    """
    if propagation not in PROPAGATIONS:
        raise InputError("awr", "propagation", f"unknown propagation {propagation!r}; valid: {', '.join(PROPAGATIONS)}")
    _check_mode(mode)
    var = np.asarray(var, dtype=np.float64)
    nd = len(axes)
    out = []
    if propagation == "cascade":
        w = get_wavelet(wavelet)
        s_lo, s_hi = _filter_sums(wavelet)
        r = 1.0 if renorm is None else float(renorm)
        # Squared taps renormalised to sum r (renorm None: the raw squares).
        flo = np.square(w.dec_lo) * (r / s_lo if renorm is not None else 1.0)
        fhi = np.square(w.dec_hi) * (r / s_hi if renorm is not None else 1.0)
        sq = pywt.Wavelet(f"{wavelet}-squared", filter_bank=[flo, fhi, np.square(w.rec_lo), np.square(w.rec_hi)])
        a = var
        for _ in range(levels):
            c = pywt.dwtn(a, sq, mode=mode, axes=axes)
            a = c.pop("a" * nd)
            out.append(a if which == "scales" else c)
        return out
    sq = {ax: _squared_matrices(var.shape[ax], wavelet, mode, levels) for ax in axes}
    for k in range(1, levels + 1):
        if which == "scales":
            v = var
            for ax in axes:
                v = _apply(sq[ax][0][k - 1], v, ax)
            out.append(v * renormalisation_factor(wavelet, k, "a" * nd, renorm))
            continue
        # Apply the first axis once per filter, then branch (shares work).
        partial = {"": var}
        for ax in axes:
            nxt = {}
            for key, v in partial.items():
                nxt[key + "a"] = _apply(sq[ax][0][k - 1], v, ax)
                nxt[key + "d"] = _apply(sq[ax][1][k - 1], v, ax)
            partial = nxt
        partial.pop("a" * nd)
        out.append({key: v * renormalisation_factor(wavelet, k, key, renorm) for key, v in partial.items()})
    return out


# --------------------------------------------------------------------------
# Reconstruction (§4.2)
# --------------------------------------------------------------------------

def soft_threshold(w: np.ndarray, delta: np.ndarray, cs: float = 1.0) -> np.ndarray:
    """``sign(W) * max(0, |W| - cs * Delta)`` (Eq. 11), skipping ``Delta = 0``.

    References
    ----------
    .. [1] Overbeck et al. 2009, Eq. 11.
    """
    w = np.asarray(w, dtype=np.float64)
    t = cs * np.asarray(delta, dtype=np.float64)
    if not np.any(t > 0):
        return w.copy()
    # w - clip(w, -t, t) equals sign(w) max(0, |w| - t) and is w where t = 0.
    return w - np.clip(w, -t, t)


def awr_reconstruct(mean: np.ndarray, var: np.ndarray, *, wavelet: str = "cdf97", cs: float = 1.0,
                    levels: int | None = None, mode: str = "symmetric", propagation: str = "exact",
                    renorm: float | None = RECONSTRUCTION_RENORM, axes: Sequence[int] = (0, 1)) -> np.ndarray:
    """Adaptive wavelet reconstruction of an image from its pixel means.

    Parameters
    ----------
    mean : ndarray (H, W, C) (or any array; ``axes`` are transformed)
        Pixel means B (no empty pixels: fill them first).
    var : ndarray, same shape
        Variances of the pixel means sigma^2(B) (Eq. 6).
    wavelet : str
        :data:`WAVELETS` key.
    cs : float
        Smoothing constant c_s >= 0 (Eq. 11); 0 reproduces ``mean``.
    levels : int or None
        Decomposition depth (None: :func:`default_levels`).
    mode, propagation, renorm
        Boundary extension, variance propagation, squared-filter sum.

    Returns
    -------
    ndarray, shape of ``mean``, float64

    References
    ----------
    .. [1] Overbeck et al. 2009, §4.2, Eq. 10 and 11.
    """
    mean = np.asarray(mean, dtype=np.float64)
    var = np.asarray(var, dtype=np.float64)
    if mean.shape != var.shape:
        raise InputError("awr_reconstruct", "var", f"shape {var.shape}, expected the mean's shape {mean.shape}")
    if not (math.isfinite(cs) and cs >= 0):
        raise InputError("awr_reconstruct", "cs", f"{cs!r}; expected a finite number >= 0")
    _check_mode(mode)
    get_wavelet(wavelet)
    if levels is None:
        levels = default_levels([mean.shape[a] for a in axes])
    if levels <= 0 or cs == 0:
        return mean.copy()
    out = mean.copy()
    kw = dict(wavelet=wavelet, cs=cs, levels=levels, mode=mode, propagation=propagation, renorm=renorm)
    if mean.ndim == 3 and tuple(axes) == (0, 1):
        # Channels with zero variance everywhere pass through without any
        # work; the others are transformed channel-first (contiguous rows
        # make PyWavelets and the sparse products ~2x faster).
        active = np.flatnonzero(np.any(var > 0, axis=(0, 1)))
        if active.size:
            mc = np.ascontiguousarray(np.moveaxis(mean[..., active], 2, 0))
            vc = np.ascontiguousarray(np.moveaxis(var[..., active], 2, 0))
            out[..., active] = np.moveaxis(_awr_core(mc, vc, axes=(1, 2), **kw), 0, 2)
        return out
    if not np.any(var > 0):
        return out
    return _awr_core(mean, var, axes=tuple(axes), **kw)


def _awr_core(mean, var, *, wavelet, cs, levels, mode, propagation, renorm, axes):
    approx, details, shapes, _ = analyze(mean, wavelet, levels, mode=mode, axes=axes)
    dvar = coefficient_variances(var, wavelet, levels, mode=mode, axes=axes, propagation=propagation,
                                 renorm=renorm, which="details")
    new = []
    for det, dv in zip(details, dvar):
        new.append({key: soft_threshold(c, np.sqrt(dv[key]), cs) for key, c in det.items()})
    return synthesize(approx, new, shapes, wavelet, mode=mode, axes=axes)


# --------------------------------------------------------------------------
# Adaptive sampling (§4.1)
# --------------------------------------------------------------------------

def scale_priorities(mean: np.ndarray, var: np.ndarray, *, wavelet: str = "cdf97", levels: int = 5,
                     mode: str = "symmetric", renorm: float | None = SAMPLING_RENORM,
                     propagation: str = "exact") -> list[np.ndarray]:
    """Priorities ``P(S_k) = sigma^2(S_k) - mean_alpha(W_k^alpha)^2`` (Eq. 8).

    Parameters
    ----------
    mean : ndarray (H, W, C) or (H, W)
        Pixel means; the wavelets are taken of their channel mean (the
        paper's "intensity image", Table 1).
    var : ndarray (H, W) or (H, W, C)
        sigma^2(B) from the sampler's estimator (Mitchell contrast, Eq. 5,
        6), averaged over channels.
    levels : int
        Highest scale level; level 0 (the pixels, which have no wavelets)
        has priority ``sigma^2(B)``.

    Returns
    -------
    list of ndarray
        ``out[k]`` (n_k^y, n_k^x) for k = 0..levels.

    References
    ----------
    .. [1] Overbeck et al. 2009, Eq. 8 and 9.
    """
    mean = np.asarray(mean, dtype=np.float64)
    var = np.asarray(var, dtype=np.float64)
    # Scalar intensity images, as in the paper's implementation (Table 1:
    # "intensity images" for the wavelet and the variance updates): the
    # channel mean of the pixel means and of sigma^2(B).
    inten = mean.mean(axis=2) if mean.ndim == 3 else mean
    v = var.mean(axis=2) if var.ndim == 3 else var
    out = [v.copy()]
    if levels <= 0:
        return out
    # float32: the wavelets only rank coefficients; halves the DWT's cost.
    _, details, _, _ = analyze(inten.astype(np.float32), wavelet, levels, mode=mode, axes=(0, 1))
    svar = coefficient_variances(v, wavelet, levels, mode=mode, axes=(0, 1), propagation=propagation,
                                 renorm=renorm, which="scales")
    for k in range(levels):
        # (W~)^2 = mean over the 3 wavelets (Eq. 8).
        w2 = sum(np.square(c, dtype=np.float64) for c in details[k].values()) / len(details[k])
        out.append(svar[k] - w2)
    return out


@functools.lru_cache(maxsize=32)
def _cdf_tables(n: int, wavelet: str, mode: str, levels: int):
    """Per level: (indptr, indices, G) with G = row + within-row CDF of |Phi_k|.

    Row r's entries have G in (r, r + 1], so one ``searchsorted`` on
    ``r + u`` finds the pixel for many rows at once (Fig. 5's tables).
    """
    lo, _ = analysis_matrices(n, wavelet, mode, levels)
    tables = []
    for m in lo:
        a = np.abs(m.data)
        csum = np.cumsum(a)
        start = np.repeat(csum[m.indptr[:-1]] - a[m.indptr[:-1]], np.diff(m.indptr))
        tot = np.repeat(np.add.reduceat(a, m.indptr[:-1]), np.diff(m.indptr))
        within = (csum - start) / tot
        within[m.indptr[1:] - 1] = 1.0
        rows = np.repeat(np.arange(m.shape[0]), np.diff(m.indptr))
        tables.append((m.indptr.copy(), m.indices.astype(np.int64), rows + within, within))
    return tables


@functools.lru_cache(maxsize=64)
def _centre_offset(wavelet: str, mode: str, level: int) -> float:
    """``offset`` with row ``a``'s |Phi_k| centroid at ``2^k a + offset`` (independent of n).

    Measured on a row of a signal long enough that the middle row is more
    than half a support away from both borders.
    """
    big = 2 ** level * (get_wavelet(wavelet).dec_len + 2) * 2
    m = analysis_matrices(big, wavelet, mode, level)[0][level - 1]
    a_mid = m.shape[0] // 2
    row = m.getrow(a_mid)
    wts = np.abs(row.data)
    return float(np.sum(row.indices * wts) / np.sum(wts)) - 2 ** level * a_mid


@functools.lru_cache(maxsize=64)
def _rows_on_film(n: int, wavelet: str, mode: str, levels: int, level: int) -> np.ndarray:
    """Level-``k`` scale coefficients whose unfolded centre lies on the film.

    With ``symmetric`` extension PyWavelets keeps extra coefficients whose
    basis functions are centred beyond the border and fold back onto the
    border pixels; ranking them would count the border several times (it
    drew 3x the interior sample density into the corners).  The sampler
    ranks the coefficients of the paper's grid only: interior rows have
    their |Phi| centroid at ``2^k a + offset``; keep ``a`` with that
    centre in ``[-1/2, n - 1/2]`` (``periodization``: every row).
    """
    lo, _ = analysis_matrices(n, wavelet, mode, levels)
    n_k = lo[level - 1].shape[0]
    if mode == "periodization":
        return np.ones(n_k, bool)
    centre = 2 ** level * np.arange(n_k) + _centre_offset(wavelet, mode, level)
    return (centre >= -0.5) & (centre <= n - 0.5)


@functools.lru_cache(maxsize=64)
def _support_bounds(n: int, wavelet: str, mode: str, levels: int, level: int):
    """First and one-past-last pixel of each level-``k`` scale function's support."""
    m = analysis_matrices(n, wavelet, mode, levels)[0][level - 1]
    starts = m.indptr[:-1]
    return (np.minimum.reduceat(m.indices, starts).astype(np.int64),
            np.maximum.reduceat(m.indices, starts).astype(np.int64) + 1)


def _draw_1d(table, rows: np.ndarray, u: np.ndarray) -> np.ndarray:
    indptr, indices, g, _ = table
    pos = np.searchsorted(g, rows + u, side="right")
    # r + u can round up to r + 1 for u near 1: stay in the row.
    pos = np.clip(pos, indptr[rows], indptr[rows + 1] - 1)
    return indices[pos]


def sample_scale_functions(level: int, iy: np.ndarray, ix: np.ndarray, counts: np.ndarray, *, width: int,
                           height: int, rng: np.random.Generator, wavelet: str = "cdf97",
                           mode: str = "symmetric", levels: int | None = None) -> np.ndarray:
    """Film positions importance-sampled from ``|Phi_{k, iy, ix}|`` (§4.1 Step 3, Fig. 5).

    Each axis is sampled independently from the 1-D CDF of the absolute
    boundary-folded discrete scale function (its row of
    :func:`analysis_matrices`); within the chosen pixel the position is
    uniform.  Level 0 is the pixel itself.

    Parameters
    ----------
    level : int
    iy, ix : ndarray of int
        Coefficient indices at that level.
    counts : ndarray of int
        Samples for each coefficient.

    Returns
    -------
    ndarray (sum(counts), 2)
        (x, y) positions on the film, grouped by coefficient.
    """
    counts = np.asarray(counts, dtype=np.int64)
    iy = np.ascontiguousarray(iy, dtype=np.int64)
    ix = np.ascontiguousarray(ix, dtype=np.int64)
    n = int(counts.sum())
    # float32 uniforms: half the cost; 2^-24 of a pixel is far below any
    # renderer's resolution.
    u = rng.random((n, 4), dtype=np.float32)
    out = np.empty((n, 2))
    if level == 0:
        empty_p, empty_i, empty_c = np.zeros(1, np.int64), np.zeros(1, np.int64), np.zeros(1)
        _draw_kernel(iy, ix, counts, u, empty_p, empty_i, empty_c, empty_p, empty_i, empty_c, False, out)
        return out
    lv = max(level, levels or level)
    ty = _cdf_tables(height, wavelet, mode, lv)[level - 1]
    tx = _cdf_tables(width, wavelet, mode, lv)[level - 1]
    _draw_kernel(iy, ix, counts, u, ty[0], ty[1], ty[3], tx[0], tx[1], tx[3], True, out)
    return out


# Largest jitter inside a pixel: p + u * _JIT < p + 1 in float64 for films
# narrower than ~1e6 pixels (spacing there is 1.2e-10 < 1e-9).
_JIT = 1.0 - 1e-9


@numba.njit(cache=True, nogil=True)
def _paint_boxes(diff, y0, y1, x0, x1):
    """Add the corners of boxes [y0, y1) x [x0, x1) to a 2-D difference array."""
    for i in range(y0.shape[0]):
        diff[y0[i], x0[i]] += 1
        diff[y1[i], x0[i]] -= 1
        diff[y0[i], x1[i]] -= 1
        diff[y1[i], x1[i]] += 1


@numba.njit(cache=True, nogil=True)
def _search_row(indptr, indices, within, r, u):
    """Pixel of row ``r`` whose within-row CDF first exceeds ``u`` (binary search)."""
    lo = indptr[r]
    hi = indptr[r + 1] - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if within[mid] > u:
            hi = mid
        else:
            lo = mid + 1
    return indices[lo]


@numba.njit(cache=True, nogil=True)
def _draw_kernel(iy, ix, counts, u, py_ptr, py_idx, py_cdf, px_ptr, px_idx, px_cdf, scaled, out):
    """Fill ``out`` with ``counts[c]`` positions per coefficient (Fig. 5).

    ``u[:, 0:2]`` choose the pixel rows/columns by inverse CDF of |phi|,
    ``u[:, 2:4]`` the position inside the pixel.
    """
    k = 0
    for c in range(counts.shape[0]):
        for _ in range(counts[c]):
            if scaled:
                y = _search_row(py_ptr, py_idx, py_cdf, iy[c], u[k, 0])
                x = _search_row(px_ptr, px_idx, px_cdf, ix[c], u[k, 1])
            else:
                y = iy[c]
                x = ix[c]
            out[k, 0] = x + u[k, 2] * _JIT
            out[k, 1] = y + u[k, 3] * _JIT
            k += 1


def plan_awr_positions(stats: PixelStats, n_samples: int, rng: np.random.Generator, *, wavelet: str = "cdf97",
                       levels: int = 5, mode: str = "symmetric", per_coefficient: int = 64,
                       renorm: float = SAMPLING_RENORM, propagation: str = "exact",
                       priority_threshold: float | None = None, estimator: str = "contrast"):
    """One batch of the adaptive wavelet sampler (§4.1 Steps 2-3).

    Ranks all scale coefficients of levels 0..``levels`` by Eq. 8 and
    takes them in decreasing priority (a priority queue popped without
    intermediate updates: the batch is the unit after which priorities
    are recomputed), giving ``per_coefficient * 2**k`` samples to each
    until ``n_samples`` are placed (the last one gets the remainder).

    Usable with any reconstruction (paper Fig. 10): the positions are a
    plain sample request.

    Returns
    -------
    positions : ndarray (M, 2) or None
        None when no coefficient's priority exceeds ``priority_threshold``
        (or ``n_samples <= 0``).
    info : dict
        ``max_priority``, ``levels_used`` (samples per level),
        ``affected_fraction`` (share of pixels inside the support of a
        selected coefficient, i.e. what a local update would recompute).
    """
    n_samples = int(n_samples)
    info = {"max_priority": float("nan"), "levels_used": {}, "affected_fraction": 0.0}
    if n_samples <= 0:
        return None, info
    h, w = stats.height, stats.width
    levels = int(min(levels, default_levels((h, w))))
    mean = fill_empty_pixels(stats.mean.copy(), stats.count, source="awr sampler") if (stats.count == 0).any() \
        else stats.mean
    var = pixel_variance(stats, estimator)
    pri = scale_priorities(mean, var, wavelet=wavelet, levels=levels, mode=mode, renorm=renorm,
                           propagation=propagation)
    for k in range(1, levels + 1):
        on = (_rows_on_film(h, wavelet, mode, levels, k)[:, None]
              & _rows_on_film(w, wavelet, mode, levels, k)[None, :])
        pri[k] = np.where(on, pri[k], -np.inf)
    flat = np.concatenate([p.ravel() for p in pri])
    lev_of = np.concatenate([np.full(p.size, k, np.int64) for k, p in enumerate(pri)])
    off = np.concatenate([[0], np.cumsum([p.size for p in pri])])
    info["max_priority"] = float(flat.max())
    if priority_threshold is not None and not flat.max() > priority_threshold:
        return None, info
    # Enough candidates for the batch even if all are level 0.
    m = min(flat.size, n_samples // per_coefficient + 1)
    cand = np.argpartition(-flat, m - 1)[:m] if m < flat.size else np.arange(flat.size)
    cand = cand[np.argsort(-flat[cand], kind="stable")]
    if priority_threshold is not None:
        cand = cand[flat[cand] > priority_threshold]
    cost = per_coefficient * (2 ** lev_of[cand])
    csum = np.cumsum(cost)
    k_last = int(np.searchsorted(csum, n_samples))          # first index reaching the quota
    cand = cand[:k_last + 1]
    cost = cost[:k_last + 1].copy()
    placed = int(cost[:-1].sum())
    cost[-1] = min(cost[-1], n_samples - placed)
    parts = []
    # Support bounding boxes of the selected coefficients, painted with a
    # 2-D difference array: the area a local priority update would redo.
    diff = np.zeros((h + 1, w + 1), np.int64)
    for k in range(levels + 1):
        sel = lev_of[cand] == k
        if not sel.any():
            continue
        local = cand[sel] - off[k]
        ny, nx = pri[k].shape
        iy, ix = local // nx, local % nx
        parts.append(sample_scale_functions(k, iy, ix, cost[sel], width=w, height=h, rng=rng, wavelet=wavelet,
                                            mode=mode, levels=levels))
        info["levels_used"][k] = int(cost[sel].sum())
        if k == 0:
            y0, y1, x0, x1 = iy, iy + 1, ix, ix + 1
        else:
            sy, sx = _support_bounds(h, wavelet, mode, levels, k), _support_bounds(w, wavelet, mode, levels, k)
            y0, y1, x0, x1 = sy[0][iy], sy[1][iy], sx[0][ix], sx[1][ix]
        _paint_boxes(diff, np.asarray(y0, np.int64), np.asarray(y1, np.int64),
                     np.asarray(x0, np.int64), np.asarray(x1, np.int64))
    cover = np.cumsum(np.cumsum(diff, axis=0), axis=1)[:h, :w] > 0
    info["affected_fraction"] = float(cover.mean())
    pos = np.concatenate(parts, axis=0) if parts else np.zeros((0, 2))
    return pos, info


# --------------------------------------------------------------------------
# The method
# --------------------------------------------------------------------------

class AWRMethod(Method):
    """Adaptive wavelet rendering: wavelet sampling and soft-thresholding reconstruction.

    Options (keyword-only; also CLI flags): see :attr:`options`.

    Diagnostics: ``pixel_std`` and ``smoothing`` of the reconstruction,
    ``samples`` (samples per pixel) of an adaptive run.

    References
    ----------
    .. [1] R. S. Overbeck, C. Donner, R. Ramamoorthi, "Adaptive Wavelet
       Rendering", SIGGRAPH Asia 2009.
    """

    name = "awr"
    adaptive = True
    initial_spp = 4
    options = (
        Option("wavelet", str, "cdf97", "wavelet basis", tuple(WAVELETS)),
        Option("cs", float, 1.0, "smoothing constant c_s of Eq. 11 (0 = no smoothing)", min=0.0),
        Option("variance", str, "range", "sigma^2(F) estimator of the reconstruction", VARIANCE_ESTIMATORS),
        Option("levels", int, None, "reconstruction depth (default: floor(log2(min side)) - 2, at most 6)",
               min=0, max=_MAX_LEVELS),
        Option("boundary", str, "symmetric", "wavelet boundary extension", BOUNDARY_MODES),
        Option("propagation", str, "exact", "variance propagation: exact Eq. 9/10 or the paper's squared-tap DWT",
               PROPAGATIONS),
        Option("renorm", float, RECONSTRUCTION_RENORM, "sum of the squared reconstruction filters (paper 2^-1/2)",
               min=0.0, min_open=True),
        Option("sampling_renorm", float, SAMPLING_RENORM, "sum of the squared sampling filters (paper 1.05)",
               min=0.0, min_open=True),
        Option("sampling_levels", int, 5, "highest scale level the sampler ranks (paper 5)", min=0),
        Option("sampling_variance", str, "contrast", "sigma^2(F) estimator of the sampler (paper: contrast)",
               VARIANCE_ESTIMATORS),
        Option("per_coefficient", int, 64, "samples per selected level-0 coefficient (x 2^k at level k)", min=1),
        Option("round_spp", float, 4.0, "samples per pixel placed per adaptive round (priority update interval)",
               min=0.0, min_open=True),
        Option("initial_spp", int, 4, "uniform samples per pixel of the first round (paper 4)", min=1),
        Option("priority_threshold", float, None, "stop sampling when no priority exceeds this"),
        Option("reconstruction", str, "awr", "final image of an adaptive run: awr, or box (AWR sampling only)",
               ("awr", "box")),
    )

    # -------------------------------------------------------------- offline
    def _levels(self, h: int, w: int) -> int:
        return default_levels((h, w)) if self.params["levels"] is None else self.params["levels"]

    def reconstruct_run(self, run: RunState, inputs: MethodInputs) -> np.ndarray:
        """AWR reconstruction (§4.2) of pixel statistics (any sampling)."""
        p = self.params
        stats = inputs.stats
        mean = fill_empty_pixels(stats.mean.copy(), stats.count, source="awr")
        var = pixel_variance(stats, p["variance"])
        levels = self._levels(stats.height, stats.width)
        img = awr_reconstruct(mean, var, wavelet=p["wavelet"], cs=p["cs"], levels=levels, mode=p["boundary"],
                              propagation=p["propagation"], renorm=p["renorm"])
        run.diagnostics["pixel_std"] = np.sqrt(var).mean(axis=2)
        run.diagnostics["smoothing"] = np.abs(img - mean).mean(axis=2)
        return img

    # ------------------------------------------------------------- adaptive
    def start(self, width, height, channels=("R", "G", "B"), *, reference=None) -> "AWRRun":
        base = super().start(width, height, channels, reference=reference)
        return AWRRun(**dataclasses.asdict(base))

    def plan(self, run: "AWRRun", state: AdaptiveState) -> SampleRequest | None:
        """Initial uniform pass, then batches of the wavelet sampler (§4.1)."""
        p = self.params
        remaining = state.remaining
        if remaining <= 0:
            return None
        npix = state.width * state.height
        if state.n_samples == 0:
            return state.uniform_request(p["initial_spp"])
        quota = min(remaining, max(1, int(round(p["round_spp"] * npix))))
        pos, info = plan_awr_positions(
            state.stats, quota, state.rng, wavelet=p["wavelet"], levels=p["sampling_levels"], mode=p["boundary"],
            per_coefficient=p["per_coefficient"], renorm=p["sampling_renorm"], propagation=p["propagation"],
            priority_threshold=p["priority_threshold"], estimator=p["sampling_variance"])
        run.last_plan_info = info
        if pos is None or len(pos) == 0:
            return None
        return state.request(positions=pos)

    def finish(self, run: "AWRRun", state: AdaptiveState) -> np.ndarray:
        """AWR (or, with ``reconstruction='box'``, box) image of the adaptive samples.

        Also fills the diagnostic map ``samples`` (samples per pixel): the
        sampler's density, the paper's Fig. 1 insets, and the first thing to
        compare against an error map when the sampler loses (see
        ``docs/methods/awr.md``, "Why adaptive AWR can lose").
        """
        run.diagnostics["samples"] = state.stats.count.astype(np.float64)
        if self.params["reconstruction"] == "box":
            return fill_empty_pixels(state.stats.mean.copy(), state.stats.count, source="awr")
        return self.reconstruct_run(run, state.inputs())


@dataclasses.dataclass(eq=False)
class AWRRun(RunState):
    """Per-run state of :class:`AWRMethod`: what the sampler's last round did."""

    last_plan_info: dict = dataclasses.field(default_factory=dict)

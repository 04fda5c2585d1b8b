"""Wavelet bases, the transform as matrices, and variance propagation (Overbeck et al. 2009, §3, Eq. 9, 10).

Bases
    :data:`WAVELETS` registers the bases by our name; an unknown name gives
    an :class:`~mcrecon.errors.InputError` listing the valid ones
    (:func:`get_wavelet`).  PyWavelets' ``bior4.4`` is CDF 9/7 with the
    paper's scaling (low-pass taps sum to sqrt 2, Appendix A), ``bior2.2``
    LeGall 5/3.

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
    The paper renormalises the squared filters of its cascade to sum to
    ``r`` (1.05 for sampling, 2^-1/2 for reconstruction).  Scaling a
    squared 1-D filter from its sum ``s`` to ``r`` multiplies every
    variance that passes through it by ``r / s``, so a level-``k``
    coefficient's variance is multiplied by
    ``prod_axes (r/s_lo)^(k-1) (r/s_last)`` with ``s_last`` the sum of the
    squared low- or high-pass filter the coefficient ends with on that
    axis.  We apply exactly these factors to the exact variances
    (:func:`renormalisation_factor`).
"""

from __future__ import annotations

import functools
import math
from typing import Sequence

import numpy as np
import pywt
import scipy.sparse as sp

from ...errors import InputError

__all__ = ["WAVELETS", "BOUNDARY_MODES", "PROPAGATIONS", "SAMPLING_RENORM", "RECONSTRUCTION_RENORM",
           "get_wavelet", "default_levels", "analysis_matrices", "analyze", "synthesize",
           "equivalent_filter_norms", "renormalisation_factor", "coefficient_variances"]

#: Registry of wavelet bases: our name -> PyWavelets name.  ``bior4.4`` is
#: CDF (Daubechies) 9/7 and ``bior2.2`` LeGall 5/3, both with the paper's
#: Appendix A scaling (analysis low-pass sums to sqrt 2).
WAVELETS = {"cdf97": "bior4.4", "legall53": "bior2.2", "haar": "haar"}
#: Boundary extensions (PyWavelets modes) we support.
BOUNDARY_MODES = ("symmetric", "periodization")
#: Variance propagation: exact inner products with squared basis functions
#: (Eq. 9/10 as written) or the paper's DWT cascade with squared taps.
PROPAGATIONS = ("exact", "cascade")
#: Sum the squared filters are renormalised to (paper §4.1 and §4.2).
SAMPLING_RENORM = 1.05
RECONSTRUCTION_RENORM = 2.0 ** -0.5


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

"""Sample-space firefly handling shared by every method: luminance cascades with density-adaptive support.

A firefly is not a large value but a *rare* one: a sample far brighter
than the samples around it.  Following the luminance cascades of Zirr,
Hanika and Dachsbacher (2018), each sample's luminance ``L`` is cut into
bands at the levels

.. math::  \\tau_k = L_{max} / s^k, \\qquad k = 0, 1, \\dots, K-1,

down to the first level at or below the median positive sample luminance
(below that level nothing is split), ``s = ratio``.  Where Zirr et al. down-weight a band that has too
few samples around a pixel (biased, energy lost), this module *moves* it:

* A band is **dense** at pixel ``p`` when the 3x3 window around ``p``
  holds at least ``min(k_min, frac * n_window)`` samples above the band's
  lower level.  Density falls as the level rises, so the dense bands of
  ``p`` are the lower ones; ``T(p)`` is the top of the highest dense band.
* A sample's part below ``T(p)`` (its value times ``min(L, T)/L``) is the
  **base**: it stays where it is and goes to the method (any method: its
  own sampling, filtering and selection see no fireflies).
* The part above ``T(p)``, band by band, is the **excess**.  The band-i
  excess of pixel ``p`` (its contribution to the pixel mean) is spread
  with an Epanechnikov kernel of the smallest radius ``r >= 2`` whose
  window holds that many samples above ``tau_i`` (the support a rare
  sample needs: the photon-mapping rule of a fixed count of neighbours),
  at most ``max_radius``; weights are normalised over the pixels inside the
  film, so no energy leaves the image.

Properties (tested in ``tests/test_fireflies.py``):

* **Energy**: base + excess is every sample's value; the spread image's
  sum equals the excess pixel means' sum, so the base's pixel means plus
  the excess have the sum of the pixel means to rounding (1e-9 relative;
  ``box`` fills empty pixels from the base, outside this balance).
* **Rims stay sharp**: a window that holds at least ``min(k_min, frac *
  n_window)`` samples of an emitter's brightness keeps them in their
  pixels; only bright samples with fewer like them within one pixel move,
  and only to pixels that saw samples at least that bright or their 3 x 3
  neighbours (tested: nothing of an emitter reaches pixels two or more
  pixels from any pixel it touches).
* **Consistent**: as the sample count grows every band with non-zero
  probability becomes dense (``frac * n_window`` and ``k_min`` are
  reached), nothing moves, and the result is the method's on all samples.

References
----------
.. [1] T. Zirr, J. Hanika and C. Dachsbacher, "Re-weighting firefly
   samples for improved finite-sample Monte Carlo estimates", Computer
   Graphics Forum 37(6), 2018.
.. [2] H. W. Jensen, "Global illumination using photon maps", Rendering
   Techniques '96 (density estimation from a fixed number of neighbours).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import InputError
import numba

__all__ = ["FireflySplit", "split_fireflies", "sample_luminance", "FIREFLY_MODES"]

#: ``fireflies`` option values: ``none`` leaves the samples alone, ``cascade`` splits them (this module).
FIREFLY_MODES = ("none", "cascade")

#: Rec. 709 luminance weights applied to |R|, |G|, |B|; other channel counts use the mean of |values|.
LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)


@dataclasses.dataclass(eq=False)
class FireflySplit:
    """The two parts of a set of samples.

    Attributes
    ----------
    base_values : ndarray (N, C) float64
        Each sample's value scaled to ``min(L, T(p)) / L``, in the input order.
    excess : ndarray (H, W, C) float64
        The spread excess, as a contribution to the pixel means: add it to a
        reconstruction of the base samples.
    threshold : ndarray (H, W) float64
        ``T(p)``, the luminance above which a sample's part moves (``inf``
        where nothing moves).
    levels : ndarray (K,) float64
        The cascade levels ``tau_k``, decreasing.
    moved_fraction : float
        Fraction of the samples' total luminance (per pixel mean) that moved.
    k_min, neighbour_weight : int, float
        The spreading used.
    """

    base_values: np.ndarray
    excess: np.ndarray
    threshold: np.ndarray
    levels: np.ndarray
    moved_fraction: float
    k_min: int = 4
    neighbour_weight: float = 0.2
    #: Non-finite samples the caller's policy removed or zeroed before the split (set by the caller).
    n_nonfinite: int = 0


def sample_luminance(values: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance of |values| for 3 channels, the mean of |values| otherwise."""
    v = np.abs(np.asarray(values, dtype=np.float64))
    if v.ndim != 2:
        raise InputError("fireflies", "values", f"expected (N, C) values, got shape {v.shape}")
    if v.shape[1] == 3:
        return v @ np.asarray(LUMINANCE_WEIGHTS)
    return v.mean(axis=1)


def _levels(lum: np.ndarray, ratio: float, max_levels: int) -> np.ndarray:
    positive = lum[lum > 0]
    if positive.size == 0:
        return np.zeros(0)
    top, floor = float(positive.max()), float(np.median(positive))
    if not top > floor:
        return np.zeros(0)
    k = min(max_levels, int(np.ceil(np.log(top / floor) / np.log(ratio))) + 1)
    return top / ratio ** np.arange(k, dtype=np.float64)


def split_fireflies(positions, values, *, width: int, height: int, k_min: int = 4, neighbour_weight: float = 0.2,
                    frac: float = 0.25, ratio: float = 2.0, max_radius: int = 32,
                    max_levels: int = 48, sampled_only: bool = False) -> FireflySplit:
    """Split samples into a base for any method and a spread excess of their rare bright parts.

    Parameters
    ----------
    positions : ndarray (N, 2)
        Film positions (x column, y row), inside ``[0, width) x [0, height)``.
    values : ndarray (N, C)
        Finite sample values.
    width, height : int
        The film.
    k_min : int
        Samples above a level a window needs for the level to be dense
        (and the count a spread kernel gathers).  Larger: smoother, more
        bias; consistent for any value.  The default 4 moves only samples
        with fewer than 4 like them within one pixel (see Notes).
    neighbour_weight : float >= 0
        Where a spread kernel puts the excess: each pixel in its support is
        weighted by the number of samples above the band's level in the
        pixel itself plus this weight times those in its 3x3 window (0: only
        pixels that saw such samples; larger: smoother).
    frac : float in (0, 1]
        A window is also dense at a level when this fraction of its
        samples is above it (keeps emitters sharp at low sample counts).
    ratio : float > 1
        Ratio of consecutive cascade levels.
    max_radius : int >= 2
        Largest spread radius in pixels.
    max_levels : int
        Most cascade levels (the top ones; the lowest level rises).
    sampled_only : bool
        Spread the excess only over pixels that hold a sample: a caller
        that adds a pixel's excess to its samples
        (:func:`mcrecon.core.cleaning.clean_samples`) then keeps all of it,
        where an empty pixel could not hold its share.

    Returns
    -------
    FireflySplit

    Notes
    -----
    How far to spread is a bias-variance trade: ``k_min = 16`` halves a
    caustic's error at 256 x 256 and 8 spp but triples it at 64 x 64 and
    16 spp, and smears an emitter's rim at 64 x 64 (measured,
    ``docs/fireflies.md``).  ``k_min = 4`` was never worse than not
    splitting in those measurements; it is the default.  Choosing ``k_min``
    by two-fold cross-validation between halves of the samples was tried
    and rejected: near emitters the halves' relative differences are so
    noisy that the candidates' scores differed by 0.1 % while their true
    errors differed tenfold.

    Examples
    --------
    >>> import numpy as np, mcrecon
    >>> rng = np.random.default_rng(1)
    >>> pos = rng.random((64 * 64 * 16, 2)) * 64
    >>> val = np.full((pos.shape[0], 3), 0.1)
    >>> val[::500] = 200.0                      # rare fireflies
    >>> s = split_fireflies(pos, val, width=64, height=64)      # expectation: 0.1 + 200/500 = 0.5
    >>> box = mcrecon.reconstruct(mcrecon.SampleSet(pos, val, width=64, height=64))
    >>> img = mcrecon.reconstruct(mcrecon.SampleSet(pos, s.base_values, width=64, height=64)) + s.excess
    >>> bool(abs(img.sum() - box.sum()) < 1e-9 * box.sum())   # energy kept
    True
    >>> bool(np.mean((img - 0.5) ** 2) < 0.5 * np.mean((box - 0.5) ** 2))
    True
    """
    where = "fireflies"
    if isinstance(k_min, (str, bool)) or int(k_min) != k_min or k_min < 1:
        raise InputError(where, "k_min", f"got {k_min!r}; expected an integer >= 1")
    if isinstance(neighbour_weight, (str, bool)) or not (neighbour_weight >= 0 and np.isfinite(neighbour_weight)):
        raise InputError(where, "neighbour_weight", f"got {neighbour_weight!r}; expected a finite number >= 0")
    for name, v, lo in (("max_radius", max_radius, 2), ("max_levels", max_levels, 1)):
        if int(v) != v or v < lo:
            raise InputError(where, name, f"got {v!r}; expected an integer >= {lo}")
    if not (0.0 < frac <= 1.0):
        raise InputError(where, "frac", f"got {frac!r}; expected 0 < frac <= 1")
    if not (ratio > 1.0 and np.isfinite(ratio)):
        raise InputError(where, "ratio", f"got {ratio!r}; expected a finite ratio > 1")
    pos = np.asarray(positions, dtype=np.float64)
    val = np.asarray(values, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[1] != 2 or val.ndim != 2 or val.shape[0] != pos.shape[0]:
        raise InputError(where, "samples", f"positions {pos.shape} and values {val.shape}: expected (N, 2), (N, C)")
    if not np.all(np.isfinite(val)):
        raise InputError(where, "values", "non-finite values: apply the nonfinite policy before splitting")
    w, h = int(width), int(height)
    col = np.floor(pos[:, 0]).astype(np.int64)
    row = np.floor(pos[:, 1]).astype(np.int64)
    if pos.shape[0] and (col.min() < 0 or row.min() < 0 or col.max() >= w or row.max() >= h):
        raise InputError(where, "positions", f"positions off the {w}x{h} film")
    pix = row * w + col
    lum = sample_luminance(val)
    options = dict(frac=float(frac), ratio=float(ratio), max_radius=int(max_radius), max_levels=int(max_levels),
                   sampled_only=bool(sampled_only))
    return _split(pix, lum, val, w, h, int(k_min), float(neighbour_weight), **options)


def _split(pix, lum, val, w, h, k_min, neighbour_weight, *, frac, ratio, max_radius, max_levels,
           sampled_only=False):
    levels = _levels(lum, ratio, max_levels)
    n_pix = np.bincount(pix, minlength=w * h).astype(np.int64)
    excess = np.zeros((h, w, val.shape[1]))
    if levels.size < 2:
        return FireflySplit(val.copy(), excess, np.full((h, w), np.inf), levels, 0.0, k_min, neighbour_weight)
    # band b of a sample: levels[b] < L <= levels[b-1] (b = 1..K-1); K: at or below the lowest level
    band = np.searchsorted(-levels, -lum, side="right").astype(np.int64)  # the number of levels >= L
    order = np.argsort(band, kind="stable")
    starts = np.searchsorted(band[order], np.arange(levels.size + 1))
    kstar = np.empty(w * h, dtype=np.int64)
    _first_dense_level(pix[order], starts, n_pix, w, h, k_min, frac, kstar)
    thr = levels[np.minimum(kstar, levels.size) - 1]
    thr = np.where(kstar <= 1, np.inf, thr)
    t_s = thr[pix]
    scale = np.where(lum > t_s, t_s / np.where(lum > 0, lum, 1.0), 1.0)
    base = val * scale[:, None]
    _spread_excess(pix[order], lum[order], val[order], starts, levels, kstar, n_pix, w, h, k_min, frac,
                   max_radius, neighbour_weight, bool(sampled_only), excess.reshape(h * w, -1))
    inv_n = 1.0 / n_pix[pix] if pix.size else np.zeros(0)
    total = float(np.sum(lum * inv_n))
    moved = float(np.sum((lum - np.minimum(lum, t_s)) * inv_n))
    return FireflySplit(base, excess, thr.reshape(h, w), levels, moved / total if total > 0 else 0.0,
                        k_min, neighbour_weight)


@numba.njit(cache=True)
def _integral(img, w, h, out):
    """Summed-area table with a zero first row/column: out (h+1, w+1)."""
    for y in range(h):
        acc = 0
        for x in range(w):
            acc += img[y * w + x]
            out[y + 1, x + 1] = out[y, x + 1] + acc


@numba.njit(cache=True)
def _window(sat, x, y, r, w, h):
    x0 = max(x - r, 0)
    x1 = min(x + r + 1, w)
    y0 = max(y - r, 0)
    y1 = min(y + r + 1, h)
    return sat[y1, x1] - sat[y0, x1] - sat[y1, x0] + sat[y0, x0]


@numba.njit(cache=True)
def _first_dense_level(pix, starts, n_pix, w, h, k_min, frac, kstar):
    """kstar[p]: the first level k (from the top) whose 3x3 window is dense; K when none is."""
    n_levels = starts.shape[0] - 1
    sat_n = np.zeros((h + 1, w + 1), dtype=np.int64)
    _integral(n_pix, w, h, sat_n)
    above = np.zeros(w * h, dtype=np.int64)
    sat = np.zeros((h + 1, w + 1), dtype=np.int64)
    for p in range(w * h):
        kstar[p] = n_levels
    for k in range(1, n_levels):
        for i in range(starts[k], starts[k + 1]):
            above[pix[i]] += 1
        _integral(above, w, h, sat)
        for y in range(h):
            for x in range(w):
                p = y * w + x
                if kstar[p] < n_levels:
                    continue
                need = min(float(k_min), frac * _window(sat_n, x, y, 1, w, h))
                if _window(sat, x, y, 1, w, h) >= need and need > 0:
                    kstar[p] = k


@numba.njit(cache=True)
def _spread_excess(pix, lum, val, starts, levels, kstar, n_pix, w, h, k_min, frac, max_radius,
                   neighbour_weight, sampled_only, out):
    """Spread each pixel's band pieces above its threshold with density-adaptive Epanechnikov kernels."""
    n_levels = starts.shape[0] - 1
    n_ch = val.shape[1]
    sat_n = np.zeros((h + 1, w + 1), dtype=np.int64)
    _integral(n_pix, w, h, sat_n)
    above = np.zeros(w * h, dtype=np.int64)
    sat = np.zeros((h + 1, w + 1), dtype=np.int64)
    # a_sum[p] = sum of v / L over samples of p above the current band's top level
    a_sum = np.zeros((w * h, n_ch))
    piece = np.zeros((w * h, n_ch))
    for k in range(1, n_levels):
        top, low = levels[k - 1], levels[k]
        for p in range(w * h):
            for c in range(n_ch):
                piece[p, c] = (top - low) * a_sum[p, c]
        for i in range(starts[k], starts[k + 1]):
            p = pix[i]
            above[p] += 1
            f = 1.0 - low / lum[i]
            for c in range(n_ch):
                piece[p, c] += val[i, c] * f
        _integral(above, w, h, sat)
        for y in range(h):
            for x in range(w):
                p = y * w + x
                if k >= kstar[p] or n_pix[p] == 0:
                    continue  # band k is dense here (or below the threshold): it stays in the base
                nonzero = False
                for c in range(n_ch):
                    if piece[p, c] != 0.0:
                        nonzero = True
                if not nonzero:
                    continue
                r = 2
                while r < max_radius:
                    need = min(float(k_min), frac * _window(sat_n, x, y, r, w, h))
                    if _window(sat, x, y, r, w, h) >= need:
                        break
                    r += 1
                inv = 1.0 / n_pix[p]
                rr = (r + 1.0) * (r + 1.0)
                wsum = 0.0
                for yy in range(max(y - r, 0), min(y + r + 1, h)):
                    for xx in range(max(x - r, 0), min(x + r + 1, w)):
                        d2 = (xx - x) * (xx - x) + (yy - y) * (yy - y)
                        if d2 < rr and not (sampled_only and n_pix[yy * w + xx] == 0):
                            wsum += (1.0 - d2 / rr) * (_window(sat, xx, yy, 0, w, h) + neighbour_weight * _window(sat, xx, yy, 1, w, h))
                for yy in range(max(y - r, 0), min(y + r + 1, h)):
                    for xx in range(max(x - r, 0), min(x + r + 1, w)):
                        d2 = (xx - x) * (xx - x) + (yy - y) * (yy - y)
                        if d2 < rr and not (sampled_only and n_pix[yy * w + xx] == 0):
                            wt = (1.0 - d2 / rr) * (_window(sat, xx, yy, 0, w, h) + neighbour_weight * _window(sat, xx, yy, 1, w, h)) / wsum * inv
                            q = yy * w + xx
                            for c in range(n_ch):
                                out[q, c] += piece[p, c] * wt
        # samples of band k are above the next band's top level
        for i in range(starts[k], starts[k + 1]):
            p = pix[i]
            for c in range(n_ch):
                a_sum[p, c] += val[i, c] / lum[i]

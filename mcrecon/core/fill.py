"""The one fill-in policy for pixels with fewer than two samples (or none).

Pixels without a variance of their own borrow from their 3x3 neighbours inside the image,
else the image average, else a fallback (:func:`fill_from_neighbours`,
:func:`mean_variance_policy`); pixels without any sample take their nearest sampled
neighbour's value (:func:`fill_empty_pixels`).
"""

from __future__ import annotations

import warnings
from typing import NamedTuple

import numpy as np

from ..errors import McreconWarning


from scipy import ndimage

from ..filters.engine import safe_div
from .stats import PixelStats

__all__ = ['mean_variance_policy', 'fill_empty_pixels', 'fill_from_neighbours', 'FilmRange', 'FilmRangeSum',
           'variance_defined']

def fill_from_neighbours(values: np.ndarray, defined: np.ndarray, fill: np.ndarray | None = None, *,
                         fallback=0.0, film=None) -> np.ndarray:
    """The one fill-in policy for per-pixel estimates a pixel cannot make itself.

    A pixel with fewer than two samples has no sample variance (nor a
    sample range) of its own.  Policy (used by every method): such a pixel
    takes the average of the estimate over the *defined* pixels of its 3x3
    neighbourhood inside the image; if none is defined there, the
    channel's average over all defined pixels of the image; if no pixel of
    the image is defined (a 1-spp input), ``fallback`` (a number or an
    (H, W, C) array the caller derives otherwise).

    Parameters
    ----------
    values : ndarray (H, W, C)
        The estimate, meaningful where ``defined``.
    defined : ndarray of bool (H, W)
        Pixels whose estimate is their own.
    fill : ndarray of bool (H, W), optional
        Pixels to fill (default: every pixel not ``defined``); others keep
        ``values``.
    fallback : float, ndarray (H, W, C) or callable
        A callable is called (without arguments) only when needed.
    film : FilmRange, callable or None
        The image-wide values of the policy (the defined values' average,
        and their range, which bounds the neighbourhood averages) when
        ``values`` is a crop of a film: the film's (:class:`FilmRange`; a
        callable is called without arguments only when a pixel is filled),
        so that a tile fills as the film does.  None: this image's.

    Returns
    -------
    ndarray (H, W, C) float64
    """
    from scipy import ndimage

    values = np.asarray(values, dtype=np.float64)
    defined = np.asarray(defined, dtype=bool)
    fill = ~defined if fill is None else np.asarray(fill, dtype=bool)
    if not fill.any():
        return values
    if film is not None:
        film = film() if callable(film) else film
    elif defined.any():
        film = FilmRange(values[defined].mean(axis=0), values[defined].min(axis=0), values[defined].max(axis=0))
    if film is None or film.mean is None:   # no defined pixel in the film
        fb = fallback() if callable(fallback) else fallback
        sub = np.broadcast_to(np.asarray(fb, dtype=np.float64), values.shape)
    else:
        ok = defined.astype(np.float64)
        num = ndimage.uniform_filter(values * ok[..., None], size=(3, 3, 1), mode="constant")
        den = ndimage.uniform_filter(ok, size=3, mode="constant")[..., None]
        local = np.zeros(np.broadcast_shapes(num.shape, den.shape))
        np.divide(num, den, out=local, where=den > 0)
        # An average cannot leave the range of what it averages, but uniform_filter's running
        # sums can by rounding (-1e-14 from non-negative variances: a negative variance that
        # awr then refused mid-run); clip it back into the defined values' range.
        local = np.clip(local, film.lo, film.hi)
        sub = np.where(den > 1e-12, local, film.mean)
    return np.where(fill[..., None], sub, values)


class FilmRange(NamedTuple):
    """The image-wide values of :func:`fill_from_neighbours`: the defined values' average ``mean`` and range
    ``lo``, ``hi`` (each (C,); all None: no pixel of the film is defined)."""

    mean: np.ndarray | None
    lo: np.ndarray | None
    hi: np.ndarray | None


class FilmRangeSum:
    """:class:`FilmRange` of a film's values added a band of rows at a time (:meth:`add`, in the film's
    order), bit for bit that of the whole film's.  numpy sums the film's defined values of several
    channels one after the other, column by column, so that sum is carried on from band to band; those of
    one channel (a contiguous column) pairwise, so they are kept (8 bytes a defined pixel) and summed at
    the end as the film's."""

    def __init__(self):
        self.total, self.n, self.lo, self.hi, self.kept = None, 0, None, None, []

    def add(self, values: np.ndarray, defined: np.ndarray) -> None:
        v = np.asarray(values, dtype=np.float64)[np.asarray(defined, dtype=bool)]
        if not len(v):
            return
        if v.shape[1] == 1:
            self.kept.append(v)
        elif self.total is None:
            self.total = v.sum(axis=0)
        else:
            self.total = np.concatenate([self.total[None], v]).sum(axis=0)
        lo, hi = v.min(axis=0), v.max(axis=0)
        self.lo, self.hi = (lo, hi) if self.lo is None else (np.minimum(self.lo, lo), np.maximum(self.hi, hi))
        self.n += len(v)

    def result(self) -> FilmRange:
        if not self.n:
            return FilmRange(None, None, None)
        mean = np.concatenate(self.kept).mean(axis=0) if self.kept else self.total / self.n
        return FilmRange(mean, self.lo, self.hi)


def variance_defined(stats: PixelStats) -> tuple[np.ndarray, np.ndarray]:
    """``(sample variances, pixels with n >= 2)``: what :func:`mean_variance_policy` fills from."""
    return stats.sample_variance(undefined=0.0), stats.count >= 2


def fill_empty_pixels(image: np.ndarray, count: np.ndarray, *, source: str = "image") -> np.ndarray:
    """Fill pixels without samples from their nearest sampled neighbours.

    Policy (documented in docs/methods/box.md): each empty pixel takes the
    value of the nearest pixel with samples (Euclidean distance transform);
    an image without any sample stays 0.  A warning counts the filled pixels.
    """
    empty = count == 0
    if not empty.any():
        return image
    if empty.all():
        warnings.warn(f"{source}: no samples at all; the image is 0", McreconWarning, stacklevel=3)
        return np.zeros_like(image)
    from scipy import ndimage

    _, (iy, ix) = ndimage.distance_transform_edt(empty, return_indices=True)
    warnings.warn(f"{source}: {int(empty.sum())} pixel(s) without samples filled from their nearest "
                  "sampled neighbour", McreconWarning, stacklevel=3)
    return image[iy, ix]


# ----------------------------------------------------------------------------
# Finest scale: variance of the pixel means
# ----------------------------------------------------------------------------

def mean_variance_policy(stats: PixelStats, film=None) -> np.ndarray:
    """Variance of each pixel's mean, ``s^2 / n`` (Sec. 6), with a policy for n < 2.

    Policy (the shared :func:`mcrecon.core.fill.fill_from_neighbours`,
    documented in ``docs/methods/gem.md``): a pixel with a single sample has
    no sample variance of its own; it borrows the average sample variance of
    the pixels with n >= 2 in its 3 x 3 neighbourhood, else the image-wide
    average over pixels with n >= 2, else (no pixel has two samples, e.g. a
    1-spp log) the variance of the pixel values in its 3 x 3 neighbourhood
    (signal plus noise: conservative, it errs towards keeping detail).
    Empty pixels get 0 (they are masked out).

    ``film``: the image-wide values (:class:`FilmRange`, or a callable giving
    them, called only when a pixel is filled) when ``stats`` are a tile's
    crop of a film: the film's, so that the tile fills as the film does.
    Default: ``stats.film_fill`` (which the tile driver,
    :func:`mcrecon.offline.tiles.reconstruct_tiles`, sets on each tile's
    statistics), else those of ``stats`` themselves.

    Returns
    -------
    ndarray (H, W, C) float64
    """
    n = stats.count
    var, defined = variance_defined(stats)
    film = stats.film_fill if film is None else film

    def spread_of_pixel_values():
        has = (n >= 1).astype(np.float64)
        m = stats.mean * has[..., None]
        den = ndimage.uniform_filter(has, size=3, mode="constant")[..., None]
        m1 = safe_div(ndimage.uniform_filter(m, size=(3, 3, 1), mode="constant"), den)
        m2 = safe_div(ndimage.uniform_filter(m * m, size=(3, 3, 1), mode="constant"), den)
        return np.maximum(m2 - m1 * m1, 0.0)

    var = fill_from_neighbours(var, defined, n == 1, fallback=spread_of_pixel_values, film=film)
    return var / np.maximum(n, 1)[..., None]

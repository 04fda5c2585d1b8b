"""Albedo demodulation: filter the light arriving at a surface, not the texture on it.

The outgoing radiance of a mostly diffuse surface is its albedo times the
irradiance it receives (over pi): the albedo carries the texture (sharp,
and known per sample from the primary hit), the irradiance carries the
noise (visibility, soft shadows, indirect light) and is smooth where the
texture is not.  Dividing each pixel's mean colour by its mean albedo,
filtering the quotient and multiplying back keeps a checkerboard's edges
however wide the filter, which a filter of the colour cannot: its patch
distance sees the texture edge and stops there, or blurs it.  Where the
albedo is (near) zero - metal, glass, emitters, the background in
renderers that report 0 there - the quotient is meaningless; below
``floor`` the divisor is ``floor`` itself, so those pixels are filtered as
colour (scaled), and their patches, far from any demodulated neighbour's,
keep to themselves.

A filter that demodulates is an ordinary function of the pixel statistics
of one half buffer (colour and albedo of the same samples), so its result
can be cross-validated against the other half without bias
(:func:`mcrecon.methods.auto.estimates.cross_validation_mse`).

References
----------
.. [1] Schied et al., "Spatiotemporal variance-guided filtering: real-time
   reconstruction for path-traced global illumination", High Performance
   Graphics 2017 (filtering the albedo-demodulated illumination).
.. [2] Bako et al., "Kernel-predicting convolutional networks for denoising
   Monte Carlo renderings", ACM TOG 36(4), 2017 (the diffuse component
   divided by the albedo before denoising).
"""

from __future__ import annotations

import numpy as np

from .nlmeans import nlmeans_filter

__all__ = ["ALBEDO_FLOOR", "demodulation_divisor", "demodulation_scale", "irradiance_magnitude", "magnitude_scale",
           "demodulated_nlmeans"]

#: Albedo below which a pixel is not demodulated (its divisor is this value).
ALBEDO_FLOOR = 0.02


def demodulation_divisor(albedo: np.ndarray, channels: int, *, floor: float = ALBEDO_FLOOR) -> np.ndarray:
    """The per-pixel, per-channel divisor of a colour image with ``channels`` channels.

    ``albedo`` (H, W, D): with D == channels each channel is divided by its
    own albedo component, otherwise every channel by the mean of the
    components.  Values below ``floor`` (and NaN, -inf, +inf) become
    ``floor``.
    """
    a = np.asarray(albedo, dtype=np.float64)
    if a.ndim == 2:
        a = a[..., None]
    if a.shape[2] != channels:
        a = np.repeat(a.mean(axis=2, keepdims=True), channels, axis=2)
    return np.where(np.isfinite(a) & (a > floor), a, floor)   # a broken albedo is not divided by


def demodulation_scale(image, albedo, *, floor: float = ALBEDO_FLOOR) -> float:
    """The mean magnitude of the irradiance ``image / albedo`` over its finite values (1 where there is none):
    the unit :func:`demodulated_nlmeans` filters it in.  A whole-image statistic: a tile of an image is
    filtered in its image's (``scale=``)."""
    return magnitude_scale(irradiance_magnitude(image, albedo, floor=floor))


def irradiance_magnitude(image, albedo, *, floor: float = ALBEDO_FLOOR) -> np.ndarray:
    """``|image / albedo|`` (H, W, C) float64, pixel by pixel (:func:`demodulation_divisor`): what
    :func:`demodulation_scale` averages, so a film's is made a band of rows at a time."""
    y = np.asarray(image, dtype=np.float64)
    return np.abs(y / demodulation_divisor(albedo, y.shape[2], floor=floor))


def magnitude_scale(magnitude) -> float:
    """:func:`demodulation_scale` of an image's :func:`irradiance_magnitude` (an array or a memory map): its
    mean over the finite values in the image's order, 1 where there is none."""
    finite = np.isfinite(magnitude)
    scale = float(np.mean(magnitude[finite])) if finite.any() else 1.0
    return scale if np.isfinite(scale) and scale > 0 else 1.0


def demodulated_nlmeans(image, variance, albedo, *, radius: int = 7, patch: int = 3, k: float = 0.45,
                        floor: float = ALBEDO_FLOOR, threads: int | None = None, scale: float | None = None) -> np.ndarray:
    """NL-means of the irradiance ``image / albedo``, multiplied back by the albedo.

    Parameters
    ----------
    image, variance : ndarray (H, W, C)
        Pixel means and the variance of each mean (HDR: never clipped).
    albedo : ndarray (H, W, D)
        Pixel means of the primary hit's albedo (D = C, or any D: then
        their mean divides every channel).
    radius, patch, k : int, int, float
        NL-means search window (2 radius + 1)^2, patch (2 patch + 1)^2 and
        bandwidth (:func:`mcrecon.filters.nlmeans.nlmeans_filter`, own
        weights: the quotient guides itself).
    floor : float
        Albedo below which a pixel's divisor is ``floor``.
    scale : float, optional
        The irradiance's unit (:func:`demodulation_scale`; default: this image's).

    Returns
    -------
    ndarray (H, W, C) float64

    Examples
    --------
    A constant albedo changes nothing (the patch distance is normalised by
    the variance, and the quotient by its mean magnitude, so the filter is
    scale-free):

    >>> rng = np.random.default_rng(0)
    >>> y = 1 + 0.1 * rng.standard_normal((16, 16, 3)); v = np.full_like(y, 0.01)
    >>> a = demodulated_nlmeans(y, v, np.full((16, 16, 3), 0.5))
    >>> b = nlmeans_filter(y, y, v, radius=7, patch=3, k=0.45)
    >>> bool(np.allclose(a, b, rtol=1e-5))
    True
    """
    y = np.asarray(image, dtype=np.float64)
    if y.ndim != 3:
        raise ValueError(f"demodulated_nlmeans: image must be (H, W, C), got shape {y.shape}")
    var = np.asarray(variance, dtype=np.float64)
    if var.shape != y.shape:
        raise ValueError(f"demodulated_nlmeans: variance {var.shape} does not match image {y.shape}")
    m = demodulation_divisor(albedo, y.shape[2], floor=floor)
    if m.shape != y.shape:
        raise ValueError(f"demodulated_nlmeans: albedo {np.shape(albedo)} does not match image {y.shape}")
    # the quotient in units of its mean magnitude: the patch distance's eps (1e-7, absolute) would
    # otherwise outweigh the variance of a dim image's pixels and average across its shadow edges
    # (checker_wall scaled by 1e-3: 0.49 of the pixel mean's error against 0.13 at scale 1)
    irr = y / m
    scale = demodulation_scale(y, albedo, floor=floor) if scale is None else float(scale)
    irr = irr / scale
    out = nlmeans_filter(irr, irr, var / (m * m * scale * scale), radius=radius, patch=patch, k=k, threads=threads)
    return (m * scale) * out

"""Per-pixel moment images (mean, variance, count) a renderer wrote: their validation, one place that says
what is wrong with them, and the statistics :meth:`mcrecon.core.stats.PixelStats.from_moments` builds
from them.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from .features import feature_components
from .samples import as_hwc

__all__ = ["check_moments", "stats_from_moments"]


def check_moments(mean, variance, count, *, variance_of: str = "samples", where: str = "from_moments"):
    """``(mean, variance, count, sampled)`` of per-pixel moment images, checked, or a one-line
    :class:`InputError` naming ``where`` and the field.

    ``mean`` and ``variance`` come back (H, W, C), the variance that of the
    samples (``variance_of='mean'`` multiplied by the count), ``count``
    (H, W) int64 (one number is broadcast), ``sampled`` the (H, W, C) mask of
    pixels with a sample.  Refused: mismatched shapes, NaN/Inf or negative
    variances in sampled pixels, non-integer or negative counts, a variance
    in a pixel with fewer than two samples that is not 0.
    """
    if variance_of not in ("samples", "mean"):
        raise InputError(where, "variance_of", f"{variance_of!r}; valid: samples, mean")
    m, v = as_hwc(mean, where=where, field="mean"), as_hwc(variance, where=where, field="variance")
    if m.ndim != 3 or m.shape[0] < 1 or m.shape[1] < 1 or m.shape[2] < 1:
        raise InputError(where, "mean", f"shape {np.shape(mean)}, expected (height, width, channels)")
    if v.shape != m.shape:
        raise InputError(where, "variance", f"shape {np.shape(variance)}, expected {m.shape} like the mean")
    h, w, c = m.shape
    n = np.asarray(count)
    if n.ndim == 0:
        n = np.full((h, w), n)
    if n.shape != (h, w):
        raise InputError(where, "count", f"shape {n.shape}, expected (height, width) = {(h, w)} or one number")
    if n.dtype.kind == "f":
        if not np.isfinite(n).all() or np.any(n != np.round(n)):
            raise InputError(where, "count", "expected whole numbers of samples per pixel")
    elif n.dtype.kind not in "iu":
        raise InputError(where, "count", f"dtype {n.dtype}, expected integers")
    n = n.astype(np.int64)
    if (n < 0).any():
        raise InputError(where, "count", f"{int((n < 0).sum())} negative count(s)")
    sampled = np.broadcast_to((n > 0)[..., None], m.shape)
    for name, a in (("mean", m), ("variance", v)):
        bad = sampled & ~np.isfinite(a)
        if bad.any():
            raise InputError(where, name, f"{int(bad.any(axis=2).sum())} sampled pixel(s) with NaN or Inf; "
                             "fix the renderer output or set their count to 0")
    if (sampled & (v < 0)).any():
        raise InputError(where, "variance", f"{int((sampled & (v < 0)).any(axis=2).sum())} pixel(s) with a "
                         "negative variance")
    if variance_of == "mean":
        v = v * n[..., None]
    few = np.broadcast_to((n == 1)[..., None], m.shape)
    if (few & (v > 0)).any():
        raise InputError(where, "variance", f"{int((few & (v > 0)).any(axis=2).sum())} pixel(s) with one "
                         "sample but a non-zero variance: a variance needs two samples (check count)")
    return m, v, n, sampled


def stats_from_moments(cls, mean, variance, count, *, channels, variance_of, features, where):
    """:meth:`PixelStats.from_moments <mcrecon.core.stats.PixelStats.from_moments>` (``cls``: the class
    that builds them): the statistics of per-pixel mean, variance and count images, features included."""
    m, v, n, sampled = check_moments(mean, variance, count, variance_of=variance_of, where=where)
    h, w, c = m.shape
    names = tuple(channels) if channels is not None else (
        ("R", "G", "B") if c == 3 else tuple(f"C{i}" for i in range(c)))
    if len(names) != c:
        raise InputError(where, "channels", f"{len(names)} names for {c} channels")
    st = cls(w, h, names)
    st.count[...] = n
    st.mean[...] = np.where(sampled, m, 0.0)
    st.m2[...] = np.where(sampled, v * np.maximum(n - 1, 0)[..., None], 0.0)
    st.min[...] = np.where(sampled, np.nan, np.inf)
    st.max[...] = np.where(sampled, np.nan, -np.inf)
    st.has_range = False
    st._note_dtype(np.result_type(np.asarray(mean).dtype, np.float32) if np.asarray(mean).dtype.kind == "f"
                   else np.float64)
    if features is not None:
        if not hasattr(features, "items"):
            raise InputError(where, "features", f"got {type(features).__name__}, expected a mapping "
                             "name -> (mean, variance)")
        for name, pair in features.items():
            if not isinstance(pair, (tuple, list)) or len(pair) != 2:
                raise InputError(where, f"features/{name}", "expected a pair (mean, variance) of per-pixel "
                                 "images (variance None when unknown)")
            f_mean = as_hwc(pair[0], where=where, field=f"features/{name} mean")
            f_var = np.zeros_like(f_mean) if pair[1] is None else pair[1]
            if f_mean.ndim != 3 or f_mean.shape[:2] != (h, w):
                raise InputError(where, f"features/{name}", f"mean shape {np.shape(pair[0])}, expected "
                                 f"({h}, {w}) or ({h}, {w}, k) like the colour")
            fst = cls.from_moments(f_mean, f_var, n, channels=feature_components(str(name), f_mean.shape[2]),
                                   variance_of=variance_of, where=f"{where}: features/{name}")
            fst.min = fst.max = None  # a feature's statistics keep no range (_feature_stats)
            st.features[str(name)] = fst
    return st

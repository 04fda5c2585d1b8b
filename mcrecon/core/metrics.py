"""Image error metrics against a reference.

Relative MSE follows the adaptive-rendering literature (Rousselle et al.
2011): ``(img - ref)^2 / (ref^2 + eps)`` per pixel and channel, averaged
over both, ``eps = 0.01`` by default.  PSNR needs an explicit data range:
HDR images have none that a dtype could tell.  SSIM is computed by
scikit-image on tone-mapped (sRGB, clipped) images, as a display metric;
reports give ``1 - SSIM`` so that every metric is an error (lower is better).
SMAPE is ``|img - ref| / (|img| + |ref| + eps)`` per pixel and channel,
averaged over both, ``eps = 0.01`` by default (in [0, 1]; no factor 2).
FLIP is NVIDIA's reference implementation (PyPI ``flip-evaluator``, an
optional dependency: ``pip install flip-evaluator``), HDR-FLIP by default.

"""

from __future__ import annotations


import numpy as np

from ..errors import InputError
from .samples import as_hwc


from .._lazy import public_dir as _public_dir

#: eps of the relative estimates: that of :func:`mcrecon.core.metrics.relative_mse`.
DEFAULT_EPS = 1e-2

__all__ = ["relative_mse", "relative_mse_map", "mse", "rmse", "psnr", "ssim", "smape", "smape_map", "flip",
           "flip_available", "error_map", "compare", "output_sanity", "add_sanity"]

FLIP_INSTALL_HINT = "pip install flip-evaluator"


def _pair(img, ref, where="compare", *, names=None, finite_image=False):
    """Both images as (H, W, C) float64, of one shape, the reference finite.

    ``names``: (image, reference) names for the messages (the files
    compared), else the roles; ``finite_image`` refuses NaN/Inf in the
    image too.
    """
    a, b = as_hwc(img), as_hwc(ref)
    if a.shape != b.shape:
        if names is not None:
            raise InputError(f"{names[0]} / {names[1]}", "shape", f"{a.shape} and {b.shape} (height, width, "
                             "channels) differ; compare images of the same size and channel count")
        raise InputError(where, "shape", f"image {a.shape} and reference {b.shape} differ; "
                         "compare images of the same size and channel count")
    for arr, i, role, check in ((b, 1, "reference", True), (a, 0, "image", finite_image)):
        if check and not np.isfinite(arr).all():
            k = int(np.count_nonzero(~np.isfinite(arr)))
            if names is not None:
                raise InputError(names[i], "values", f"{k} non-finite value(s) (NaN or Inf); "
                                 "the metrics compare finite images")
            raise InputError(where, role, f"{k} non-finite value(s)")
    return a, b


def relative_mse_map(img, ref, *, eps: float = 0.01) -> np.ndarray:
    """Per-pixel relative squared error ``(img - ref)^2 / (ref^2 + eps)``, mean over channels (H, W)."""
    if not eps > 0:
        raise InputError("relative_mse", "eps", f"got {eps}, expected > 0")
    a, b = _pair(img, ref)
    return np.mean((a - b) ** 2 / (b * b + eps), axis=2)


def relative_mse(img, ref, *, eps: float = 0.01) -> float:
    """Relative MSE averaged over pixels and channels.

    References
    ----------
    .. [1] F. Rousselle, C. Knaus, M. Zwicker, "Adaptive Sampling and
       Reconstruction using Greedy Error Minimization", SIGGRAPH Asia 2011.
    """
    return float(np.mean(relative_mse_map(img, ref, eps=eps)))


def error_map(img, ref) -> np.ndarray:
    """Per-pixel squared error averaged over channels (H, W)."""
    a, b = _pair(img, ref)
    return np.mean((a - b) ** 2, axis=2)


def mse(img, ref) -> float:
    return float(np.mean(error_map(img, ref)))


def rmse(img, ref) -> float:
    return float(np.sqrt(mse(img, ref)))


def psnr(img, ref, *, data_range: float) -> float:
    """Peak signal-to-noise ratio in dB, with an explicit ``data_range``."""
    if not (np.isfinite(data_range) and data_range > 0):
        raise InputError("psnr", "data_range", f"got {data_range}, expected a positive number "
                         "(HDR images have no implicit range)")
    m = mse(img, ref)
    if m == 0:
        return float("inf")
    return float(10.0 * np.log10(data_range ** 2 / m))


def ssim(img, ref, *, exposure: float = 0.0) -> float:
    """SSIM (scikit-image) of the sRGB tone-mapped images, data range 1."""
    from skimage.metrics import structural_similarity

    from .display import tonemap_srgb

    a, b = _pair(img, ref)
    a = tonemap_srgb(a, exposure=exposure)
    b = tonemap_srgb(b, exposure=exposure)
    h, w = a.shape[:2]
    win = min(7, h, w)
    if win < 3:
        # SSIM needs a window of at least 3 pixels; tiny images compare by exact match.
        return 1.0 if np.array_equal(a, b) else float(1.0 - np.mean((a - b) ** 2))
    if win % 2 == 0:
        win -= 1
    return float(structural_similarity(a, b, data_range=1.0, channel_axis=2, win_size=win))


def smape_map(img, ref, *, eps: float = 0.01) -> np.ndarray:
    """Per-pixel ``|img - ref| / (|img| + |ref| + eps)``, mean over channels (H, W)."""
    if not eps > 0:
        raise InputError("smape", "eps", f"got {eps}, expected > 0")
    a, b = _pair(img, ref, where="smape")
    return np.mean(np.abs(a - b) / (np.abs(a) + np.abs(b) + eps), axis=2)


def smape(img, ref, *, eps: float = 0.01) -> float:
    """Symmetric mean absolute percentage error, in [0, 1].

    ``|img - ref| / (|img| + |ref| + eps)`` averaged over pixels and
    channels, ``eps = 0.01`` by default (no factor 2, so 0 for equal
    images and at most 1).
    """
    return float(np.mean(smape_map(img, ref, eps=eps)))


def flip_available() -> bool:
    """True when ``flip-evaluator`` (NVIDIA's FLIP) can be imported."""
    try:
        import flip_evaluator  # noqa: F401
    except ImportError:
        return False
    return True


def _flip_rgb(x, hdr):
    # flip-evaluator wants C-contiguous float32 (H, W, 3) arrays; one channel
    # is repeated to grey RGB (it gives nonsense for a single channel).
    # Rounding to float32 first makes float32 and float64 inputs agree exactly.
    x = x.astype(np.float32).astype(np.float64)
    if x.shape[2] == 1:
        x = np.repeat(x, 3, axis=2)
    elif x.shape[2] != 3:
        raise InputError("flip", "channels", f"got {x.shape[2]} channels, FLIP compares 1 or 3 (RGB)")
    if hdr:
        # HDR-FLIP is defined for nonnegative linear (sRGB primaries) radiance.
        x = np.maximum(x, 0.0)
    else:
        from .display import tonemap_srgb

        x = tonemap_srgb(x)  # LDR-FLIP takes sRGB-encoded values in [0, 1]
    return np.ascontiguousarray(x, dtype=np.float32)


#: FLIP clamps the reference's median luminance to at least this (float32's epsilon) when it derives
#: HDR-FLIP's exposure range; a maximum below it gives a start exposure above the stop exposure.
_FLIP_MIN_LUMINANCE = float(np.finfo(np.float32).eps)


def _hdr_flip_undefined(ref_rgb) -> str | None:
    """Why HDR-FLIP is not defined against this reference (FLIP-ready RGB), or None.

    HDR-FLIP's exposures run from log2(x / Y_max) to log2(x / max(Y_median,
    eps)), Y being the reference's luminance: a reference whose Y_max is
    below eps (all black, or nearly) has no exposure range, and
    flip-evaluator then prints an error on stdout and ends the process.
    """
    r, g, b = (ref_rgb[..., i].astype(np.float64) for i in range(3))
    y_max = float(np.max((2613072.0 * r + 8788810.0 * g + 887015.0 * b) / 12288897.0))  # FLIP's linear RGB to Y
    if y_max < _FLIP_MIN_LUMINANCE * (1 + 1e-5):  # the margin covers float32 rounding of FLIP's own Y
        return (f"HDR-FLIP is not defined: the reference's largest luminance is {y_max:.3g} (an all-black or "
                f"nearly black reference, below {_FLIP_MIN_LUMINANCE:.3g}), so FLIP has no exposure range; "
                "use LDR-FLIP (--ldr-flip) or skip FLIP (--no-flip)")
    return None


def flip(img, ref, *, hdr: bool = True) -> float:
    """Mean FLIP error (NVIDIA's ``flip-evaluator``), HDR-FLIP by default.

    HDR: linear images, negative values clamped to 0, FLIP's default
    exposure range and ACES tone mapper.  LDR (``hdr=False``): both images
    are first tone-mapped to sRGB and clipped to [0, 1].  67 pixels per
    degree (FLIP's default).  NaN when the image has a non-finite value.

    Raises
    ------
    InputError
        When ``flip-evaluator`` is not installed (``pip install flip-evaluator``),
        or, for HDR-FLIP, the reference is (nearly) black: FLIP has no
        exposure range then.

    References
    ----------
    .. [1] P. Andersson et al., "FLIP: A Difference Evaluator for
       Alternating Images", HPG 2020; "Visualizing Errors in Rendered High
       Dynamic Range Images", Eurographics 2021.
    """
    try:
        import flip_evaluator
    except ImportError:
        raise InputError("flip", "flip-evaluator", f"not installed; FLIP needs it: {FLIP_INSTALL_HINT}") from None
    a, b = _pair(img, ref, where="flip")
    if not np.isfinite(a).all():
        return float("nan")
    ref_rgb = _flip_rgb(b, hdr)
    why = _hdr_flip_undefined(ref_rgb) if hdr else None
    if why is not None:
        raise InputError("flip", "reference", why)
    _, mean, _ = flip_evaluator.evaluate(ref_rgb, _flip_rgb(a, hdr), "HDR" if hdr else "LDR", applyMagma=False)
    return float(mean)


def compare(img, ref, *, eps: float = 0.01, data_range: float | None = None, smape_eps: float = 0.01,
            flip_mode: str | None = "hdr", names: tuple[str, str] | None = None) -> dict:
    """All metrics as a dict (PSNR with ``data_range``, default the reference's max).

    ``relative_mse`` with ``eps`` (also as ``relative_mse_eps``), ``smape``
    with ``smape_eps``, ``ssim`` and ``one_minus_ssim``, and ``flip`` with
    ``flip_mode`` ("hdr" or "ldr"; None skips FLIP).  When
    ``flip-evaluator`` is not installed, or HDR-FLIP is not defined (a
    black reference), ``flip`` is left out and ``notes`` (a list of
    strings) says why.  Both images must be finite (NaN or Inf in either
    is an :class:`InputError` with the count); ``names`` (image,
    reference), e.g. their files, are what the errors name.
    """
    if flip_mode not in (None, "hdr", "ldr"):
        raise InputError("compare", "flip_mode", f"got {flip_mode!r}, expected 'hdr', 'ldr' or None")
    a, b = _pair(img, ref, names=names, finite_image=True)
    if data_range is None:
        data_range = float(np.max(b)) if np.max(b) > 0 else 1.0
    s = ssim(a, b)
    out = {
        "relative_mse": relative_mse(a, b, eps=eps),
        "relative_mse_eps": eps,
        "smape": smape(a, b, eps=smape_eps),
        "smape_eps": smape_eps,
        "mse": mse(a, b),
        "rmse": rmse(a, b),
        "psnr": psnr(a, b, data_range=data_range),
        "psnr_data_range": data_range,
        "ssim": s,
        "one_minus_ssim": 1.0 - s,
        "eps": eps,
    }
    if flip_mode is not None:
        why = _hdr_flip_undefined(_flip_rgb(b, True)) if flip_mode == "hdr" and b.shape[2] in (1, 3) else None
        if not flip_available():
            out["notes"] = [f"FLIP omitted: flip-evaluator is not installed ({FLIP_INSTALL_HINT})"]
        elif why is not None:
            out["notes"] = [f"FLIP omitted: {why}"]
        else:
            out["flip"] = flip(a, b, hdr=flip_mode == "hdr")
            out["flip_mode"] = flip_mode
    return out


def output_sanity(image, stats, *, radius: int = 1, rows=None) -> dict | None:
    """How far a reconstruction leaves the range of the samples it was built from.

    For every pixel and channel the samples of the pixel's (2 radius + 1)^2
    neighbourhood (3x3 by default) span ``[lo, hi]`` (``stats.min`` /
    ``stats.max``).  A reconstruction that filters, thresholds or splats
    can leave that range (ringing, negative lobes); this counts it.

    Parameters
    ----------
    image : ndarray (H, W, C)
    stats : PixelStats
        The statistics of the samples (with their per-pixel range).
    radius : int
        Neighbourhood half-width in pixels.
    rows : (r0, r1), optional
        ``image`` holds rows ``r0:r1`` of the statistics' pixels only (a band
        of a film whose statistics are read with ``radius`` rows around it,
        or up to the film's edge): the band's counts, to be added with
        :func:`add_sanity` over the film's bands.  A neighbourhood without
        samples then counts as non-negative where the band's samples are.

    Returns
    -------
    dict or None
        ``negative_pixels``: pixels with a channel below 0 although every
        sample of their neighbourhood is >= 0 in that channel (a
        neighbourhood without samples counts as non-negative when no sample
        of the image is negative); ``overshoot_pixels``: pixels with a
        channel outside ``[lo, hi]`` by more than 1e-6 of the range's
        magnitude; ``max_overshoot``: the largest distance outside
        ``[lo, hi]`` (0 when none); ``max_overshoot_relative``: that
        distance over ``max(|lo|, |hi|, 1e-12)`` at the worst pixel;
        ``nonfinite_pixels``: pixels with a NaN or Inf.  None when the
        statistics hold no range (built from moments).
    """
    from scipy.ndimage import maximum_filter, minimum_filter

    if not getattr(stats, "has_range", False):
        return None
    img = np.asarray(image, dtype=np.float64)
    if img.ndim == 2:
        img = img[..., None]
    r0, r1 = (0, stats.shape[0]) if rows is None else (int(rows[0]), int(rows[1]))
    if img.shape != (r1 - r0,) + tuple(stats.shape[1:]):
        raise InputError("output_sanity", "image", f"shape {img.shape}, expected the statistics' {stats.shape}"
                         + ("" if rows is None else f" in rows {r0}:{r1}"))
    size = (2 * int(radius) + 1, 2 * int(radius) + 1, 1)
    lo = minimum_filter(stats.min, size=size, mode="nearest")[r0:r1]  # +inf where no sample around
    hi = maximum_filter(stats.max, size=size, mode="nearest")[r0:r1]  # -inf where no sample around
    finite = np.isfinite(img)
    defined = np.isfinite(lo) & np.isfinite(hi) & finite
    any_sample = bool(np.isfinite(stats.min).any())
    global_nonneg = not any_sample or float(np.min(np.where(np.isfinite(stats.min), stats.min, 0.0))) >= 0
    nonneg = np.where(np.isfinite(lo), lo >= 0, global_nonneg)
    negative = (img < 0) & finite & nonneg
    with np.errstate(invalid="ignore"):
        over = np.where(defined, np.maximum(np.maximum(img - hi, lo - img), 0.0), 0.0)
        scale = np.maximum(np.maximum(np.abs(np.where(defined, lo, 0.0)), np.abs(np.where(defined, hi, 0.0))),
                           1e-12)
    rel = over / scale
    worst = int(np.argmax(over)) if over.size else 0
    return {
        "negative_pixels": int(negative.any(axis=2).sum()),
        "overshoot_pixels": int((rel > 1e-6).any(axis=2).sum()),
        "max_overshoot": float(over.flat[worst]) if over.size else 0.0,
        "max_overshoot_relative": float(rel.flat[worst]) if over.size else 0.0,
        "nonfinite_pixels": int((~finite).any(axis=2).sum()),
    }


def add_sanity(total: dict | None, band: dict | None) -> dict | None:
    """The :func:`output_sanity` of a film from its bands' (``rows``), added band after band in row order: the
    counts summed, the worst overshoot the first largest (the film's ``argmax``)."""
    if total is None or band is None:
        return band if total is None else total
    out = {k: total[k] + band[k] for k in ("negative_pixels", "overshoot_pixels", "nonfinite_pixels")}
    worst = band if band["max_overshoot"] > total["max_overshoot"] else total
    out["max_overshoot"], out["max_overshoot_relative"] = worst["max_overshoot"], worst["max_overshoot_relative"]
    return out

__dir__ = _public_dir(__name__)

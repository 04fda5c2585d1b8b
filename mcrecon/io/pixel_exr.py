"""Per-pixel statistics EXRs: a renderer's mean, variance and sample count, read into :class:`PixelStats`.

Most renderers never dump individual samples, but several write, per
pixel, the mean and a variance (or a second moment) of their samples.
:func:`read_pixel_stats_exr` turns such an EXR into the statistics every
method that works from pixel statistics reconstructs from.

Layouts
-------
``pbrt-v4``
    pbrt-v4's GBufferFilm (``src/pbrt/film.cpp``, ``GBufferFilm::GetImage``):
    ``R,G,B`` is the filter-weighted pixel mean in the output colour
    space; ``Variance.R/G/B`` is ``VarianceEstimator::Variance()``, the
    unbiased variance *of the samples* (``S / (n - 1)``, 0 for n <= 1), of
    the *sensor* RGB values added to the pixel.  With pbrt's default
    sensor (``cie1931``, no white balance) the sensor RGB is CIE XYZ, so
    the variances are those of X, Y and Z.  The preset therefore works
    in XYZ: mean = XYZ_from_RGB(file colour space) . (R, G, B), variance
    = ``Variance.*`` as they are, and the reconstruction is converted back
    to the file's RGB (:attr:`PixelStatsEXR.output_matrix`).  The count
    is no channel: pbrt writes the header attribute ``samplesPerPixel``
    (an int); without it ``--spp`` is required.  Every other channel
    (``Albedo.*``, ``P.*``/``Px``, ``N.*``, ``Ns.*``, ``u``, ``v``,
    ``dzdx``, ``dzdy``, ``RelativeVariance.*``) is ignored.
    ``savefp16`` (default true) stores half floats: pbrt clamps ``R,G,B``
    at 65504 (warned here), and a variance above 65504 becomes Inf in the
    file (refused here: render with ``"bool savefp16" false``).
``mitsuba-moment``
    Mitsuba 3's ``moment`` integrator (``src/integrators/moment.cpp``)
    wraps integrators and adds, for the integrator named ``P``, the AOVs
    ``P.X, P.Y, P.Z`` (its radiance converted to CIE XYZ with
    ``srgb_to_xyz``) and ``m2_P.X, m2_P.Y, m2_P.Z`` (their squares): the
    film averages them into the first and second moments per pixel.  The
    preset reads them: mean = m1, variance of the samples
    ``n / (n - 1) * max(m2 - m1^2, 0)``, in XYZ, and converts the
    reconstruction to sRGB with Mitsuba's ``xyz_to_srgb``.  Files written
    from the film (``film.bitmap()``, the ``mitsuba`` command line) keep
    the names; ``mi.util.write_bitmap(path, mi.render(...))`` writes the
    tensor as ``ch0 ... ch8`` (R, G, B, X, Y, Z, m2 X, m2 Y, m2 Z for one
    nested integrator without AOVs), which is recognised positionally.
    Mitsuba writes no sample count: ``--spp`` is required.  Exact with a
    ``box`` reconstruction filter; other filters spread a sample over
    neighbouring pixels (moments become filter-weighted).
``cycles``
    Blender Cycles' multilayer EXR (:mod:`.pixel_exr_cycles`): the mean
    is ``ViewLayer.Noisy Image.R/G/B`` when Cycles denoised (never the
    denoised ``Combined``), else ``ViewLayer.Combined.R/G/B``; the count
    the header attribute ``cycles.ViewLayer.samples``.  One render holds
    no variance (``has_variance`` False): only methods that read the
    means alone take it; several renders with different seeds give the
    variance and half buffers (:func:`mcrecon.io.seed_sets.read_seed_set`).
explicit
    ``mean=`` channels plus ``variance=`` channels (``variance_of``
    'samples' or 'mean') or ``second_moment=`` channels, and a count;
    ``mean=`` alone reads means without a variance, as ``cycles``.

The count comes from ``spp`` (a number), or ``count`` (a number, a
channel holding per-pixel counts, or a header attribute), or else the
header attributes ``samplesPerPixel`` (pbrt-v4) or ``spp``.  A given
``spp`` that contradicts the file's attribute is refused.

Statistics from moments carry no per-pixel sample range
(``stats.has_range`` False) and no subpixel grid nor samples, so methods
that need those refuse them (:func:`mcrecon.methods.supply.check_supply`),
unless the options they declare for pixel statistics
(``Requirements.statistics_options``) do without, and the caller did not
choose otherwise: ``mcrecon.reconstruct("frame.exr")`` then uses those
(:mod:`mcrecon.offline.pixel_files`).

Features
--------
Feature channels found next to the colour are read into the statistics'
per-pixel features (``PixelStats.from_moments(features=...)``; see
``docs/pixel-statistics-inputs.md``), by :data:`FEATURE_CHANNELS`:

* pbrt-v4 (``pbrt-v4`` layout or an explicit mapping): ``albedo`` from
  ``Albedo.R/G/B``; ``normal`` from ``Ns.X/Y/Z`` (the shading normal),
  else ``N.X/Y/Z`` (the geometric one); ``depth`` from ``P.Z`` (pbrt
  writes the camera-space position: its z is the depth).  pbrt writes no
  variance of them: they count as noise-free (variance None).
* Mitsuba 3's ``aov`` integrator (explicit mapping): the AOV names
  ``albedo`` (``albedo.R/G/B``), ``sh_normal`` or ``nn`` (``.X/Y/Z``,
  the name Mitsuba's documentation gives the ``sh_normal`` AOV) and
  ``depth``, ``dd`` or ``dd.y`` (``.T``).  Mitsuba names the channels
  after the AOV's *name*, not its type: other names are not guessed.
* Cycles (``cycles`` layout): ``Denoising Albedo.R/G/B``,
  ``Denoising Normal.X/Y/Z`` and ``Denoising Depth.Z`` of the view layer
  (``view_layer.cycles.denoising_store_passes``), noise-free as pbrt's.
* Mitsuba's ``moment`` integrator wrapping an ``aov`` integrator named
  ``P`` (the prefix of the colour moments): the same AOV names prefixed
  ``P.``, with their second moments ``m2_P.*``, which give the features'
  variances like the colour's; a feature whose ``m2_`` channels are not all
  there is read from its means alone, as noise-free (as pbrt's).

Two candidates for one feature (``sh_normal`` and ``nn``, pbrt and
Mitsuba names) are refused as ambiguous, naming them: choose with
``features={"normal": "nn.X,nn.Y,nn.Z"}``.  Non-finite feature values in
sampled pixels are set to 0 and warned, as for per-sample features
(:func:`mcrecon.core.features.check_features`).  ``features="none"``
reads none.

Half-buffer pairs
-----------------
Two EXRs of independent halves of the samples (dual buffers), read with
the same options by :func:`read_half_buffer_exrs`: the same layout, size,
channels and colour conversion; each file's count is its own half's.
Methods that declare ``requires.half_buffers`` (``auto``) use the pair as
their two halves; the statistics of all the samples are the Chan merge.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import re
import warnings
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from ..errors import InputError, McreconWarning, the_one
from ..core.stats import PixelStats
from ._exr_moments import _split, _variance_from_moments
from .images import subsampled
from .pixel_exr_cycles import cycles_count_attributes, cycles_layers, cycles_mean_channels
from .pixel_exr_features import FEATURE_CHANNELS, _read_features, find_feature_channels  # noqa: F401 (re-exported)

__all__ = ['LAYOUTS', 'PixelStatsEXR', 'read_pixel_stats_exr', 'read_half_buffer_exrs', 'HALF_MAX',
           'MITSUBA_XYZ_TO_SRGB', 'xyz_from_rgb_matrix', 'FEATURE_CHANNELS', 'find_feature_channels',
           'describe_pixel_exr', 'is_pixel_exr', 'is_pixel_file_source']

#: The layout presets (besides the explicit mapping).
LAYOUTS = ("pbrt-v4", "mitsuba-moment", "cycles")

#: The largest finite half float; pbrt clamps its fp16 output here.
HALF_MAX = 65504.0

#: Header attributes holding a per-pixel sample count, searched in this order.
COUNT_ATTRIBUTES = ("samplesPerPixel", "spp")

#: Mitsuba 3's ``xyz_to_srgb`` (include/mitsuba/core/spectrum.h); its inverse is ``srgb_to_xyz``.
MITSUBA_XYZ_TO_SRGB = np.array([[3.240479, -1.537150, -0.498535],
                                [-0.969256, 1.875991, 0.041556],
                                [0.055648, -0.204043, 1.057311]])
_MITSUBA_SRGB_TO_XYZ = np.array([[0.412453, 0.357580, 0.180423],
                                 [0.212671, 0.715160, 0.072169],
                                 [0.019334, 0.119193, 0.950227]])

#: sRGB / Rec. 709 primaries and D65 white (EXR's default when no ``chromaticities`` attribute).
_SRGB_CHROMATICITIES = ((0.64, 0.33), (0.30, 0.60), (0.15, 0.06), (0.3127, 0.3290))


def xyz_from_rgb_matrix(chromaticities=_SRGB_CHROMATICITIES, *, where: str = "xyz_from_rgb_matrix",
                        field: str = "chromaticities") -> np.ndarray:
    """The 3x3 matrix taking linear RGB of the given primaries (red, green, blue, white xy) to XYZ.

    The standard construction (white maps to Y = 1), as pbrt-v4's
    ``RGBColorSpace`` builds its ``XYZFromRGB``.  Chromaticities that
    define no colour space (a y of 0, primaries on one line) are an
    :class:`InputError` naming ``where`` and ``field``.
    """
    (rx, ry), (gx, gy), (bx, by), (wx, wy) = chromaticities
    xy = np.array([rx, ry, gx, gy, bx, by, wx, wy], dtype=np.float64)
    shown = "(" + ", ".join(f"{v:g}" for v in xy) + ")"
    if not np.isfinite(xy).all() or not (xy[1::2] != 0).all():  # ACES AP0's blue has y < 0
        raise InputError(where, field, f"{shown}: every x, y must be finite and every y (red, green, blue, "
                         "white) nonzero; these define no colour space (sRGB / Rec. 709: 0.64 0.33 0.3 0.6 0.15 "
                         "0.06 0.3127 0.329)")
    prim = np.array([[rx / ry, gx / gy, bx / by], [1.0, 1.0, 1.0],
                     [(1 - rx - ry) / ry, (1 - gx - gy) / gy, (1 - bx - by) / by]])
    white = np.array([wx / wy, 1.0, (1 - wx - wy) / wy])
    # primaries on one line (or one point) span no 3-D colour space: no matrix to XYZ exists
    if not np.linalg.cond(prim) < 1e12:
        raise InputError(where, field, f"{shown}: the red, green and blue primaries lie on one line (or "
                         "coincide), so they span no colour space; write the file's real primaries")
    return prim * np.linalg.solve(prim, white)[None, :]


@dataclasses.dataclass(frozen=True, eq=False)
class PixelStatsEXR:
    """Pixel statistics read from an EXR, and how to turn a reconstruction into the file's colours.

    Attributes
    ----------
    stats : PixelStats
        Built with :meth:`PixelStats.from_moments` (``has_range`` False).
    path : Path
    layout : str
        'pbrt-v4', 'mitsuba-moment', 'cycles' or 'explicit'.
    sources : dict
        The channels read: ``mean``, ``variance`` or ``second_moment``.
    count_source : str
        Where the sample count came from, for messages.
    output_channels : tuple of str
        Channel names of :meth:`output_image`.
    output_matrix : ndarray (C_out, C) or None
        Linear map from the statistics' channels to the output channels
        (XYZ to RGB for the presets); None: the identity.
    has_variance : bool
        False for means without a variance (one Cycles render, ``mean=``
        alone): ``stats`` then holds a variance of 0 that no method may
        take for noise-free (:mod:`mcrecon.offline.pixel_files` refuses).
    """

    stats: PixelStats
    path: Path
    layout: str
    sources: dict
    count_source: str
    output_channels: tuple
    output_matrix: np.ndarray | None = None
    has_variance: bool = True

    def output_image(self, image) -> np.ndarray:
        """A reconstruction of :attr:`stats` in the output channels (float64)."""
        img = np.asarray(image, dtype=np.float64)
        return img if self.output_matrix is None else img @ self.output_matrix.T


# ------------------------------------------------------------------ reading
class _EXR:
    """The channels (float arrays, with their stored dtype) and header of one EXR."""

    def __init__(self, path: Path):
        from .images import open_exr_parts

        # parts: what a multi-part file's other parts hold, said once the file is read (a refused file
        # says it in its one error line)
        self.arrays, self.sampling, self.header, self.parts = open_exr_parts(path)
        self.path = path
        self.names = tuple(sorted(self.arrays))

    def present(self) -> str:
        names = self.names
        shown = ", ".join(names[:40]) + (f", ... ({len(names)} channels)" if len(names) > 40 else "")
        return shown or "(none)"

    def get(self, names: Sequence[str], field: str) -> tuple[np.ndarray, bool]:
        """(H, W, len(names)) float64 and whether any of them is stored as half floats."""
        missing = [n for n in names if n not in self.arrays]
        if missing:
            raise InputError(str(self.path), field, f"channel {missing[0]!r} missing"
                             + (f" (and {', '.join(missing[1:])})" if len(missing) > 1 else "")
                             + f"; channels present: {self.present()}")
        subsampled(self.path, self.sampling, names)
        arrs = [self.arrays[n] for n in names]
        half = any(a.dtype == np.float16 for a in arrs)
        return np.stack([a.astype(np.float64) for a in arrs], axis=-1), half


#: The largest sample count a pixel may hold (the statistics count in int64).
_MAX_COUNT = np.iinfo(np.int64).max


def _as_count_number(value) -> int | None:
    """A whole number given as text or number (None if not one, or beyond int64's range)."""
    n = None
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        n = int(value)
    elif isinstance(value, (float, np.floating)) and float(value).is_integer():
        n = int(value)
    elif isinstance(value, str) and re.fullmatch(r"\s*\d+\s*", value):
        n = int(value)
    return n if n is not None and n <= _MAX_COUNT else None


def _attribute_count(exr: _EXR, name: str):
    v = exr.header.get(name)
    if v is None:
        return None
    n = _as_count_number(v if not isinstance(v, np.ndarray) or v.size != 1 else v.item())
    if n is None or n < 1:
        raise InputError(str(exr.path), f"header attribute {name}", f"{v!r}: expected a positive whole number "
                         "of samples per pixel")
    return n


def _resolve_count(exr: _EXR, count, spp):
    """(count array or int, description)."""
    where = str(exr.path)
    if spp is not None and count is not None:
        raise InputError("--spp/--count", "count", "give one of them: --spp N, or --count N|CHANNEL|ATTRIBUTE")
    header_n, header_name = None, None
    for name in COUNT_ATTRIBUTES + cycles_count_attributes(exr.header):
        header_n = _attribute_count(exr, name)
        if header_n is not None:
            header_name = name
            break
    given = spp if spp is not None else count
    flag = "--spp" if spp is not None else "--count"
    if given is not None:
        n = _as_count_number(given)
        if n is None and spp is not None:
            raise InputError("--spp", "spp", f"{spp!r}: expected a positive whole number of samples per pixel")
        if n is not None:
            if n < 1:
                raise InputError(flag, "count", f"{given!r}: expected at least 1 sample per pixel")
            if header_n is not None and header_n != n:
                raise InputError(where, f"header attribute {header_name}",
                                 f"{header_n} samples per pixel, but {flag} says {n}: drop {flag} or fix it")
            return n, f"{flag} {n}"
        name = str(given)
        if name in exr.arrays:
            arr, _ = exr.get([name], "count")
            if not (arr > 0).any():  # refused here, not after a method's note on the statistics
                raise InputError(where, f"count channel {name}", "no pixel has a positive count (no sample "
                                 "anywhere), there is nothing to reconstruct; give the channel of the per-pixel "
                                 "sample counts, or --spp N")
            return arr[..., 0], f"channel {name}"
        if name in exr.header:
            return _attribute_count(exr, name), f"header attribute {name}"
        raise InputError(where, "count", f"{name!r} is neither a number, a channel nor a header attribute; "
                         f"channels present: {exr.present()}")
    if header_n is not None:
        return header_n, f"header attribute {header_name} = {header_n}"
    raise InputError(where, "sample count", "none in the file (no count channel, no samplesPerPixel/spp header "
                     "attribute): pass --spp N (the samples per pixel the renderer took) or --count CHANNEL")


def _check_total(exr: _EXR, n, count_source: str, flag: str) -> None:
    """Refuse a count whose total over the image exceeds int64, in which the statistics count samples."""
    pixels = max((a.size for a in exr.arrays.values()), default=0)
    if np.ndim(n) == 0:
        if int(n) * pixels > _MAX_COUNT:
            given = count_source.startswith(flag)  # the flag's number, else the file's attribute
            raise InputError(flag if given else str(exr.path), flag.lstrip("-") if given else count_source,
                             f"{int(n)} samples per pixel on {pixels} pixels is {int(n) * pixels} "
                             f"samples, beyond the 2^63 - 1 mcrecon counts: at most {_MAX_COUNT // pixels} "
                             "samples per pixel on this image")
    elif float(np.sum(n, dtype=np.float64)) > _MAX_COUNT:
        raise InputError(str(exr.path), count_source, "the counts add up to more than the 2^63 - 1 samples "
                         "mcrecon counts")


def _mitsuba_prefixes(names) -> list[str]:
    """Integrator names P with P.X/Y/Z and m2_P.X/Y/Z channels (the moment integrator's output)."""
    out = []
    for n in names:
        m = re.fullmatch(r"m2_(.+)\.X", n)
        if m:
            p = m.group(1)
            if all(c in names for c in (f"{p}.X", f"{p}.Y", f"{p}.Z", f"m2_{p}.Y", f"m2_{p}.Z")):
                out.append(p)
    # the AOVs of an aov integrator P (P.nn.X: its normals) are not a second colour output
    return sorted(p for p in out if not any(p.startswith(q + ".") for q in out))


def _detect_layout(exr: _EXR) -> str | None:
    names = set(exr.names)
    if {"R", "G", "B", "Variance.R", "Variance.G", "Variance.B"} <= names:
        return "pbrt-v4"
    if _mitsuba_prefixes(names) or set(exr.names) == {f"ch{i}" for i in range(9)}:
        return "mitsuba-moment"
    if cycles_layers(names):
        return "cycles"
    return None


def _file_chromaticities(exr: _EXR):
    c = exr.header.get("chromaticities")
    if c is None:
        return _SRGB_CHROMATICITIES
    try:
        v = [float(x) for x in np.asarray(c, dtype=np.float64).ravel()]
        if len(v) != 8:
            raise ValueError(len(v))
        return ((v[0], v[1]), (v[2], v[3]), (v[4], v[5]), (v[6], v[7]))
    except Exception:
        raise InputError(str(exr.path), "header attribute chromaticities", f"{c!r}: expected 8 numbers "
                         "(red, green, blue, white x y)") from None


def _warn_half_saturation(exr: _EXR, names, values, half, layout):
    if not half:
        return
    sat = np.any(values >= HALF_MAX, axis=-1)
    k = int(sat.sum())
    if k:
        hint = ("pbrt clamps values there when savefp16 is on (its default): these means are too low; "
                "render with \"bool savefp16\" false" if layout == "pbrt-v4" else
                "half floats cannot hold more: these means are clamped or overflowed; write float32 channels")
        warnings.warn(f"{exr.path}: {','.join(names)}: {k} pixel(s) at {HALF_MAX:g}, the largest half float; "
                      f"{hint}", McreconWarning, stacklevel=4)


def _check_finite(exr, names, values, count, field, half):
    sampled = np.broadcast_to(np.asarray(count) > 0, values.shape[:2])[..., None]
    bad = sampled & ~np.isfinite(values)
    if bad.any():
        per = [names[c] for c in range(values.shape[2]) if bad[..., c].any()]
        hint = (" (half-float channels overflow to Inf above 65504: render with float32 output, e.g. pbrt's "
                "\"bool savefp16\" false)" if half and np.isinf(values[bad]).any() else "")
        raise InputError(str(exr.path), ",".join(per), f"{int(bad.any(axis=2).sum())} sampled pixel(s) with "
                         f"NaN or Inf {field}{hint}")


def read_pixel_stats_exr(path, *, layout: str | None = None, mean=None, variance=None, second_moment=None,
                         variance_of: str = "samples", count=None, spp=None, features="auto") -> PixelStatsEXR:
    """Read an EXR of per-pixel statistics (see the module docstring for the layouts).

    Parameters
    ----------
    path : path-like
    layout : {'pbrt-v4', 'mitsuba-moment', 'cycles'} or None
        None: the explicit mapping when ``mean`` is given, else detected
        from the channel names (pbrt-v4's ``Variance.R/G/B``, Mitsuba's
        ``m2_*`` moments, Cycles' ``ViewLayer.Combined``).
    mean, variance, second_moment : str or sequence of str, optional
        Comma-separated channel names; override the preset's.  Give
        ``variance`` or ``second_moment`` (E[x^2]), not both.  Under
        ``mitsuba-moment``, ``mean`` alone picks the first moments and the
        second moments are ``m2_`` + each name.
    variance_of : {'samples', 'mean'}
        What the ``variance`` channels hold (explicit mapping).
    count : int, str, optional
        Samples per pixel: a number, a channel name or a header attribute.
    spp : int, optional
        Samples per pixel (the same as a numeric ``count``).
    features : 'auto', 'none' or mapping
        The feature channels to read into ``stats.features`` (see
        :func:`find_feature_channels` and the module notes): 'auto'
        (default) every one found, 'none' none, or ``{feature: channels}``.

    Returns
    -------
    PixelStatsEXR
        ``sources["features"]`` names the channels each feature was read
        from (``{}`` when none).

    Raises
    ------
    InputError
        A missing channel (naming the channels present), no sample count,
        NaN/Inf or negative variances in sampled pixels, contradicting
        counts.
    """
    path = Path(path)
    if layout is not None and layout not in LAYOUTS:
        raise InputError("--layout", "layout", f"{layout!r}; valid: {', '.join(LAYOUTS)} (or the explicit "
                         "mapping --mean ... --variance ...)")
    if variance_of not in ("samples", "mean"):
        raise InputError("--variance-of", "variance_of", f"{variance_of!r}; valid: samples, mean")
    mean, variance, second_moment = (_split(mean, "mean"), _split(variance, "variance"),
                                     _split(second_moment, "second_moment"))
    if variance is not None and second_moment is not None:
        raise InputError("--variance/--second-moment", "variance", "give one of them")
    exr = _EXR(path)
    try:
        out = _read_stats(exr, layout, mean, variance, second_moment, variance_of, count, spp, features)
    except InputError as exc:
        if exr.parts is None or str(exc.where) != str(path):
            raise
        raise type(exc)(exc.where, exc.field, f"{exc.problem} ({exr.parts})") from None
    if exr.parts is not None:
        warnings.warn(f"{path}: {exr.parts}", McreconWarning, stacklevel=2)
    return out


def _read_stats(exr: _EXR, layout, mean, variance, second_moment, variance_of, count, spp,
                features) -> PixelStatsEXR:
    """:func:`read_pixel_stats_exr` of the opened file, its options checked."""
    path = exr.path
    where = str(path)
    if layout is None:
        layout = "explicit" if mean is not None else _detect_layout(exr)
        if layout is None:
            raise InputError(where, "layout", "not recognised (no pbrt-v4 Variance.R/G/B, no Mitsuba m2_* "
                             f"moments, no Cycles ViewLayer.Combined); channels present: {exr.present()}; pass "
                             "--layout pbrt-v4|mitsuba-moment|cycles or the mapping --mean R,G,B --variance ... "
                             "--count N")
    if not (isinstance(features, Mapping) or features in ("auto", "none")):
        raise InputError(where, "features", f"{features!r}; valid: 'auto', 'none', or a mapping feature -> "
                         "comma-separated channels")
    n, count_source = _resolve_count(exr, count, spp)
    _check_total(exr, n, count_source, "--spp" if spp is not None else "--count")
    out_matrix, out_channels = None, None
    feature_prefix = None
    means_only = layout == "cycles" or (layout == "explicit" and variance is None and second_moment is None)
    if means_only:  # one render's means: the variance comes from several renders (seed_sets)
        if variance is not None or second_moment is not None:
            raise InputError("--variance-channels" if variance is not None else "--second-moment", "variance",
                             "Cycles writes no variance nor second moment: read one render's means, and pass "
                             "several renders with different seeds for the variance")
        if layout == "cycles":
            feature_prefix, mean, _ = cycles_mean_channels(exr.names, where, mean)
        m, half = exr.get(mean, "mean")
        _warn_half_saturation(exr, mean, m, half, layout)
        _check_finite(exr, mean, m, n, "mean", half)
        var, v_of, sources = np.zeros_like(m), "samples", {"mean": tuple(mean)}
        channels = ("R", "G", "B") if layout == "cycles" and len(mean) == 3 else tuple(mean)
    elif layout == "pbrt-v4":
        rgb_names = mean or ("R", "G", "B")
        m_rgb, half = exr.get(rgb_names, "mean")
        _warn_half_saturation(exr, rgb_names, m_rgb, half, layout)
        _check_finite(exr, rgb_names, m_rgb, n, "mean", half)
        if second_moment is not None:
            raise InputError("--second-moment", "second_moment", "pbrt-v4 writes variances: use --variance")
        var_names = variance or ("Variance.R", "Variance.G", "Variance.B")
        var, vhalf = exr.get(var_names, "variance")
        _check_finite(exr, var_names, var, n, "variance", vhalf)
        if len(rgb_names) == 3 and len(var_names) == 3:
            xyz_from_rgb = xyz_from_rgb_matrix(_file_chromaticities(exr), where=where,
                                               field="header attribute chromaticities")
            m = m_rgb @ xyz_from_rgb.T
            channels = ("X", "Y", "Z")
            out_matrix, out_channels = np.linalg.inv(xyz_from_rgb), tuple(rgb_names)
        else:
            m, channels = m_rgb, tuple(rgb_names)
        sources = {"mean": tuple(rgb_names), "variance": tuple(var_names)}
        v_of = "samples"
    elif layout == "mitsuba-moment":
        if variance is not None:
            raise InputError("--variance", "variance", "the moment integrator writes second moments: use "
                             "--second-moment (or --mean alone: m2_ + each name)")
        if mean is None and set(exr.names) == {f"ch{i}" for i in range(9)}:
            mean, second_moment = ("ch3", "ch4", "ch5"), ("ch6", "ch7", "ch8")
        if mean is None:
            prefix = the_one(where, "mean", _mitsuba_prefixes(exr.names),
                             none="no moment-integrator channels (P.X,P.Y,P.Z with m2_P.X,m2_P.Y,m2_P.Z); "
                                  f"channels present: {exr.present()}",
                             several="several moment-integrator outputs ({found}): choose one with --mean P.X,P.Y,P.Z")
            mean = tuple(f"{prefix}.{a}" for a in "XYZ")
        if second_moment is None:
            second_moment = tuple(f"m2_{c}" for c in mean)
        if len(second_moment) != len(mean):
            raise InputError("--second-moment", "second_moment", f"{len(second_moment)} channels for "
                             f"{len(mean)} mean channels")
        m, half = exr.get(mean, "mean")
        m2, half2 = exr.get(second_moment, "second_moment")
        _warn_half_saturation(exr, mean, m, half, layout)
        _check_finite(exr, mean, m, n, "first moment", half)
        _check_finite(exr, second_moment, m2, n, "second moment", half2)
        var = _variance_from_moments(exr, second_moment, m, m2, n, half or half2)
        channels = ("X", "Y", "Z") if len(mean) == 3 else tuple(mean)
        if len(mean) == 3:
            out_matrix, out_channels = MITSUBA_XYZ_TO_SRGB.copy(), ("R", "G", "B")
        sources = {"mean": tuple(mean), "second_moment": tuple(second_moment)}
        v_of = "samples"
        m_prefix = re.fullmatch(r"(.+)\.X", mean[0]) if len(mean) == 3 else None
        feature_prefix = m_prefix.group(1) if m_prefix else None
    else:  # explicit
        m, half = exr.get(mean, "mean")
        _warn_half_saturation(exr, mean, m, half, layout)
        _check_finite(exr, mean, m, n, "mean", half)
        other = variance if variance is not None else second_moment
        if len(other) != len(mean):
            raise InputError("--variance" if variance is not None else "--second-moment", "channels",
                             f"{len(other)} channels for {len(mean)} mean channels")
        if variance is not None:
            var, vhalf = exr.get(variance, "variance")
            _check_finite(exr, variance, var, n, "variance", vhalf)
            sources = {"mean": tuple(mean), "variance": tuple(variance)}
            v_of = variance_of
        else:
            m2, half2 = exr.get(second_moment, "second_moment")
            _check_finite(exr, second_moment, m2, n, "second moment", half2)
            var = _variance_from_moments(exr, second_moment, m, m2, n, half or half2)
            sources = {"mean": tuple(mean), "second_moment": tuple(second_moment)}
            v_of = "samples"
        channels = tuple(mean)

    names_for_var = sources.get("variance", sources.get("second_moment", sources["mean"]))
    sampled = np.broadcast_to(np.asarray(n) > 0, var.shape[:2])[..., None]
    neg = sampled & (var < 0)
    if neg.any():
        per = [names_for_var[c] for c in range(var.shape[2]) if neg[..., c].any()]
        raise InputError(where, ",".join(per), f"{int(neg.any(axis=2).sum())} sampled pixel(s) with a negative "
                         "variance; a variance is >= 0")
    n_arr = np.asarray(n)
    if n_arr.ndim == 0:
        var = np.where(int(n_arr) <= 1, 0.0, var)
    else:
        var = np.where((n_arr <= 1)[..., None], 0.0, var)
    found = find_feature_channels(exr.names, layout, features=features, where=where,
                                  prefix=feature_prefix if layout in ("mitsuba-moment", "cycles") else None)
    # a colour channel is no feature (a mapping --mean P.X,P.Y,P.Z of other data would be read twice)
    used = set(sources["mean"]) | set(sources.get("variance", ())) | set(sources.get("second_moment", ()))
    found = {f: c for f, c in found.items() if not set(c[0]) & used}
    feats = _read_features(exr, found, n) if found else None
    if feats:
        n_arr = np.asarray(n)
        one = (n_arr <= 1) if n_arr.ndim else np.full(m.shape[:2], int(n_arr) <= 1)
        feats = {f: (fm, None if fv is None else np.where(one[..., None], 0.0, fv)) for f, (fm, fv) in feats.items()}
    sources["features"] = {f: c[0] for f, c in found.items()}
    stats = PixelStats.from_moments(m, var, n, channels=channels, variance_of=v_of, where=where, features=feats)
    return PixelStatsEXR(stats, path, layout, sources, count_source,
                         tuple(out_channels) if out_channels is not None else tuple(channels), out_matrix,
                         has_variance=not means_only)


def read_half_buffer_exrs(path_a, path_b, **options) -> tuple[PixelStatsEXR, PixelStatsEXR]:
    """Read a half-buffer pair: two EXRs of independent halves of the samples, with the same options.

    ``options`` are those of :func:`read_pixel_stats_exr`, applied to both
    files (a numeric ``spp`` / ``count`` is then the samples per pixel of
    *each* half; a count channel or header attribute is read from each
    file).  The two must agree in layout, size, channels and colour
    conversion (a pbrt-v4 file's ``chromaticities``); each pixel's counts
    may differ.  Returns the two :class:`PixelStatsEXR`; the statistics of
    all the samples are ``merge_halves(a.stats, b.stats)``
    (:func:`mcrecon.core.halves.merge_halves`).

    Raises
    ------
    InputError
        Anything :func:`read_pixel_stats_exr` refuses, or two files that do
        not match (naming both files and the field).
    """
    with contextlib.suppress(OSError):  # a missing file is named by the reader below
        if os.path.samefile(path_a, path_b):
            raise InputError(f"{path_a} / {path_b} (half-buffer pair)", "--half-buffer",
                             "the same file as both halves: a pair is two EXRs of independent halves of the "
                             "samples (their difference is the noise a dual-buffer method estimates)")
    a = read_pixel_stats_exr(path_a, **options)
    b = read_pixel_stats_exr(path_b, **options)
    where = f"{a.path} / {b.path} (half-buffer pair)"
    if a.layout != b.layout:
        raise InputError(where, "layout", f"the halves have different layouts: {a.layout} vs {b.layout}; "
                         "pass --layout (or the explicit mapping) to read both the same way")
    sa, sb = a.stats, b.stats
    if (sa.height, sa.width) != (sb.height, sb.width):
        raise InputError(where, "shape", f"the halves differ in size: {sa.width}x{sa.height} vs "
                         f"{sb.width}x{sb.height} (width x height)")
    fa, fb = a.sources.get("features", {}), b.sources.get("features", {})
    if fa != fb:
        show = lambda f: ", ".join(f"{k} ({','.join(v)})" for k, v in f.items()) or "none"  # noqa: E731
        raise InputError(where, "features", f"the halves carry different features: {show(fa)} vs {show(fb)}; "
                         "write the same feature channels into both (or read none: features='none')")
    if sa.channels != sb.channels or a.sources != b.sources or a.output_channels != b.output_channels:
        raise InputError(where, "channels", f"the halves differ in channels: "
                         f"{','.join(a.sources['mean'])} vs {','.join(b.sources['mean'])}")
    if int(sa.count.sum(dtype=np.float64)) + int(sb.count.sum(dtype=np.float64)) > _MAX_COUNT:
        raise InputError(where, "count", "the two halves hold more than the 2^63 - 1 samples mcrecon counts "
                         "together: lower --spp/--count")
    ma, mb = a.output_matrix, b.output_matrix
    if (ma is None) != (mb is None) or (ma is not None and not np.allclose(ma, mb, rtol=1e-6, atol=1e-9)):
        raise InputError(where, "chromaticities", "the halves have different colour spaces (their "
                         "chromaticities header attributes differ)")
    return a, b


def describe_pixel_exr(path) -> dict:
    """What a pixel-statistics EXR holds (size, channels, layout, count, features), for ``mcrecon info``:
    read without needing its sample count, so it also describes a file that cannot be reconstructed yet."""
    exr = _EXR(Path(path))
    shapes = {a.shape for a in exr.arrays.values()}
    h, w = next(iter(shapes)) if len(shapes) == 1 else (None, None)
    layout = _detect_layout(exr)
    prefixes = (_mitsuba_prefixes(exr.names) if layout == "mitsuba-moment" else
                cycles_layers(exr.names) if layout == "cycles" else [])
    feats = find_feature_channels(exr.names, layout or "explicit", where=str(path),
                                  prefix=prefixes[0] if len(prefixes) == 1 else None)
    count = next((f"{a} = {exr.header[a]}" for a in COUNT_ATTRIBUTES + cycles_count_attributes(exr.header)
                  if a in exr.header), None)
    return {"file": str(path), "width": w, "height": h, "channels": list(exr.names),
            "layout": layout,
            "count": count or "none in the file (pass --spp N)",
            "features": [{"name": f, "channels": list(m), "second_moments": list(m2) if m2 else None}
                         for f, (m, m2) in feats.items()]}


def is_pixel_exr(x) -> bool:
    """Whether ``x`` is one pixel-statistics EXR: a path ending in ``.exr`` or a read :class:`PixelStatsEXR`."""
    return isinstance(x, PixelStatsEXR) or (isinstance(x, (str, os.PathLike)) and
                                             os.fspath(x).lower().endswith(".exr"))


def is_pixel_file_source(source) -> bool:
    """Whether ``source`` is meant as pixel-statistics EXRs: a path ending in ``.exr``, a read
    :class:`PixelStatsEXR`, or a tuple or list holding one and no :class:`PixelStats`
    (:func:`mcrecon.offline.pixel_files.read_pixel_file_source` then refuses one that is not a pair of two EXRs; with
    statistics in it, it is meant as statistics, and the half-buffer check blames what is not)."""
    if isinstance(source, (tuple, list)):
        return any(is_pixel_exr(x) for x in source) and not any(isinstance(x, PixelStats) for x in source)
    return is_pixel_exr(source)

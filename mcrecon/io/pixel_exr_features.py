"""The feature channels of a pixel-statistics EXR (albedo, normal, depth), for :mod:`.pixel_exr`.

Which channel names mean which feature, per renderer, is in
:data:`FEATURE_CHANNELS` and the notes of :mod:`mcrecon.io.pixel_exr`
(``docs/pixel-statistics-inputs.md``); :func:`find_feature_channels`
picks them out of a file's channel names, refusing ambiguous ones, and
``_read_features`` reads them (variances from second moments where the
file has them; non-finite values set to 0 and warned).
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from ..errors import InputError
from ._exr_moments import _split, _variance_from_moments

__all__ = ["FEATURE_CHANNELS", "find_feature_channels"]

#: Where each feature is found: ``{feature: (source, [channel names, ...] in order of preference)}``
#: per source (pbrt-v4 names, Mitsuba aov names, Cycles' denoising passes); a Mitsuba moment
#: layout looks for the Mitsuba names behind its prefix ``P.`` with second moments ``m2_P.*``
#: (read without a variance, as pbrt's, when some of those are missing); the cycles layout for
#: Cycles' names behind the view layer ``ViewLayer.``.
FEATURE_CHANNELS: dict[str, dict[str, tuple[tuple[str, ...], ...]]] = {
    "albedo": {"pbrt-v4": (("Albedo.R", "Albedo.G", "Albedo.B"),),
               "mitsuba": (("albedo.R", "albedo.G", "albedo.B"),),
               "cycles": (("Denoising Albedo.R", "Denoising Albedo.G", "Denoising Albedo.B"),)},
    # pbrt: the shading normal first, the geometric one only without it (a preference, not ambiguity)
    "normal": {"pbrt-v4": (("Ns.X", "Ns.Y", "Ns.Z"), ("N.X", "N.Y", "N.Z")),
               "mitsuba": (("sh_normal.X", "sh_normal.Y", "sh_normal.Z"), ("nn.X", "nn.Y", "nn.Z")),
               "cycles": (("Denoising Normal.X", "Denoising Normal.Y", "Denoising Normal.Z"),)},
    "depth": {"pbrt-v4": (("P.Z",),),
              "mitsuba": (("depth.T",), ("dd.T",), ("dd.y.T",)),
              "cycles": (("Denoising Depth.Z",),)},
}
#: Sources whose candidates are alternatives in order of preference; in the others two present
#: candidates are ambiguous.
_PREFERENCE_SOURCES = ("pbrt-v4",)


def find_feature_channels(names, layout: str, *, prefix: str | None = None, features="auto",
                          where: str = "EXR") -> dict[str, tuple[tuple[str, ...], tuple[str, ...] | None]]:
    """The feature channels of an EXR: ``{feature: (mean channels, second-moment channels or None)}``.

    Parameters
    ----------
    names : iterable of str
        The file's channel names.
    layout : {'pbrt-v4', 'mitsuba-moment', 'cycles', 'explicit'}
        pbrt-v4 looks for pbrt's names, mitsuba-moment for Mitsuba's behind
        ``prefix`` (with ``m2_`` second moments), cycles for Cycles'
        denoising passes behind ``prefix`` (the view layer), explicit for
        pbrt's and Mitsuba's.
    prefix : str, optional
        The moment integrator's output the colour comes from (``nested``),
        or Cycles' view layer.
    features : 'auto', 'none' or mapping
        'auto': every feature of :data:`FEATURE_CHANNELS` found; 'none':
        none; a mapping ``{feature: "C1,C2,C3"}``: those channels (their
        ``m2_`` second moments too under mitsuba-moment, when present).
    where : str
        The file, for errors.

    Raises
    ------
    InputError
        A feature with two candidates (naming both and the fix), an
        unknown ``features`` value, a mapped channel that is missing.
    """
    names = set(names)
    if isinstance(features, str) and features == "none":
        return {}
    if isinstance(features, Mapping):
        out = {}
        for feat, chans in features.items():
            chans = _split(chans, "features")
            missing = [c for c in chans if c not in names]
            if missing:
                raise InputError(where, f"features/{feat}", f"channel {missing[0]!r} missing; channels present: "
                                 f"{', '.join(sorted(names)[:40])}")
            m2 = tuple(f"m2_{c}" for c in chans)
            out[str(feat)] = (chans, m2 if layout == "mitsuba-moment" and set(m2) <= names else None)
        return out
    if not (isinstance(features, str) and features == "auto"):
        raise InputError(where, "features", f"{features!r}; valid: 'auto', 'none', or a mapping feature -> "
                         "comma-separated channels (e.g. {'normal': 'nn.X,nn.Y,nn.Z'})")
    if layout in ("mitsuba-moment", "cycles") and prefix is None:
        return {}  # positional ch0 ... ch8 (or a Cycles layer not found): no names, no features
    out = {}
    for feat, by_source in FEATURE_CHANNELS.items():
        found = []  # (source, mean channels, m2 channels or None)
        partial = None  # the first candidate with some of its channels but not all
        for source, candidates in by_source.items():
            if layout == "pbrt-v4" and source != "pbrt-v4":
                continue
            if layout == "mitsuba-moment" and source != "mitsuba":
                continue
            if (layout == "cycles") != (source == "cycles"):
                continue
            hits = []
            for cand in candidates:
                if layout == "mitsuba-moment":
                    cand = tuple(f"{prefix}.{c}" for c in cand)
                    m2 = tuple(f"m2_{c}" for c in cand)
                    if set(cand) <= names:  # without all its m2_ moments: means only, as pbrt's features
                        hits.append((source, cand, m2 if set(m2) <= names else None))
                else:
                    if layout == "cycles":
                        cand = tuple(f"{prefix}.{c}" for c in cand)
                    if set(cand) <= names:
                        hits.append((source, cand, None))
                if partial is None and 0 < len(names.intersection(cand)) < len(cand):
                    partial = cand
            if source in _PREFERENCE_SOURCES:
                hits = hits[:1]
            found += hits
        if len(found) > 1:
            shown = " and ".join(",".join(f[1]) for f in found)
            raise InputError(where, f"features/{feat}", f"ambiguous: {shown} could both be the {feat}; choose "
                             f"with features={{{feat!r}: '{','.join(found[0][1])}'}} (Python), or drop one from the "
                             "file")
        if found:
            out[feat] = (found[0][1], found[0][2])
        elif partial is not None:  # said, not silently dropped (Albedo.R and .G without .B)
            import warnings

            from ..errors import McreconWarning

            warnings.warn(f"{where}: features/{feat}: {', '.join(c for c in partial if c in names)} present "
                          f"without {', '.join(c for c in partial if c not in names)}: the {feat} is left out "
                          "(write all its channels, or map them: features={...})", McreconWarning, stacklevel=4)
    return out


def _read_features(exr, found, n):
    """``{feature: (mean (H, W, k), variance of the samples or None)}`` of the channels ``found``."""
    from ..core.features import as_guide, warn_feature_zeroed, within_feature_limit

    out = {}
    zeroed = 0
    sampled = np.broadcast_to(np.asarray(n) > 0, (exr.arrays[next(iter(exr.arrays))].shape[:2]))
    for feat, (chans, m2_chans) in found.items():
        m, half = exr.get(chans, f"features/{feat}")
        var = None
        if m2_chans is not None:
            m2, half2 = exr.get(m2_chans, f"features/{feat}")
            # NaN, Inf or a "no hit" sentinel (FLT_MAX) beyond the features' limit, as in a log
            bad = ~(within_feature_limit(m) & np.isfinite(m2)).all(axis=-1) & sampled
            if bad.any():
                zeroed = max(zeroed, int(bad.sum()))
                m = np.where(bad[..., None], 0.0, m)
                m2 = np.where(bad[..., None], 0.0, m2)
            m2 = np.maximum(m2, 0.0)  # a feature's moments are a guide: no damage report, no refusal
            var = _variance_from_moments(exr, m2_chans, m, m2, n, half or half2)
        else:
            bad = ~within_feature_limit(m).all(axis=-1) & sampled
            if bad.any():
                zeroed = max(zeroed, int(bad.sum()))
                m = np.where(bad[..., None], 0.0, m)
        # an empty pixel's values are ignored by the statistics; keep them finite
        m = np.where(np.isfinite(m), m, 0.0)
        out[feat] = (as_guide(feat, m), var)  # an albedo as a reflectance, as core.features reads samples
    if zeroed:
        warn_feature_zeroed(str(exr.path), zeroed, stacklevel=5, unit="pixel")
    return out

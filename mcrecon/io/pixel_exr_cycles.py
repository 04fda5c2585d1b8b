"""Blender Cycles' multilayer EXRs (``OPEN_EXR_MULTILAYER``), for the ``cycles`` layout of :mod:`.pixel_exr`.

Cycles names every channel ``<view layer>.<pass>.<component>``:
``ViewLayer.Combined.R/G/B/A`` is the image; with
``view_layer.cycles.denoising_store_passes`` on, ``ViewLayer.Denoising
Albedo.R/G/B``, ``ViewLayer.Denoising Normal.X/Y/Z`` and
``ViewLayer.Denoising Depth.Z`` hold the features; when Cycles' own
denoiser ran (``cycles.use_denoising``), ``Combined`` holds the *denoised*
image and ``ViewLayer.Noisy Image.R/G/B/A`` the raw one.  A denoised image
has no sampling noise left to estimate, and its errors are correlated
across pixels: the noisy image is the input, always.  Cycles writes the
samples per pixel as the header attribute ``cycles.<view layer>.samples``
(text, e.g. ``'16'``; with adaptive sampling the most any pixel took).

One render holds each pixel's mean and features, but no variance: Cycles
keeps no second moment.  The variance comes from several renders of the
frame with different seeds (:mod:`.seed_sets`).
"""

from __future__ import annotations

import re

from ..errors import InputError, the_one

__all__ = ["cycles_layers", "cycles_mean_channels", "cycles_count_attributes", "COMBINED", "NOISY"]

#: The pass of the image, and the pass of the raw image when Cycles denoised it.
COMBINED, NOISY = "Combined", "Noisy Image"


def cycles_layers(names) -> list[str]:
    """The view layers L with ``L.Combined.R/G/B`` among ``names`` (sorted)."""
    names = set(names)
    out = []
    for n in names:
        m = re.fullmatch(r"(.+)\.Combined\.R", n)
        if m and {f"{m.group(1)}.{COMBINED}.{c}" for c in "GB"} <= names:
            out.append(m.group(1))
    return sorted(out)


def cycles_mean_channels(names, where: str, mean=None) -> tuple[str, tuple[str, ...], bool]:
    """``(view layer, mean channels, denoised)`` of a Cycles EXR.

    The ``Noisy Image`` pass when present (Cycles denoised: ``Combined``
    is then refused as a mean, even when asked for), else ``Combined``.
    ``mean``: channels the caller chose (a view layer among several).
    """
    names = set(names)
    layers = cycles_layers(names)
    if mean is not None:
        layer = next((lay for lay in layers if mean[0].startswith(lay + ".")), "")
        noisy = tuple(f"{layer}.{NOISY}.{c}" for c in "RGB")
        if set(noisy) <= names and any(f".{COMBINED}." in c for c in mean):
            raise InputError(where, "mean", f"{','.join(mean)} is the image Cycles denoised; the raw image is "
                             f"{','.join(noisy)} (the input: a denoised image has no noise left to estimate)")
        return layer or "", tuple(mean), set(noisy) <= names
    layer = the_one(where, "mean", layers,
                    none="no Cycles image (VIEWLAYER.Combined.R/G/B, from an OPEN_EXR_MULTILAYER render); channels "
                         f"present: {', '.join(sorted(names)[:40])}",
                    several="several view layers ({found}): choose one with --mean "
                            "'{first}.Combined.R,{first}.Combined.G,{first}.Combined.B'")
    noisy = tuple(f"{layer}.{NOISY}.{c}" for c in "RGB")
    if set(noisy) <= names:
        return layer, noisy, True
    return layer, tuple(f"{layer}.{COMBINED}.{c}" for c in "RGB"), False


def cycles_count_attributes(header) -> tuple[str, ...]:
    """The header attributes ``cycles.<view layer>.samples`` Cycles writes (sorted)."""
    return tuple(sorted(k for k in header if re.fullmatch(r"cycles\..+\.samples", str(k))))

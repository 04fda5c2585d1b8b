"""Images: EXR (float32, any channels, names kept), PNG previews, false colour.

HDR is the norm: EXR files hold the radiance as computed, never clipped
or rescaled.  Only the PNG previews are tone mapped (exposure, then the
sRGB curve, then clipped to [0, 1] for display).
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import InputError, McreconWarning
from ..samples import FLOAT32_MAX
from ._atomic import atomic_path

__all__ = ["write_exr", "read_exr", "tonemap_srgb", "write_png_preview", "write_false_colour"]


def _as_hwc(img, where) -> np.ndarray:
    arr = np.asarray(img)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3 or arr.shape[0] < 1 or arr.shape[1] < 1 or arr.shape[2] < 1:
        raise InputError(str(where), "image", f"shape {arr.shape}, expected (H, W) or (H, W, C)")
    if arr.dtype.kind not in "fiub":
        raise InputError(str(where), "image", f"dtype {arr.dtype}, expected a real dtype")
    return arr


def write_exr(path, image, *, channels: Sequence[str] | None = None) -> Path:
    """Write an (H, W, C) image as a float32 EXR, atomically.

    Parameters
    ----------
    path : path-like
    image : array_like, shape (H, W) or (H, W, C)
    channels : sequence of str, optional
        Channel names; default R, G, B for 3 channels, Y for 1, else C0, C1...
        Their order is kept in the header attribute ``mcrecon_channels``.
    """
    import OpenEXR

    path = Path(path)
    img = _as_hwc(image, path)
    c = img.shape[2]
    if channels is None:
        channels = {1: ("Y",), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}.get(c, tuple(f"C{i}" for i in range(c)))
    channels = tuple(str(x) for x in channels)
    if len(channels) != c or len(set(channels)) != c:
        raise InputError(str(path), "channels", f"{channels}: expected {c} distinct names")
    if img.dtype.kind == "f" and img.dtype.itemsize > 4:
        # a float32 EXR cannot hold finite values beyond +-3.4e38: they become +-Inf (said once,
        # with the count; never rescaled -- the radiance is the user's)
        over = np.count_nonzero(np.isfinite(img) & (np.abs(img) > FLOAT32_MAX))
        if over:
            warnings.warn(f"{path}: {over} finite value(s) beyond float32's range (|x| > 3.4e38) are stored as "
                          "+-Inf: the EXR holds float32; scale the renderer's units to keep them",
                          McreconWarning, stacklevel=2)
    with np.errstate(over="ignore"):
        data = {name: np.ascontiguousarray(img[..., i], dtype=np.float32) for i, name in enumerate(channels)}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
              "mcrecon_channels": ",".join(channels)}
    with atomic_path(path, suffix=path.suffix) as tmp, OpenEXR.File(header, data) as f:
        f.write(tmp)
    return path


def read_exr(path) -> tuple[np.ndarray, tuple[str, ...]]:
    """Read an EXR: (H, W, C) float32 image and its channel names.

    The channel order written by :func:`write_exr` is restored; for other
    files R, G, B, A come first, then the rest alphabetically.
    """
    import OpenEXR

    path = Path(path)
    if not path.exists():
        raise InputError(str(path), "file", "does not exist")
    try:
        f = OpenEXR.File(str(path), separate_channels=True)
        chans = f.channels()
        header = f.header()
    except Exception as exc:
        raise InputError(str(path), "file", f"not a readable EXR image ({exc})") from None
    names = list(chans.keys())
    order = header.get("mcrecon_channels")
    if isinstance(order, str) and sorted(order.split(",")) == sorted(names):
        names = order.split(",")
    else:
        first = [n for n in ("R", "G", "B", "A") if n in names]
        names = first + sorted(n for n in names if n not in first)
    img = np.stack([np.asarray(chans[n].pixels, dtype=np.float32) for n in names], axis=-1)
    return img, tuple(names)


def tonemap_srgb(image, *, exposure: float = 0.0) -> np.ndarray:
    """Display values in [0, 1]: scale by 2**exposure, sRGB curve, clip.

    Only for previews; never applied to data that is saved as EXR.
    """
    x = np.asarray(image, dtype=np.float64) * (2.0 ** float(exposure))
    x = np.nan_to_num(x, nan=0.0, posinf=1.0, neginf=0.0)
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def _save_png(path: Path, rgb8: np.ndarray):
    from PIL import Image

    with atomic_path(path, suffix=path.suffix) as tmp:
        Image.fromarray(rgb8).save(tmp, format="PNG")
    return path


def write_png_preview(path, image, *, exposure: float = 0.0) -> Path:
    """An 8-bit sRGB PNG preview of an HDR image (1, 3 or 4+ channels: first three shown)."""
    path = Path(path)
    img = _as_hwc(image, path)
    if img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    elif img.shape[2] == 2:
        img = np.concatenate([img, np.zeros_like(img[..., :1])], axis=2)
    img = img[..., :3]
    rgb8 = np.round(tonemap_srgb(img, exposure=exposure) * 255.0).astype(np.uint8)
    return _save_png(path, rgb8)


def write_false_colour(path, scalar, *, cmap: str = "viridis", vmin: float | None = None,
                       vmax: float | None = None, log: bool = False) -> Path:
    """A false-colour PNG of a scalar map (sample density, selected scale...).

    ``vmin``/``vmax`` default to the finite data's range; ``log`` maps
    log10 of positive values.  Non-finite entries are drawn black.
    """
    from matplotlib import colormaps

    path = Path(path)
    a = np.asarray(scalar, dtype=np.float64)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim != 2:
        raise InputError(str(path), "map", f"shape {a.shape}, expected (H, W)")
    if log:
        with np.errstate(divide="ignore", invalid="ignore"):
            a = np.where(a > 0, np.log10(a), np.nan)
    finite = np.isfinite(a)
    lo = float(np.min(a[finite])) if vmin is None and finite.any() else float(vmin if vmin is not None else 0.0)
    hi = float(np.max(a[finite])) if vmax is None and finite.any() else float(vmax if vmax is not None else 1.0)
    if log:
        lo = np.log10(vmin) if vmin is not None else lo
        hi = np.log10(vmax) if vmax is not None else hi
    span = hi - lo if hi > lo else 1.0
    t = np.clip((np.where(finite, a, lo) - lo) / span, 0.0, 1.0)
    rgb = colormaps[cmap](t)[..., :3]
    rgb[~finite] = 0.0
    return _save_png(path, np.round(rgb * 255).astype(np.uint8))

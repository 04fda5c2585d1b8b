"""Images: EXR (float32, any channels, names kept), PNG previews, false colour.

HDR is the norm: EXR files hold the radiance as computed, never clipped
or rescaled.  Only the PNG previews are tone mapped (exposure, then the
sRGB curve, then clipped to [0, 1] for display).
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import sys
import tempfile
import threading
import warnings
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import InputError, McreconWarning
from ..core.samples import FLOAT32_MAX
from ._atomic import atomic_path
from ..core.display import tonemap_srgb

__all__ = ['write_exr', 'read_exr', 'write_png_preview', 'write_false_colour']

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


#: The first four bytes of every OpenEXR file.
EXR_MAGIC = b"\x76\x2f\x31\x01"


_FD_LOCK = threading.Lock()


@contextlib.contextmanager
def _quiet_fds():
    """Send what C/C++ code prints to file descriptors 1 and 2 into a temporary file while inside.

    The OpenEXR library prints its own lines about a damaged file (to
    stdout and stderr) before it raises; mcrecon says it in one line.
    Yields the file, whose text is the library's words (for the message).
    """
    saved = []
    # one at a time: two threads swapping fds 1/2 would restore each other's sinks; the binding may
    # also print through Python's sys.stdout/sys.stderr, kept apart and added to the sink at the end
    py_out = io.StringIO()
    with _FD_LOCK, tempfile.TemporaryFile(mode="w+b") as sink, contextlib.redirect_stdout(py_out), \
            contextlib.redirect_stderr(py_out):
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(AttributeError, ValueError, OSError):
                stream.flush()
        try:
            for fd in (1, 2):
                try:
                    saved.append((fd, os.dup(fd)))
                except OSError:  # no such descriptor (a daemon): nothing to silence
                    continue
                os.dup2(sink.fileno(), fd)
            yield sink
        finally:
            _flush_c_streams()  # what the library printed is still in libc's buffers: into the sink with it
            if py_out.getvalue():
                sink.seek(0, os.SEEK_END)
                sink.write(py_out.getvalue().encode(errors="replace"))
            for fd, copy in saved:
                os.dup2(copy, fd)
                os.close(copy)


def _flush_c_streams() -> None:
    """fflush(NULL): C's (and C++'s, synced with them) buffered output reaches its file descriptor now."""
    import ctypes

    with contextlib.suppress(OSError, AttributeError, TypeError):
        ctypes.CDLL(None).fflush(None)


def _exr_failure(path: Path, exc: Exception, said: bytes) -> InputError:
    """What is true about an EXR that OpenEXR could not read (its own error text misleads)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(4)
    except OSError as e:
        return InputError(str(path), "file", f"cannot be read ({e.strerror or e})")
    if head != EXR_MAGIC:
        what = "empty" if not head else "no OpenEXR magic number"
        return InputError(str(path), "file", f"not an OpenEXR file ({what}); give an .exr image")
    lines = [ln.strip() for ln in said.decode(errors="replace").splitlines() if ln.strip()]
    found = (re.search(r"\((EXR_ERR_\w+)\)\s*(.*)", ln) for ln in lines)
    detail = next((f"{m.group(1)}: {m.group(2)}" for m in found if m), None)
    return InputError(str(path), "file", "truncated or corrupt OpenEXR file ("
                      + (detail or " ".join(str(exc).split())) + "); write it again")


def open_exr(path) -> tuple[dict, dict, dict]:
    """The channels of an EXR as ``{name: array}``, their ``{name: (xSampling, ySampling)}`` and its header.

    Every input EXR is opened here: a missing, truncated or corrupt file,
    or one that is no EXR, is one :class:`InputError` naming it, and the
    OpenEXR library's own output is kept off stdout and stderr.  A
    multi-part file is warned (:func:`open_exr_parts` says it instead).
    """
    arrays, sampling, header, parts = open_exr_parts(path)
    if parts is not None:
        import warnings

        from ..errors import McreconWarning

        warnings.warn(f"{path}: {parts}", McreconWarning, stacklevel=2)
    return arrays, sampling, header


def open_exr_parts(path) -> tuple[dict, dict, dict, str | None]:
    """:func:`open_exr` and, for a multi-part file, what its other parts hold that is not read (else None):
    a reader that may yet refuse the file says it in its one line, not in a warning before it."""
    import OpenEXR

    path = Path(path)
    if not path.exists():
        raise InputError(str(path), "file", "does not exist")
    with _quiet_fds() as sink:
        f = chans = None
        others = []
        try:
            f = OpenEXR.File(str(path), separate_channels=True)
            chans = f.channels()
            arrays = {name: np.asarray(ch.pixels) for name, ch in chans.items()}
            sampling = {name: (int(ch.xSampling), int(ch.ySampling)) for name, ch in chans.items()}
            header = dict(f.header())
            others = [sorted(part.channels) for part in (getattr(f, "parts", None) or [])[1:]]
            exc = None
        except Exception as e:  # noqa: BLE001 - OpenEXR raises bare RuntimeErrors and others
            exc = e
            exc.__traceback__ = None  # nothing keeps the half-read file alive past the silenced region
        del f, chans  # the library may still print as it closes the file
        _flush_c_streams()
        sink.seek(0)
        said = sink.read()
    if exc is not None:
        raise _exr_failure(path, exc, said) from None
    parts = None
    if others:  # a multi-part file: what lies in the other parts (a renderer's feature part) is not read
        shown = "; ".join(", ".join(c[:6]) + (", ..." if len(c) > 6 else "") for c in others)
        parts = (f"{len(others) + 1} parts; only the first is read, not the channels of the others ({shown}): "
                 "write them into the first part to use them")
    return arrays, sampling, header, parts


def subsampled(path, sampling: dict, names) -> None:
    """Refuse channels among ``names`` stored subsampled (x/ySampling > 1): mcrecon reads full-resolution
    channels only (one value per pixel)."""
    sub = [n for n in names if sampling.get(n, (1, 1)) != (1, 1)]
    if sub:
        xs, ys = sampling[sub[0]]
        raise InputError(str(path), f"channel {sub[0]!r}", f"subsampled (xSampling {xs}, ySampling {ys})"
                         + (f", as are {', '.join(sub[1:])}" if len(sub) > 1 else "")
                         + ": mcrecon reads one value per pixel; write the channel at full resolution")


def read_exr(path) -> tuple[np.ndarray, tuple[str, ...]]:
    """Read an EXR: (H, W, C) float32 image and its channel names.

    The channel order written by :func:`write_exr` is restored; for other
    files R, G, B, A come first, then the rest alphabetically.
    """
    path = Path(path)
    chans, sampling, header = open_exr(path)
    names = list(chans.keys())
    if not names:
        raise InputError(str(path), "channels", "none: the EXR holds no image")
    subsampled(path, sampling, names)
    order = header.get("mcrecon_channels")
    if isinstance(order, str) and sorted(order.split(",")) == sorted(names):
        names = order.split(",")
    else:
        first = [n for n in ("R", "G", "B", "A") if n in names]
        names = first + sorted(n for n in names if n not in first)
    img = np.stack([np.asarray(chans[n], dtype=np.float32) for n in names], axis=-1)
    return img, tuple(names)


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
                       vmax: float | None = None, log: bool = False, title: str | None = None) -> Path:
    """A false-colour PNG of a scalar map (sample density, selected scale...).

    ``vmin``/``vmax`` default to the finite data's range; ``log`` maps
    log10 of positive values.  Non-finite entries are drawn black.

    Without ``title`` the PNG has one pixel per map pixel (a layer the HTML
    viewer stacks on the image).  With it, the PNG is a figure to read on
    its own: the map, the title with the value range (or the one value of
    a constant map, drawn mid-scale, not at the bottom colour) and a colour
    bar, since colour alone says nothing of the values.
    """
    from matplotlib import colormaps

    path = Path(path)
    a = np.asarray(scalar, dtype=np.float64)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim != 2:
        raise InputError(str(path), "map", f"shape {a.shape}, expected (H, W)")
    if title is not None:
        return _false_colour_figure(path, a, title=str(title), cmap=cmap, vmin=vmin, vmax=vmax, log=log)
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


def _false_colour_figure(path: Path, a: np.ndarray, *, title: str, cmap: str, vmin, vmax, log: bool) -> Path:
    """The titled figure of :func:`write_false_colour`: map, colour bar, value range."""
    from matplotlib import colormaps, colors
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    shown = np.where(a > 0, a, np.nan) if log else a
    finite = np.isfinite(shown)
    data_lo = float(np.min(shown[finite])) if finite.any() else None
    data_hi = float(np.max(shown[finite])) if finite.any() else None
    lo = float(vmin) if vmin is not None else (data_lo if data_lo is not None else (1e-3 if log else 0.0))
    hi = float(vmax) if vmax is not None else (data_hi if data_hi is not None else 1.0)
    if data_lo is None:
        what = "no finite value"
    elif data_lo == data_hi:
        what = f"every pixel {data_lo:.6g}"
    else:
        what = f"{data_lo:.4g} to {data_hi:.4g}"
    if not hi > lo:  # a constant map: mid-scale, on a bar around its value
        pad = 0.5 * max(abs(lo), 1.0)
        lo, hi = (lo / 10.0, hi * 10.0) if log and lo > 0 else (lo - pad, hi + pad)
    bad = int((~np.isfinite(a)).sum() + (int((a <= 0).sum()) if log else 0))
    if bad:
        what += f"; {bad} pixel(s) " + ("not positive or not finite" if log else "not finite") + " (black)"
    h, w = a.shape
    width_in = 6.0
    map_h = min(max(width_in * 0.82 * h / w, 1.5), 9.0)
    fig = Figure(figsize=(width_in, map_h + 0.9), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    cm = colormaps[cmap].with_extremes(bad="black")
    norm = colors.LogNorm(lo, hi) if log else colors.Normalize(lo, hi)
    im = ax.imshow(np.ma.masked_invalid(shown), cmap=cm, norm=norm, interpolation="nearest")
    ax.set_title(f"{title}: {what}", fontsize=10)
    ax.set_xlabel(f"x (pixels, {w} wide)", fontsize=8)
    ax.set_ylabel(f"y (pixels, {h} high)", fontsize=8)
    ax.tick_params(labelsize=7)
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04).ax.tick_params(labelsize=7)  # as high as the map
    fig.tight_layout()
    with atomic_path(path, suffix=path.suffix) as tmp:
        fig.savefig(tmp, format="png")
    return path

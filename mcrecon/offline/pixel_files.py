"""Pixel-statistics files as reconstruction sources: one EXR, or a half-buffer pair of two.

``mcrecon.reconstruct("frame.exr", method=...)`` and
``mcrecon.reconstruct(("a.exr", "b.exr"), method=...)`` read the files
(:func:`mcrecon.io.read_pixel_stats_exr`, :func:`mcrecon.io.read_half_buffer_exrs`)
into pixel statistics or :class:`~mcrecon.core.halves.Halves`, and the
image comes back in the file's output colours
(:meth:`~mcrecon.io.pixel_exr.PixelStatsEXR.output_image`).  A method whose
options need what such statistics lack (the samples, a sample range) runs
with the options it declares for them
(:func:`mcrecon.methods.supply.statistics_fallback`), with a warning,
when the caller did not choose those options.
"""

from __future__ import annotations

import dataclasses
import os
import warnings

from ..errors import InputError, McreconWarning
from ..methods.supply import Supply, statistics_fallback
from .inputs import check_method_supply

__all__ = ["is_pixel_file_source", "PixelFileSource", "read_pixel_file_source"]


def _is_exr(x) -> bool:
    from ..io.pixel_exr import PixelStatsEXR

    return isinstance(x, PixelStatsEXR) or (isinstance(x, (str, os.PathLike)) and
                                             os.fspath(x).lower().endswith(".exr"))


def is_pixel_file_source(source) -> bool:
    """Whether ``source`` is a pixel-statistics EXR (a path or a read :class:`PixelStatsEXR`) or a pair of them."""
    if isinstance(source, (tuple, list)):
        return len(source) == 2 and all(_is_exr(x) for x in source)
    return _is_exr(source)


@dataclasses.dataclass(frozen=True, eq=False)
class PixelFileSource:
    """What a pixel-statistics file source gives: the method to run, its input, the files read, a note.

    Attributes
    ----------
    method : Method
        The method given, or rebuilt with the options it declares for pixel
        statistics (``note`` then says so).
    source : PixelStats or Halves
        The file's statistics, or the pair's halves.
    files : tuple of PixelStatsEXR
        One, or the pair's two.
    what : str
        How messages name the files.
    note : str or None
    """

    method: object
    source: object
    files: tuple
    what: str
    note: str | None = None

    @property
    def channels(self) -> tuple:
        """Channel names of the output image (:meth:`output_image`)."""
        return tuple(self.files[0].output_channels)

    def output_image(self, image):
        """A reconstruction of the statistics in the file's output colours (float64)."""
        return self.files[0].output_image(image)


def read_pixel_file_source(source, method, *, options: dict | None = None) -> PixelFileSource:
    """Read a pixel-statistics EXR or a pair of them for ``method``; refuse, before reading, what it cannot take.

    ``options`` are those of :func:`mcrecon.io.read_pixel_stats_exr`
    (``layout``, ``mean``, ``variance``, ``second_moment``, ``variance_of``,
    ``count``, ``spp``, ``features``), for both files of a pair.
    """
    from ..core.halves import as_halves
    from ..io.pixel_exr import PixelStatsEXR, read_half_buffer_exrs, read_pixel_stats_exr

    options = dict(options or {})
    pair = isinstance(source, (tuple, list))
    items = tuple(source) if pair else (source,)
    names = [str(x.path) if isinstance(x, PixelStatsEXR) else os.fspath(x) for x in items]
    what = f"this half-buffer pair ({names[0]} / {names[1]})" if pair else f"a pixel-statistics EXR ({names[0]})"
    # what the method cannot take is refused before the files are read
    before = Supply(what, halves=pair, has_range=False, features=("?",), surface="files")
    fallback = statistics_fallback(method, before)
    if fallback is not None:
        method, note = fallback
    else:
        note = None
    check_method_supply(method, before)
    if options and any(isinstance(x, PixelStatsEXR) for x in items):
        raise InputError(names[0], "exr_options", "the files are read already: give the read options to "
                         "mcrecon.io.read_pixel_stats_exr, or give paths")
    if all(isinstance(x, PixelStatsEXR) for x in items):
        files = items
    elif pair:
        files = read_half_buffer_exrs(items[0], items[1], **options)
    else:
        files = (read_pixel_stats_exr(items[0], **options),)
    if pair:
        got = as_halves((files[0].stats, files[1].stats), what)
        features = tuple(got.a.feature_names)
    else:
        got = files[0].stats
        features = tuple(got.feature_names)
    check_method_supply(method, dataclasses.replace(before, features=features))
    if note is not None:  # after the input is read: a refused input gets its one error line only
        warnings.warn(note, McreconWarning, stacklevel=3)
    return PixelFileSource(method, got, tuple(files), what, note)

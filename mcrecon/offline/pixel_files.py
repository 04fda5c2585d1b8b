"""Pixel-statistics files as reconstruction sources: one EXR, a half-buffer pair of two, or a seed set.

``mcrecon.reconstruct("frame.exr", method=...)``,
``mcrecon.reconstruct(("a.exr", "b.exr"), method=...)`` and
``mcrecon.reconstruct("shot.seed*.exr", method=...)`` (a glob, or a list of
three or more paths: K renders of one frame with different seeds,
:func:`mcrecon.io.seed_sets.read_seed_set`) read the files
(:func:`mcrecon.io.read_pixel_stats_exr`,
:func:`mcrecon.io.pixel_exr.read_half_buffer_exrs`) into pixel statistics
or :class:`~mcrecon.core.halves.Halves`, and the image comes back in the
file's output colours
(:meth:`~mcrecon.io.pixel_exr.PixelStatsEXR.output_image`).  A method whose
options need what such statistics lack (the samples, a sample range) runs
with the options it declares for them
(:func:`mcrecon.methods.supply.statistics_fallback`), with a warning,
when the caller did not give those options.  One file of means without a
variance (a Cycles render) serves only the methods that read the means
alone (a method class's ``reads_variance`` False); two such files are a seed set of two,
not a half-buffer pair.  :func:`is_pixel_file_source`
is the one test of "is this an EXR input" (the command line and the batch
ask it too); :func:`command_line` makes the messages name flags.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import inspect
import os
import warnings
from collections.abc import Mapping

from ..errors import InputError, McreconWarning
from ..io.pixel_exr import is_pixel_exr, is_pixel_file_source
from ..methods.supply import Supply, statistics_fallback
from .inputs import check_method_supply

__all__ = ["is_pixel_file_source", "PixelFileSource", "read_pixel_file_source", "command_line",
           "check_exr_options"]

#: Whether the reconstruction was asked for on the command line: its messages then name flags
#: (``--candidates``), not keywords (``candidates=``); set by :func:`command_line`.
_CLI = contextvars.ContextVar("mcrecon_pixel_files_cli", default=False)


@contextlib.contextmanager
def command_line():
    """Within it, refusals of pixel-statistics sources name the command line's flags (``mcrecon reconstruct``)."""
    token = _CLI.set(True)
    try:
        yield
    finally:
        _CLI.reset(token)




def _read_option_names() -> tuple:
    from ..io.pixel_exr import read_pixel_stats_exr

    return tuple(p.name for p in inspect.signature(read_pixel_stats_exr).parameters.values()
                 if p.kind is inspect.Parameter.KEYWORD_ONLY)


def check_exr_options(options, where: str = "reconstruct") -> dict:
    """``options`` as a dict of :func:`mcrecon.io.read_pixel_stats_exr`'s keywords, or one
    :class:`InputError` line naming ``exr_options`` and the valid keys."""
    valid = _read_option_names()
    if options is None:
        return {}
    if not isinstance(options, Mapping):
        raise InputError(where, "exr_options", f"got {type(options).__name__}; expected a dict of read "
                         f"options, keys among {', '.join(valid)}")
    unknown = sorted(str(k) for k in options if k not in valid)
    if unknown:
        raise InputError(where, "exr_options", f"unknown key {unknown[0]!r}; valid: {', '.join(valid)}")
    return dict(options)


def _check_pair(source, cli: bool) -> tuple:
    """The items of a pair of pixel-statistics files, or one line saying what a pair is."""
    items = tuple(source)
    field = "--half-buffer" if cli else "source"
    accepted = ("a half-buffer pair is two EXR paths (\"a.exr\", \"b.exr\") or two PixelStats "
                "(stats_a, stats_b)")
    if len(items) != 2:
        raise InputError("reconstruct", field, f"got {len(items)} item(s); {accepted}")
    for i, x in enumerate(items):
        if not is_pixel_exr(x):
            shown = os.fspath(x) if isinstance(x, (str, os.PathLike)) else type(x).__name__
            raise InputError("reconstruct", f"{field}[{i}]" if not cli else field, f"{shown} is not an EXR (a "
                             f"path ending in .exr) while the other item is; {accepted}")
    return items


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
    files : tuple of PixelStatsEXR or SeedSetEXR
        One, the pair's two, or a seed set's one SeedSetEXR.
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


def read_pixel_file_source(source, method, *, options: dict | None = None,
                           fireflies: str = "none") -> PixelFileSource:
    """Read a pixel-statistics EXR or a pair of them for ``method``; refuse, before reading, what it cannot take.

    ``options`` are those of :func:`mcrecon.io.read_pixel_stats_exr`
    (``layout``, ``mean``, ``variance``, ``second_moment``, ``variance_of``,
    ``count``, ``spp``, ``features``), for both files of a pair.
    ``fireflies``: :func:`mcrecon.reconstruct`'s mode; ``'cascade'``
    splits individual samples, which the files do not hold.  Messages name
    the options as :func:`command_line` says the caller gave them.
    """
    from ..core.halves import as_halves
    from ..io.pixel_exr import PixelStatsEXR, read_half_buffer_exrs, read_pixel_stats_exr
    from ..io.seed_sets import is_glob_pattern, seed_set_paths

    cli = _CLI.get()
    options = check_exr_options(options)
    if seed_set_paths(source) is not None:
        return _read_seed_set(source, method, options, fireflies, cli)
    pair = isinstance(source, (tuple, list))
    items = _check_pair(source, cli) if pair else (source,)
    if pair and any(is_glob_pattern(x) for x in items):
        raise InputError(os.fspath(next(x for x in items if is_glob_pattern(x))), "--half-buffer" if cli else "source",
                         "a glob is a seed set, which gives its own half buffers: give it alone")
    names = [str(x.path) if isinstance(x, PixelStatsEXR) else os.fspath(x) for x in items]
    what = f"this half-buffer pair ({names[0]} / {names[1]})" if pair else f"a pixel-statistics EXR ({names[0]})"
    if fireflies == "cascade":
        raise InputError(names[0], "--fireflies" if cli else "fireflies",
                         ("--fireflies cascade" if cli else "fireflies='cascade'") + " splits individual samples, "
                         "which pixel statistics no longer hold; give a sample log"
                         + (" or --fireflies none" if cli else " or a SampleSet, or fireflies='none'"))
    # what the method cannot take is refused before the files are read
    before = Supply(what, halves=pair, has_range=False, features=("?",), surface="files", cli=cli)
    given = method
    fallback = statistics_fallback(method, before)
    if fallback is not None:
        method, note = fallback
    else:
        note = None
    try:
        check_method_supply(method, before)
    except InputError as refusal:  # two renders' means (Cycles) are a seed set of two, for any method
        if not pair or not all(isinstance(x, (str, os.PathLike)) for x in items):
            raise
        try:
            means_only = not read_pixel_stats_exr(items[0], **options).has_variance
        except InputError:
            raise refusal from None  # the method's refusal, not the unreadable file's
        if not means_only:
            raise
        return _read_seed_set(list(items), given, options, fireflies, cli)
    if options and any(isinstance(x, PixelStatsEXR) for x in items):
        raise InputError(names[0], "exr_options", "the files are read already: give the read options to "
                         "mcrecon.io.read_pixel_stats_exr, or give paths")
    if all(isinstance(x, PixelStatsEXR) for x in items):
        files = items
    elif pair:
        files = read_half_buffer_exrs(items[0], items[1], **options)
    else:
        files = (read_pixel_stats_exr(items[0], **options),)
    if pair and not (files[0].has_variance and files[1].has_variance):  # two renders' means: a seed set of two
        return _read_seed_set(list(items), given, options, fireflies, cli)
    if not files[0].has_variance:
        _refuse_means_only(method, files[0], cli)
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


def _refuse_means_only(method, file, cli: bool) -> None:
    """One render's means without a variance: refused, naming the fix, for a method that reads the variance."""
    if not method.reads_variance:  # a method of the means alone (the pixel mean)
        return
    from ..methods import available_methods, method_class

    means = [n for n in available_methods() if not method_class(n).reads_variance]
    seeds = "'shot.seed*.exr'" if cli else "mcrecon.reconstruct('shot.seed*.exr', ...)"
    held = "one cycles render holds" if file.layout == "cycles" else \
        f"means alone ({'--mean' if cli else 'mean='} without a variance) hold"
    raise InputError(str(file.path), "variance", f"{held} each pixel's mean and features "
                     f"but no variance, which {method.name} needs; render the frame K >= 2 times with different "
                     f"seeds and pass the set ({seeds}): their spread is the variance and their two groups the half "
                     f"buffers" + (f" (or use {' or '.join(means)}, which read the means alone)" if means else ""))


def _read_seed_set(source, method, options: dict, fireflies: str, cli: bool) -> PixelFileSource:
    """:func:`read_pixel_file_source` of a seed set: its halves for a method that takes half buffers,
    else the statistics of all the renders."""
    from ..io.pixel_exr import PixelStatsEXR
    from ..io.seed_sets import read_seed_set

    if isinstance(source, (list, tuple)) and any(isinstance(x, PixelStatsEXR) for x in source):
        raise InputError("reconstruct", "source", "a seed set is read from its files: give the paths (or a "
                         "glob such as 'shot.seed*.exr'), not read PixelStatsEXR")
    what = f"this seed set ({os.fspath(source) if isinstance(source, (str, os.PathLike)) else 'of renders'})"
    if fireflies == "cascade":
        raise InputError(what, "--fireflies" if cli else "fireflies", "cascade splits individual samples, which "
                         "renders' pixel means no longer hold; give a sample log, or fireflies none")
    halves = bool(method.requires.half_buffers)
    before = Supply(what, halves=halves, has_range=False, features=("?",), surface="files", cli=cli)
    fallback = statistics_fallback(method, before)
    method, note = fallback if fallback is not None else (method, None)
    check_method_supply(method, before)
    seeds = read_seed_set(source, **options)
    got = seeds.halves if halves else seeds.stats
    check_method_supply(method, dataclasses.replace(before, what=f"this seed set ({seeds.path})",
                                                    features=tuple(seeds.stats.feature_names)))
    if note is not None:
        warnings.warn(note, McreconWarning, stacklevel=4)
    return PixelFileSource(method, got, (seeds,), f"this seed set ({seeds.path})", note)

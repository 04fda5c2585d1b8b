"""Seed sets: K renders of one frame with different seeds, read as pixel statistics and half buffers.

Every production renderer (Cycles, Arnold, Karma, RenderMan, V-Ray) can
render a frame again with another seed, and most write no variance.  K
such renders give what one cannot: each pixel's K means are K independent
estimates of the same integral, so

* the mean is their average, over ``count = K x spp`` samples;
* the variance of that mean is ``s^2 / K``, with ``s^2`` the unbiased
  variance of the K render means (``ddof=1``).  It measures the error
  each render actually has, stratification included: a low-discrepancy
  sampler's (Cycles' Sobol) mean varies far less than its samples do, so
  a per-file variance of the samples (pbrt-v4's ``Variance``) would
  overstate it; the spread across renders does not, and is used for every
  layout;
* the half buffers are the means of two groups of renders: the even-
  numbered renders (in the order given, a glob's sorted) and the odd-
  numbered ones.  For an odd K the first group has one render more, so its
  count is ``(K + 1) / 2 x spp`` against ``(K - 1) / 2 x spp`` (half-buffer
  methods take halves of unequal counts).  Each half's variance of the
  mean is ``s^2 / K_half`` from the pooled ``s^2`` of all K renders (a
  half of one render has no spread of its own); a half of one sample
  (K = 2, spp = 1) gets variance 0, as statistics of one sample do;
* the features are the average of the renders' feature passes (AOVs),
  with their variance of the mean across renders the same way.

Each file is read by :func:`mcrecon.io.read_pixel_stats_exr` with the same
options (any layout: ``cycles``, ``pbrt-v4``, ``mitsuba-moment``, the
explicit mapping, ``mean=`` alone for means only); every render must have
the same size, channels, features and sample count.  The files are read
one after another into running sums (Welford), so memory holds a few
images, not K.
"""

from __future__ import annotations

import contextlib
import dataclasses
import glob
import hashlib
import os
import re
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..core.stats import PixelStats

__all__ = ["SeedSetEXR", "read_seed_set", "seed_set_paths", "is_glob_pattern", "SeedSetFrame", "seed_set_frames"]

_GLOB_MAGIC = ("*", "?", "[")


def is_glob_pattern(x) -> bool:
    """Whether ``x`` is a glob of EXRs: a path ending in ``.exr`` with ``*``, ``?`` or ``[`` that is no file
    (a name that exists is that file, literally)."""
    if not isinstance(x, (str, os.PathLike)):
        return False
    s = os.fspath(x)
    return s.lower().endswith(".exr") and any(c in s for c in _GLOB_MAGIC) and not os.path.exists(s)


def seed_set_paths(source) -> tuple | None:
    """The renders of a seed set ``source`` (None when it is none): a glob (sorted matches, maybe none), or a
    list or tuple of three or more items (two are a half-buffer pair unless the files hold no variance)."""
    if is_glob_pattern(source):
        return tuple(Path(p) for p in sorted(glob.glob(os.fspath(source))))
    if isinstance(source, (list, tuple)) and len(source) >= 3:
        return tuple(source)
    return None


@dataclasses.dataclass(frozen=True, eq=False)
class SeedSetEXR:
    """The statistics of a seed set (see the module notes), shaped like :class:`~mcrecon.io.PixelStatsEXR`.

    Attributes
    ----------
    stats : PixelStats
        Mean and variance of the mean across the renders, count K x spp.
    halves : Halves
        The means of the even- and odd-numbered renders.
    paths : tuple of Path
        The renders, in the order read.
    path : str
        How messages name the set (the glob, or the first and last file).
    layout, sources, count_source, output_channels, output_matrix
        As the first render's :class:`~mcrecon.io.PixelStatsEXR` (every
        render's agree); ``count_source`` says K and where spp came from.
    renders : int
        K.
    """

    stats: PixelStats
    halves: object
    paths: tuple
    path: str
    layout: str
    sources: dict
    count_source: str
    output_channels: tuple
    output_matrix: np.ndarray | None
    renders: int
    has_variance: bool = True

    def output_image(self, image) -> np.ndarray:
        """A reconstruction of :attr:`stats` in the output channels (float64)."""
        img = np.asarray(image, dtype=np.float64)
        return img if self.output_matrix is None else img @ self.output_matrix.T


class _Running:
    """Welford's running mean and sum of squared deviations of K images, with the two groups' sums."""

    def __init__(self):
        self.k = 0
        self.mean = self.m2 = None
        self.sums = [None, None]
        self.sizes = [0, 0]

    def add(self, x: np.ndarray, group: int) -> None:
        self.k += 1
        if self.mean is None:
            self.mean, self.m2 = x.copy(), np.zeros_like(x)
        else:
            d = x - self.mean
            self.mean += d / self.k
            self.m2 += d * (x - self.mean)
        self.sums[group] = x.copy() if self.sums[group] is None else self.sums[group] + x
        self.sizes[group] += 1

    def variance(self) -> np.ndarray:
        """The unbiased variance of one render's mean, ``s^2``."""
        return self.m2 / (self.k - 1)


def _name(paths, source) -> str:
    if isinstance(source, (str, os.PathLike)):
        return f"{os.fspath(source)} ({len(paths)} renders)"
    return f"{paths[0]} ... {paths[-1]} ({len(paths)} renders)" if len(paths) > 1 else str(paths[0])


def _check_items(items, where: str) -> tuple:
    from .pixel_exr import is_pixel_exr

    paths = []
    for x in items:
        if not is_pixel_exr(x) or not isinstance(x, (str, os.PathLike)):
            shown = os.fspath(x) if isinstance(x, (str, os.PathLike)) else type(x).__name__
            raise InputError(where, "seed set", f"{shown} is not an EXR path; a seed set is the paths (or a glob "
                             "such as 'shot.seed*.exr') of K >= 2 renders of one frame with different seeds")
        paths.append(Path(x))
    if len(paths) < 2:
        raise InputError(str(paths[0]) if paths else where, "seed set",
                         "one render: a seed set is K >= 2 renders of the frame with different seeds (their "
                         "spread is the variance); render more seeds, or give the one file alone")
    for i, p in enumerate(paths):  # the same file twice would count one render's noise as two
        for q in paths[:i]:
            same = os.path.abspath(p) == os.path.abspath(q)
            with contextlib.suppress(OSError):
                same = same or os.path.samefile(p, q)
            if same:
                raise InputError(str(p), "seed set", f"the same file as {q}: each render of a seed set is its "
                                 "own file, rendered with its own seed")
    return tuple(paths)


def _compare(first, f, where_first) -> None:
    """Refuse a render that does not match the first: size, layout, channels, features, count."""
    where = str(f.path)
    a, b = first.stats, f.stats
    if (a.height, a.width) != (b.height, b.width):
        raise InputError(where, "shape", f"{b.width}x{b.height}, but {where_first} is {a.width}x{a.height} "
                         "(width x height): a seed set's renders are of one frame")
    if first.layout != f.layout or first.sources != f.sources or first.output_channels != f.output_channels:
        show = lambda src: "; ".join(f"{k} {','.join(v) or '-'}" for k, v in src.items())  # noqa: E731 (dict: its keys)
        raise InputError(where, "channels", f"layout {f.layout}: {show(f.sources)}, but {where_first} has layout "
                         f"{first.layout}: {show(first.sources)}; write the same passes into every render")
    ma, mb = first.output_matrix, f.output_matrix
    if (ma is None) != (mb is None) or (ma is not None and not np.allclose(ma, mb, rtol=1e-6, atol=1e-9)):
        raise InputError(where, "chromaticities", f"a colour space other than {where_first}'s")
    if not np.array_equal(a.count, b.count):
        raise InputError(where, "count", f"{f.count_source}, but {where_first}: {first.count_source}; every "
                         "render of a seed set takes the same samples per pixel (only the seed differs)")


def read_seed_set(source, **options) -> SeedSetEXR:
    """Read K >= 2 renders of one frame with different seeds as statistics and half buffers.

    Parameters
    ----------
    source : str, path-like, list or tuple
        A glob (``'shot.seed*.exr'``, sorted) or the paths of the renders.
    **options
        Keywords of :func:`mcrecon.io.read_pixel_stats_exr` (``layout``,
        ``mean``, ``spp``, ``features``, ...), applied to every render; a
        numeric ``spp`` is each render's samples per pixel.

    Returns
    -------
    SeedSetEXR

    Raises
    ------
    InputError
        A glob matching nothing, fewer than two renders, a file given twice
        or two identical renders (the same seed), renders that differ in
        size, channels, features or count, anything the reader refuses in a
        render (NaN/Inf means, missing channels); each names the file and
        the field.
    """
    from ..core.halves import as_halves
    from .pixel_exr import read_pixel_stats_exr

    where = os.fspath(source) if isinstance(source, (str, os.PathLike)) else "seed set"
    items = seed_set_paths(source)
    if items is None:
        items = tuple(source) if isinstance(source, (list, tuple)) else (source,)
    if isinstance(source, (str, os.PathLike)) and not items:
        raise InputError(where, "seed set", "no file matches this glob; a seed set is K >= 2 renders of the "
                         "frame with different seeds, e.g. 'shot.seed*.exr' (quote it on the command line)")
    paths = _check_items(items, where)
    first = None
    colour, feats = _Running(), {}
    digests = {}
    for i, p in enumerate(paths):
        f = read_pixel_stats_exr(p, **options)
        x = np.asarray(f.stats.mean, dtype=np.float64)
        digest = hashlib.sha1(np.ascontiguousarray(x).tobytes()).hexdigest()
        if digest in digests:
            raise InputError(str(p), "seed set", f"the same pixels as {digests[digest]}: the two renders used the "
                             "same seed; render each with its own (Cycles: scene.cycles.seed)")
        digests[digest] = p
        if first is None:
            first = f
        else:
            _compare(first, f, str(first.path))
        colour.add(x, i % 2)
        for name, fst in f.stats.features.items():
            feats.setdefault(name, _Running()).add(np.asarray(fst.mean, dtype=np.float64), i % 2)
    k = len(paths)
    n = first.stats.count.astype(np.int64)
    channels = tuple(first.stats.channels)

    def build(mean_of, var_of, count, what):
        fs = {name: (mean_of(r), var_of(r)) for name, r in feats.items()} or None
        return PixelStats.from_moments(mean_of(colour), var_of(colour), count, channels=channels,
                                       variance_of="mean", features=fs, where=what)

    name = _name(paths, source)
    stats = build(lambda r: r.mean, lambda r: r.variance() / k, k * n, name)
    halves = []
    for g in (0, 1):
        kg = colour.sizes[g]
        one = (kg * n <= 1)[..., None]  # statistics of one sample hold no variance
        halves.append(build(lambda r, g=g, kg=kg: r.sums[g] / kg,
                            lambda r, kg=kg, one=one: np.where(one, 0.0, r.variance() / kg),
                            kg * n, f"{name}: half {'ab'[g]}"))
    sources = dict(first.sources)
    return SeedSetEXR(stats, as_halves(tuple(halves), name), paths, name, first.layout, sources,
                      f"{k} renders x {first.count_source}", tuple(first.output_channels), first.output_matrix, k)


# ------------------------------------------------------------------ frames of seed sets (batch)
@dataclasses.dataclass(frozen=True)
class SeedSetFrame:
    """One frame of :func:`seed_set_frames`: its name, the glob of its renders, and the files it matched.

    Path-like (``os.fspath`` is the glob, which :func:`mcrecon.reconstruct`
    reads as a seed set), with the ``stem`` a frame is named by and the
    ``stat`` of its newest render (a batch redoes the frame when a render
    is newer than its output).
    """

    stem: str
    pattern: str
    files: tuple

    def __fspath__(self) -> str:
        return self.pattern

    def __str__(self) -> str:
        return self.pattern

    def stat(self):
        return max((os.stat(f) for f in self.files), key=lambda st: st.st_mtime_ns)


def _pattern_regex(base: str) -> str:
    out = []
    for tok in re.findall(r"#+|\*|\?|\[[^\]]*\]|[^#*?\[]+", base):
        if tok.startswith("#"):
            out.append(f"(?P<frame>\\d{{{len(tok)}}})")
        elif tok == "*":
            out.append(".*")
        elif tok == "?":
            out.append(".")
        elif tok.startswith("["):
            out.append("[^" + tok[2:] if tok.startswith("[!") else tok)
        else:
            out.append(re.escape(tok))
    return "".join(out)


def _frame_stem(base: str, digits: str) -> str:
    """A frame's name: its file name without ``.exr`` and without the parts that match the seeds
    (``shot.0001.seed*.exr`` -> ``shot.0001``; ``shot_0001_s*.exr`` -> ``shot_0001_s``), always with the
    frame's digits (``s*_0001.exr`` -> ``s_0001``)."""
    stem = base[:-4] if base.lower().endswith(".exr") else base
    kept = [part for part in stem.split(".") if not any(c in part for c in _GLOB_MAGIC)]
    if kept and len(kept) < len(stem.split(".")) and digits in ".".join(kept):
        return ".".join(kept)
    cut = min((stem.index(c) for c in _GLOB_MAGIC if c in stem), default=len(stem))
    if digits in stem[:cut]:
        return stem[:cut].rstrip("._-")
    return re.sub(r"\*|\?|\[[^\]]*\]", "", stem).strip("._-")


def seed_set_frames(pattern, *, where: str = "--seed-sets") -> list[SeedSetFrame]:
    """The frames of a sequence of seed sets: ``'shot.####.seed*.exr'`` -> one :class:`SeedSetFrame` per
    frame number (the ``#`` run, that many digits), holding that frame's renders (the rest of the glob).

    Raises
    ------
    InputError
        No ``#`` run or more than one, ``#`` outside the file name, no glob
        for the seeds, no file matching.
    """
    s = os.fspath(pattern)
    head, base = os.path.split(s)
    runs = re.findall(r"#+", s)
    if len(runs) != 1 or "#" in head:
        raise InputError(s, where, f"{len(runs)} runs of '#' ({'in the directory' if '#' in head else 'expected one'}"
                         "): mark the frame number with one run of '#' in the file name, one per digit, and the "
                         "seed with a glob, e.g. 'shot.####.seed*.exr'")
    if not any(c in base.replace("#", "") for c in _GLOB_MAGIC) or not base.lower().endswith(".exr"):
        raise InputError(s, where, "no glob for the seeds, or not ending in .exr: e.g. 'shot.####.seed*.exr' "
                         "(#: the frame number's digits, *: the seed)")
    regex = re.compile(_pattern_regex(base))
    frames: dict[str, list] = {}
    for f in sorted(glob.glob(re.sub(r"#+", lambda m: "[0-9]" * len(m.group()), s))):
        m = regex.fullmatch(os.path.basename(f))
        if m:
            frames.setdefault(m.group("frame"), []).append(Path(f))
    if not frames:
        raise InputError(s, where, "no file matches this pattern (#: the frame number's digits, *: the seed)")
    out = []
    for digits, files in sorted(frames.items()):
        base_f = re.sub(r"#+", digits, base)
        out.append(SeedSetFrame(_frame_stem(base_f, digits), os.path.join(head, base_f), tuple(files)))
    return out

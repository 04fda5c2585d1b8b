"""Tiled offline reconstruction: a local method's untiled image, with the memory of one band of tiles at a time.

A method whose result at a pixel depends only on the inputs within
``halo`` pixels of it (:meth:`~mcrecon.methods.Method.halo`) gives, on a
tile grown by its halo (clipped at the film's edges), the untiled result
inside the tile.  :func:`reconstruct_tiles` runs it tile after tile.  From
a sample source (a log, a SampleSet: :class:`FilmReader`) it reads the
statistics of one band of tiles at a time, the band's rows grown by the
halo, from a pass over the whole source
(:func:`~mcrecon.offline.inputs.gather_inputs` with a ``window``: the
film's statistics cropped to the band, bit for bit), and cuts each tile
from them; so neither the film's statistics nor the method's working
arrays are held whole.  From statistics given in memory (pixel
statistics, a half-buffer pair) it crops them.  For methods that read
half buffers the Chan merge of the two halves is made tile by tile.

Two methods of :class:`~mcrecon.methods.Method` tile it besides its halo:
:meth:`~mcrecon.methods.Method.tile_grid`, ``(rows, columns)`` that a
grown tile's first pixel is a multiple of (kernels that work in bands of
rows from the array's first row sum in the film's order only on the
film's bands), and :meth:`~mcrecon.methods.Method.for_tiles`, the method
the tiles run, given the film's inputs: the whole-image decisions it
makes (nfor: the scale of its features) computed once for the film and
fixed in it.
"""

from __future__ import annotations

import functools
import warnings

import numpy as np

from ..core.fill import FilmRangeSum, variance_defined
from ..core.halves import Halves
from ..errors import InputError
from ..methods.base import Method, MethodInputs, RunState
from .inputs import gather_inputs

__all__ = ["tile_windows", "check_tile", "tileable_halo", "tile_inputs", "reconstruct_tiles", "FilmReader", "FilmFill",
           "film_inputs"]


def check_tile(tile, where: str = "reconstruct") -> int | None:
    """``tile`` as a positive int (None: untiled), or a one-line :class:`InputError` naming the option."""
    if tile is None:
        return None
    if isinstance(tile, bool) or not isinstance(tile, (int, np.integer)) or int(tile) < 1:
        raise InputError(where, "tile", f"{tile!r}, expected a tile side in pixels (a positive integer; "
                         "the halo comes on top of it), or None for an untiled reconstruction")
    return int(tile)


def _splits(n: int, tile: int, even: bool) -> list[tuple[int, int]]:
    if not even:  # dask.array's chunks of `tile`: the last one the remainder
        return [(a, min(n, a + tile)) for a in range(0, n, tile)]
    # ceil(n / tile) parts of equal size to a pixel, so that no thin last tile pays a whole halo
    parts = -(-n // tile)
    edges = [n * i // parts for i in range(parts + 1)]
    return list(zip(edges[:-1], edges[1:]))


def tile_windows(width: int, height: int, tile: int, halo: int, *, even: bool = True, grid=(1, 1)):
    """``(outer, inner)`` windows of the tiles of a film, each ``(y0, y1, x0, x1)`` in film pixels.

    The film is cut into ``ceil(width / tile) x ceil(height / tile)`` tiles,
    each at most ``tile`` pixels a side: of (nearly) equal size, or with
    ``even=False`` starting at multiples of ``tile`` (``dask.array``'s
    chunks, which :func:`mcrecon.distributed.map_tiles` reproduces); ``inner``
    is a tile, ``outer`` the tile grown by ``halo`` on every side and
    clipped to the film (``map_overlap``'s ``boundary="none"``), its first
    row and column then moved back to multiples of ``grid`` ``(rows,
    columns)`` (:meth:`~mcrecon.methods.Method.tile_grid`).
    """
    gy, gx = (int(g) for g in grid)
    for y0, y1 in _splits(int(height), int(tile), even):
        for x0, x1 in _splits(int(width), int(tile), even):
            outer = (max(0, (y0 - halo) // gy * gy), min(height, y1 + halo),
                     max(0, (x0 - halo) // gx * gx), min(width, x1 + halo))
            yield outer, (y0, y1, x0, x1)


class FilmReader:
    """A sample source (a log, a :class:`~mcrecon.core.samples.SampleSet`) whose inputs are read a window at a
    time: :meth:`read` is :func:`~mcrecon.offline.inputs.gather_inputs` of the window (one pass over the
    whole source, the memory of the window), the film's inputs cropped to it, bit for bit.

    What :func:`reconstruct_tiles` and a method's :meth:`~mcrecon.methods.Method.for_tiles` read the
    film through, in place of the film's :class:`~mcrecon.methods.MethodInputs`.  ``bands``: the row
    ranges ``(y0, y1)`` of the tiles, set by the driver (:meth:`planes` reads the film by them).
    """

    def __init__(self, source, method: Method, *, nonfinite: str = "drop", reference=None, where: str | None = None):
        self.source, self.method, self.nonfinite, self.reference, self.where = \
            source, method, nonfinite, reference, where
        self.width, self.height = int(source.width), int(source.height)
        self.channels = tuple(source.channels)
        self.bands = [(0, self.height)]
        #: The film's fill-in values (:class:`FilmFill`) that :meth:`read` hands to the statistics it reads
        #: (set by :func:`reconstruct_tiles`); None: each window's own.
        self.fill = None
        self.said: dict = {}   # the warnings of the reads, each said once (every read passes the whole source)
        #: The image's sanity line (:func:`~mcrecon.core.metrics.output_sanity`), added band by band as the
        #: tiles finish (:meth:`add_sanity`); None until then, or for statistics without a range.
        self.sanity = None

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.height, self.width, len(self.channels)

    def read(self, window, method: Method | None = None) -> MethodInputs:
        """The inputs of the pixels ``window`` = ``(y0, y1, x0, x1)``; half buffers come without their merge.
        ``method``: what another method (of the same samples' layout: a variant of this one) reads instead."""
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            out = gather_inputs(self.source, method or self.method, nonfinite=self.nonfinite, reference=self.reference,
                                where=self.where, merged=False, window=tuple(int(v) for v in window))
        for wn in caught:
            self.said.setdefault((wn.category, str(wn.message)), wn)
        return out if self.fill is None else self.fill.mark(out)

    def add_sanity(self, image: np.ndarray, band) -> None:
        """Add the sanity line of a finished band ``((y0, y1), first row read, its inputs)`` of ``image``."""
        from ..core.metrics import add_sanity, output_sanity

        (y0, y1), by0, sub = band
        # the colour's range of all the samples: the halves' merged
        st = sub.halves.without_features().merged() if sub.halves is not None else sub.stats
        if st is not None and st.has_range:
            self.sanity = add_sanity(self.sanity, output_sanity(image[y0:y1], st, rows=(y0 - by0, y1 - by0)))

    def planes(self, planes_of):
        """The film's planes that ``planes_of(inputs)`` makes pixel by pixel from a window's inputs.

        ``planes_of`` yields groups of (h, w) planes of the window it is
        given, each plane's pixel a function of that pixel's inputs alone.
        The film is read band by band (:attr:`bands`, without halos); the
        groups' planes go to a temporary file each, and come back one group
        at a time, as (H, W) float64 planes of the film: the memory of a
        band's inputs while reading, then of one group's film planes.
        """
        import tempfile

        with tempfile.TemporaryDirectory(prefix="mcrecon-planes-") as tmp:
            files, sizes = [], []
            for y0, y1 in self.bands:
                sub = self.read((y0, y1, 0, self.width))
                i = 0
                for g, group in enumerate(planes_of(sub)):
                    if len(sizes) <= g:
                        sizes.append(len(group))
                    for plane in group:
                        if len(files) <= i:
                            files.append(open(f"{tmp}/{i}.f64", "wb"))
                        np.ascontiguousarray(plane, dtype=np.float64).tofile(files[i])
                        i += 1
                del sub
            for f in files:
                f.close()
            i = 0
            for k in sizes:
                yield tuple(np.fromfile(f"{tmp}/{j}.f64", np.float64).reshape(self.height, self.width)
                            for j in range(i, i + k))
                i += k


def film_inputs(source, method: Method, *, nonfinite: str = "drop", reference=None, where: str | None = None):
    """What the tiles of ``source`` are read from: a :class:`FilmReader` for a sample source (a log path, a
    SampleLog, a SampleSet), else the film's inputs (:func:`~mcrecon.offline.inputs.gather_inputs`, half buffers
    without their merge) for statistics given in memory."""
    from pathlib import Path

    from ..core.halves import is_half_buffer_pair
    from ..core.stats import PixelStats

    if isinstance(source, (str, Path)):
        from ..io import read_log
        source = read_log(source)
    if not (isinstance(source, PixelStats) or is_half_buffer_pair(source)) and hasattr(source, "iter_chunks"):
        return FilmReader(source, method, nonfinite=nonfinite, reference=reference, where=where)
    return gather_inputs(source, method, nonfinite=nonfinite, reference=reference, where=where, merged=False)


def tileable_halo(method: Method, width: int, height: int, where: str, *, inputs: MethodInputs | None = None) -> int:
    """The method's halo on a ``width`` x ``height`` film, or a one-line refusal saying why tiles would change
    the image: the one refusal of every tiled path (``reconstruct --tile``, :func:`reconstruct_tiles`,
    :func:`mcrecon.distributed.reconstruct_tiled`).

    Refused: a whole-image method (no finite :meth:`~mcrecon.methods.Method.halo`); with ``inputs`` (tiles
    of statistics) a method that filters the individual samples, and pixels without a sample (in one of
    the halves for half buffers), which take the value of the nearest sampled pixel, however far.  Without
    ``inputs`` the caller gives each tile its own samples (a sample-filtering method's tiles).
    """
    halo = method.halo(int(width), int(height))
    if halo is None:
        raise InputError(where, "tile", f"{method.name}'s result at a pixel depends on the whole image (it declares "
                         "no finite halo: Method.halo), so tiles would change it; reconstruct it untiled "
                         "(no tile option)")
    if inputs is None:
        return int(halo)
    req = method.requires
    halves = inputs.halves is not None if isinstance(inputs, MethodInputs) else req.half_buffers
    if req.samples and not (req.half_buffers and halves):
        raise InputError(where, "tile", f"{method.name} filters the individual samples, which the tiles of "
                         "offline statistics do not hold; tile it with mcrecon.distributed.reconstruct_tiled "
                         "(each tile streams its samples), or reconstruct untiled")
    if isinstance(inputs, FilmReader):   # the samples per pixel are counted band by band (_check_counts)
        return int(halo)
    _check_counts(inputs, where)
    return int(halo)


def _check_counts(inputs: MethodInputs, where: str, rows=None) -> None:
    """Refuse pixels (of ``rows`` ``(y0, y1)`` of ``inputs``, or all) without a sample, or without one in a
    half: their fill-in takes the nearest sampled pixel's value, however far
    (:func:`~mcrecon.core.fill.fill_empty_pixels`).  A pixel with one sample (in a half, or in all) borrows a
    variance from its 3 x 3 neighbours, else the film's average: the tiles are given the film's
    (:class:`FilmFill`)."""
    cut = (lambda a: a) if rows is None else (lambda a: a[rows[0]:rows[1]])  # noqa: E731
    if inputs.halves is not None:
        few = int(np.count_nonzero(np.minimum(cut(inputs.halves.a.count), cut(inputs.halves.b.count)) < 1))
        what = "without a sample in one of its halves"
    else:
        few = int(np.count_nonzero(cut(inputs.stats.count) < 1))
        what = "without a sample"
    if few:
        band = "" if rows is None else " in a band of tiles"
        raise InputError(where, "tile", f"{few} pixel(s){band} {what}: their fill-in takes the value of the "
                         "nearest sampled pixel, however far, so tiles would not reproduce the untiled result; "
                         "reconstruct untiled (no tile option), or give every pixel a sample (one in each half)")


class FilmFill:
    """The film's image-wide values of the variance fill-in (:func:`~mcrecon.core.fill.mean_variance_policy`:
    the average and range of the sample variances of pixels with two samples or more) of each of the tiles'
    statistics (each half, or the pixel statistics, and each of their features), which :meth:`mark` hands to
    a tile's (``PixelStats.film_fill``), so that a tile fills its pixels with one sample as the film does.

    Computed once, when a tile first fills a pixel: from the film's inputs, or from a :class:`FilmReader`
    band by band (one more read of each band, in the film's order: bit for bit the film's values)."""

    def __init__(self, inputs):
        self.inputs, self.values = inputs, None

    @staticmethod
    def _roles(sub: MethodInputs):
        tops = {"a": sub.halves.a, "b": sub.halves.b} if sub.halves is not None else {"stats": sub.stats}
        for key, st in tops.items():
            yield (key,), st
            for name, fst in st.features.items():
                yield (key, name), fst

    def get(self, role):
        if self.values is None:
            if isinstance(self.inputs, FilmReader):
                reads = (self.inputs.read((y0, y1, 0, self.inputs.width)) for y0, y1 in self.inputs.bands)
            else:
                reads = [self.inputs]
            sums: dict = {}
            for sub in reads:
                for key, st in self._roles(sub):
                    sums.setdefault(key, FilmRangeSum()).add(*variance_defined(st))
            self.values = {key: total.result() for key, total in sums.items()}
        return self.values[role]

    def mark(self, sub: MethodInputs, *, now: bool = False) -> MethodInputs:
        """``sub`` (a tile's inputs, crops of their own) with each statistics' ``film_fill`` set: a callable,
        or with ``now`` the values themselves (a tile shipped to another process, without the film)."""
        for key, st in self._roles(sub):
            st.film_fill = self.get(key) if now else functools.partial(self.get, key)
        return sub


def tile_inputs(inputs: MethodInputs, outer) -> MethodInputs:
    """The inputs of one grown tile ``outer`` (``(y0, y1, x0, x1)``): contiguous crops of the film's statistics,
    reference and prefix halves, and for half buffers their merge on the tile only."""
    y0, y1, x0, x1 = outer
    ref = None if inputs.reference is None else np.ascontiguousarray(inputs.reference[y0:y1, x0:x1])
    strata = inputs.strata.crop(y0, y1, x0, x1) if inputs.strata is not None else None
    if inputs.halves is not None:
        a = inputs.halves.a.crop(y0, y1, x0, x1)
        b = inputs.halves.b.crop(y0, y1, x0, x1)
        # the merge is elementwise, so the tile's merge is the crop of the film's, bit for bit
        return MethodInputs(a.merged(b), None, ref, inputs.nonfinite,
                            Halves.from_pair(a, b, sampler=inputs.halves.sampler),
                            strata)
    return MethodInputs(inputs.stats.crop(y0, y1, x0, x1), None, ref, inputs.nonfinite, strata=strata)


def _tiles(inputs, windows, where: str, fill: FilmFill, done=None):
    """``(outer, inner, inputs of outer)`` for each of ``windows`` (:func:`tile_windows`, in order): crops of
    the film's inputs, or of a :class:`FilmReader`'s bands (the rows of a band's tiles, grown, read at
    once; pixels of its tiles without a sample, or without one in a half, refused), ``done(band)`` called as
    each band is let go (:meth:`FilmReader.add_sanity`'s argument); each tile's statistics given the film's
    fill-in values (``fill``: a reader's reads are given them by the reader)."""
    if not isinstance(inputs, FilmReader):
        for outer, inner in windows:
            yield outer, inner, fill.mark(tile_inputs(inputs, outer))
        return
    h, w, _ = inputs.shape
    bands: dict = {}   # the tiles of each band of rows, in order
    for outer, inner in windows:
        bands.setdefault(inner[:2], []).append((outer, inner))
    for (y0, y1), tiles in bands.items():
        # the band's statistics: its rows grown by the halo, one row more each side for the sanity line's
        # 3 x 3 sample range
        by0 = min([o[0] for o, _ in tiles] + [max(0, y0 - 1)])
        by1 = max([o[1] for o, _ in tiles] + [min(h, y1 + 1)])
        band = inputs.read((by0, by1, 0, w))
        _check_counts(band, where, rows=(y0 - by0, y1 - by0))
        for outer, inner in tiles:
            oy0, oy1, ox0, ox1 = outer
            yield outer, inner, tile_inputs(band, (oy0 - by0, oy1 - by0, ox0, ox1))
        if done is not None:
            done(((y0, y1), by0, band))
        del band


def reconstruct_tiles(method: Method, inputs: MethodInputs | FilmReader, *, tile: int, diagnostics: bool = True,
                      where: str = "reconstruct") -> tuple[np.ndarray, RunState]:
    """The untiled image of a local method, reconstructed tile by tile: ``(image (H, W, C) float64, run)``.

    Parameters
    ----------
    method : Method
        A method declaring a finite :meth:`~mcrecon.methods.Method.halo`
        that reads pixel statistics or half buffers.
    inputs : FilmReader or MethodInputs
        Where the tiles' inputs come from (:func:`film_inputs`): a sample
        source read one band of tiles at a time (the band's rows grown by
        the halo and moved back onto the method's grid; the tiles of a band
        are crops of its inputs), or the film's inputs in memory
        (:func:`~mcrecon.offline.inputs.gather_inputs`; with ``halves``,
        ``stats`` may be None: each tile merges its own).
    tile : int
        Largest tile side in pixels; the halo comes on top of it.
    diagnostics : bool
        Assemble the tiles' diagnostic maps (:meth:`~mcrecon.methods.Method.diagnostics`)
        into maps of the film.  Each map holds every pixel of the film beside
        the tiles' work (gem's 18 maps: 144 bytes a pixel), so a caller that
        reads none says False.
    where : str
        How refusals name the caller.

    Returns
    -------
    image : ndarray (H, W, C) float64
    run : RunState
        A run of the whole film whose ``diagnostics`` are the tiles' maps,
        each tile's inner part in place (empty with ``diagnostics=False``).

    Raises
    ------
    InputError
        A whole-image method, a method that filters samples, or a pixel
        without a sample (without one in a half for half buffers): it takes
        the value of the nearest sampled pixel, however far.  Read band by
        band, such pixels are refused when their band is read (before its
        tiles run).  A pixel with one sample (in a half, or in all) borrows
        a variance from its 3 x 3 neighbours, else the film's average: each
        tile's statistics are given the film's (``PixelStats.film_fill``).
    """
    tile = check_tile(tile, where)
    h, w, c = inputs.shape
    halo = tileable_halo(method, w, h, where, inputs=inputs)
    channels = inputs.channels
    grid = method.tile_grid()
    windows = list(tile_windows(w, h, tile, halo, grid=grid))
    streamed = isinstance(inputs, FilmReader)
    if streamed:
        inputs.bands = list(dict.fromkeys(inner[:2] for _, inner in windows))
    image = np.empty((h, w, c), np.float64)

    fill = FilmFill(inputs)
    if streamed:   # every read of the reader (its bands, the tiles cut from them: crops keep it) reads the film's
        inputs.fill = fill

    def each_tile(reach):   # the film's tiles grown by another reach (a method's pass before its tiles')
        return _tiles(inputs, list(tile_windows(w, h, tile, reach, grid=grid)), where, fill)

    # one tile: the untiled run
    runner = method if len(windows) == 1 else method.for_tiles(inputs, each_tile=each_tile)
    maps: dict[str, np.ndarray] = {}
    said: dict = {}
    for outer, inner, sub in _tiles(inputs, windows, where, fill, done=lambda band: inputs.add_sanity(image, band)):
        oy0, oy1, ox0, ox1 = outer
        y0, y1, x0, x1 = inner
        run = runner.start(ox1 - ox0, oy1 - oy0, channels, reference=sub.reference)
        if hasattr(run, "window"):   # a run that reads its place in the film (auto's tiles: AutoRun.window)
            run.window = outer
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            img = runner.reconstruct(sub, run=run)
        for wn in caught:  # what a method says of its inputs, said once for the film, not once a tile
            said.setdefault((wn.category, str(wn.message)), wn)
        iy, ix = slice(y0 - oy0, y1 - oy0), slice(x0 - ox0, x1 - ox0)
        image[y0:y1, x0:x1] = np.asarray(img, dtype=np.float64)[iy, ix]
        for name, m in (runner.diagnostics(run) if diagnostics else {}).items():
            m = np.asarray(m)
            if m.shape[:2] != (oy1 - oy0, ox1 - ox0):
                continue  # not a per-pixel map: no tile of it to place
            full = maps.get(name)
            if full is None:
                full = maps[name] = np.zeros((h, w) + m.shape[2:], m.dtype)
            full[y0:y1, x0:x1] = m[iy, ix]
        del sub, run, img
    if streamed:
        for key, wn in inputs.said.items():
            said.setdefault(key, wn)
    for wn in said.values():
        warnings.warn_explicit(wn.message, wn.category, wn.filename, wn.lineno)
    run = method.start(w, h, channels, reference=None if streamed else inputs.reference)
    run.diagnostics = maps
    return image, run

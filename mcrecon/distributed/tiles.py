"""Tiled reconstruction of one huge film with explicit halos, on a Dask cluster or here.

The tiles, their halos and the refusals are those of ``reconstruct --tile``
(:mod:`mcrecon.offline.tiles`: :func:`~mcrecon.offline.tiles.tile_windows`,
:func:`~mcrecon.offline.tiles.tileable_halo`, :func:`~mcrecon.offline.tiles.tile_inputs`);
this module adds the cluster (each grown tile a task) and the tiles of a
sample-filtering method, each of which reads its own samples.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from ..errors import InputError, McreconWarning


from ..offline.tiles import check_tile, tile_inputs, tile_windows, tileable_halo
from .cluster import _dask
from .ingestion import ingest

__all__ = ['reconstruct_tiled', 'map_tiles', 'tile_windows']


def _reconstruct_tile(method, inputs, inner):
    """Reconstruct one grown tile's inputs and trim it to its inner part (runs on a worker)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", McreconWarning)
        img = method.reconstruct(inputs)
    (a, b), (c, d) = inner
    return np.asarray(img[a:b, c:d], dtype=np.float64)


def _boxes(width: int, height: int, tile: int, halo: int, *, even: bool = True, grid=(1, 1)):
    """:func:`tile_windows` as ``(outer, tile, inner)`` boxes ``((y0, y1), (x0, x1))``: the grown tile and the
    tile in film pixels, and the tile inside the grown one."""
    for (oy0, oy1, ox0, ox1), (y0, y1, x0, x1) in tile_windows(width, height, tile, halo, even=even, grid=grid):
        yield ((oy0, oy1), (ox0, ox1)), ((y0, y1), (x0, x1)), ((y0 - oy0, y1 - oy0), (x0 - ox0, x1 - ox0))


def _run_tiles(func, tasks, shape, client=None) -> np.ndarray:
    """Assemble ``out[tile] = func(*args)`` for each ``(tile, args)`` of ``tasks``.

    Without a client the tiles run here one after another; with one, as
    Dask futures (arguments that are futures stay on the workers), placed
    into the output as they complete.
    """
    out = np.empty(shape, np.float64)
    if client is None:
        for (iy, ix), args in tasks:
            out[iy[0]:iy[1], ix[0]:ix[1]] = func(*args)
        return out
    distributed = _dask()
    futs = {client.submit(func, *args, pure=False): box for box, args in tasks}
    for f in distributed.as_completed(futs):
        iy, ix = futs[f]
        out[iy[0]:iy[1], ix[0]:ix[1]] = f.result()
        f.release()
    return out


def _trim_apply(func, block, inner):
    (a, b), (c, d) = inner
    return np.asarray(func(block))[a:b, c:d]


def map_tiles(func, image, *, tile: int, halo: int, client=None) -> np.ndarray:
    """``func`` applied to tiles of ``image`` grown by ``halo`` (clipped at the edges), each trimmed back.

    The tiling of :func:`reconstruct_tiled`, on a plain array: for a
    ``func`` whose result at a pixel depends on pixels at most ``halo``
    away it equals ``func(image)``, and it equals
    ``dask.array.map_overlap(func, image, depth=halo, boundary="none")``
    (``tests/test_distributed.py`` checks both bit for bit).  The output
    is float64 with the image's first two dimensions.
    """
    image = np.asarray(image)
    h, w = image.shape[:2]
    tasks = [(box, (func, np.ascontiguousarray(image[oy[0]:oy[1], ox[0]:ox[1]]), inner))
             for (oy, ox), box, inner in _boxes(w, h, int(tile), int(halo), even=False)]
    probe = np.asarray(func(image[:1, :1]))
    return _run_tiles(_trim_apply, tasks, (h, w) + probe.shape[2:], client)


# ---------------------------------------------------------------- sample tiles (splat)
class _TileSamples:
    """The samples of one grown tile, shifted to its origin, as a sample source for a method.

    Chunks are kept as the method reads the film's source (the same
    chunk boundaries, each chunk reduced to the tile's samples), so the
    method accumulates every pixel's contributions in the same order as
    on the whole film.
    """

    def __init__(self, width, height, channels, name, rounds, feature_names=()):
        self.width, self.height, self.channels, self.name = width, height, tuple(channels), name
        self.feature_names = tuple(feature_names)  # per-sample features kept with the samples (splat's gate)
        self._rounds = rounds        # [(round index or None, [(positions, values, features), ...]), ...]
        ends = np.cumsum([sum(p.shape[0] for p, _, _ in chunks) for _, chunks in rounds])
        self._slices = list(zip([0, *ends[:-1].tolist()], ends.tolist()))

    @property
    def n_samples(self) -> int:
        return int(self._slices[-1][1]) if self._slices else 0

    def round_slices(self):
        return self._slices

    def iter_chunks(self, *, rounds=None, with_round: bool = False, chunk_size=None, features=()):
        from ..core.samples import SampleChunk

        groups = range(len(self._rounds)) if rounds is None else [int(r) for r in rounds]
        for g in groups:
            for pos, val, feats in self._rounds[g][1]:
                yield SampleChunk(pos, val, None, 0, {k: feats[k] for k in features})


def _film_rounds(source) -> list:
    """How a sample-filtering method groups the source's chunks: per round (two or more), else all at once."""
    nonempty = [r for r, (a, b) in enumerate(source.round_slices()) if b > a]
    return [[r] for r in nonempty] if len(nonempty) >= 2 else [None]


def _tile_samples(source, outer, where: str):
    """The samples of ``source`` in the pixels of ``outer``, shifted by its origin; and the per-round counts.

    Returns (_TileSamples, film counts per round, tile counts per round).
    Positions are checked as the method checks them (an off-film or
    non-finite position is the same one-line error).  Shifting a float
    x >= x0 by an integer x0 is exact (x0 is a multiple of x's spacing),
    so the method computes the same offsets to every pixel centre.
    """
    from ..core.samples import check_samples

    (oy0, oy1), (ox0, ox1) = outer
    groups, film_n, tile_n = [], [], []
    names = tuple(getattr(source, "feature_names", ()))
    fkw = {"features": names} if names else {}
    for g in _film_rounds(source):
        chunks, nf, nt = [], 0, 0
        for ch in source.iter_chunks(rounds=g, with_round=False, **fkw):
            pos, val, _ = check_samples(ch.positions, ch.values, width=source.width, height=source.height,
                                        n_channels=len(source.channels), where=where)
            nf += pos.shape[0]
            ix, iy = np.floor(pos[:, 0]), np.floor(pos[:, 1])
            keep = (ix >= ox0) & (ix < ox1) & (iy >= oy0) & (iy < oy1)
            if keep.any():
                p = pos[keep]
                p[:, 0] -= ox0
                p[:, 1] -= oy0
                chunks.append((p, val[keep], {k: np.asarray(a)[keep] for k, a in (ch.features or {}).items()}))
                nt += p.shape[0]
        groups.append((None if g is None else g[0], chunks))
        film_n.append(nf)
        tile_n.append(nt)
    sub = _TileSamples(ox1 - ox0, oy1 - oy0, source.channels, source_name_of(source), groups, names)
    return sub, film_n, tile_n


def source_name_of(source) -> str:
    from ..core.samples import source_name

    return source_name(source)


def _splat_tile(method, source, outer, inner, film_pixels: int, nonfinite: str, reference=None):
    """Reconstruct one grown tile of a sample-filtering method from the samples that reach it (on a worker).

    ``source`` is a log path (the worker streams the whole log and keeps
    the tile's samples: memory is the grown tile's samples) or a
    :class:`_TileSamples` already cut on the client.
    """
    from ..methods.base import MethodInputs

    where = f"{method.where} (tiled)"
    if isinstance(source, _TileSamples):
        sub, film_n, tile_n = source, None, None
    else:
        from ..io import read_log

        sub, film_n, tile_n = _tile_samples(read_log(source), outer, where)
    if film_n is not None:
        _check_round_densities(where, film_n, tile_n, film_pixels, sub.width * sub.height)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", McreconWarning)
        img = method.reconstruct(MethodInputs(None, sub, reference, nonfinite=nonfinite))
    (a, b), (c, d) = inner
    return np.asarray(img[a:b, c:d], dtype=np.float64)


def _check_round_densities(where, film_n, tile_n, film_pixels, tile_pixels):
    """Refuse a tile whose rounds are not as dense as the film's.

    Splatting weighs round j by its mean samples per pixel over the
    *film*, N_j = n_j / pixels (Suykens and Willems' scale-down); a tile
    reproduces it exactly only if its own rounds have the same densities
    (equal fractions give the same correctly rounded quotient), as rounds
    that sample every pixel alike do.  One round is weighed 1 whatever
    its density.
    """
    if len(film_n) < 2:
        return
    for r, (nf, nt) in enumerate(zip(film_n, tile_n)):
        if nt * film_pixels != nf * tile_pixels:
            raise InputError(where, "rounds", f"round {r} has {nt / tile_pixels:.6g} samples per pixel in a tile "
                             f"but {nf / film_pixels:.6g} over the film: splatting weighs rounds by their "
                             "film-wide density, so tiles of an adaptively sampled log are not local; "
                             "reconstruct it untiled (mcrecon.reconstruct)")


def reconstruct_tiled(source, *, method="box", tile: int = 1024, client=None, reference=None,
                      nonfinite: str = "drop", **options) -> np.ndarray:
    """Reconstruct in tiles with halos: the untiled image of a local method, tile by tile.

    Parameters
    ----------
    source : PixelStats, a sample log (path or SampleLog), a SampleSet or a half-buffer pair
        Without a ``client``, what ``reconstruct --tile`` reads
        (:func:`mcrecon.offline.tiles.film_inputs`: a sample source band
        by band, statistics given in memory as they are, half buffers
        included), reconstructed by its tiles
        (:func:`mcrecon.offline.tiles.reconstruct_tiles`).  With one,
        methods of pixel statistics take statistics (a log is ingested
        with :func:`ingest`).  Sample-filtering methods (splat) take a log
        or a SampleSet: each tile gets the samples whose pixel lies in the
        tile grown by the halo.
    method : str or Method
        A method declaring a finite :meth:`~mcrecon.methods.Method.halo`;
        whole-image methods (awr) are refused
        (:func:`mcrecon.offline.tiles.tileable_halo`, the one refusal of
        every tiled path).
    tile : int
        Tile side in pixels (the halo comes on top of it).
    client : distributed.Client, optional
        Tiles run as tasks on it; without one, in this process one after
        the other (memory: one band of grown tiles' statistics and one
        tile's work at a time, for a sample source).
        For a log and a sample-filtering method each task streams the log
        itself (the log must be on a file system the workers share).
    reference : ndarray (H, W, C), optional
        For oracle modes (cropped with each tile).

    Raises
    ------
    InputError
        A whole-image method; statistics with a pixel of fewer than two
        samples (the fill-in policies for such pixels can borrow from
        anywhere in the image, so no finite halo makes the result local);
        for splat, the paper variant (``spread='all'``: its pseudo-rounds
        and scatter depend on the whole film) or rounds whose density in a
        tile differs from the film's (adaptive logs).
    """
    from ..methods.base import Method, MethodInputs
    from ..methods import get_method
    from ..core.stats import PixelStats
    from ..offline.tiles import FilmFill, film_inputs, reconstruct_tiles

    m = method if isinstance(method, Method) else get_method(str(method), **options)
    if isinstance(method, Method) and options:
        raise InputError("reconstruct_tiled", sorted(options)[0], "a method object already carries its options")
    where = f"{m.where} (tiled)"
    tile = check_tile(tile, where)
    if m.requires.samples and not m.requires.half_buffers:
        return _reconstruct_tiled_samples(m, source, tile, client, reference, nonfinite, where)
    if client is None:   # the tiles of reconstruct --tile, one after the other
        inputs = film_inputs(_opened(source), m, nonfinite=nonfinite, reference=reference, where=where)
        return reconstruct_tiles(m, inputs, tile=tile, diagnostics=False, where=where)[0]
    if not m.requires.statistics or m.requires.half_buffers:
        raise InputError(where, "client", f"{m.name} reads half buffers or no pixel statistics, which the "
                         "cluster's ingestion does not build: tile it without a client, or reconstruct untiled")
    strata = None
    if isinstance(source, PixelStats):
        stats = source
    else:
        stats = ingest(source, client=client, subpixels=m.requires.subpixels, nonfinite=nonfinite)
        if m.requires.prefix_halves:   # as the untiled dispatcher builds them (each pixel's sequence order)
            from ..core.strata import prefix_halves_of
            strata = prefix_halves_of(_opened(source))
    if m.requires.subpixels and stats.subpixels != m.requires.subpixels:
        raise InputError(where, "statistics", f"need a {m.requires.subpixels}x{m.requires.subpixels} subpixel "
                         f"grid, got subpixels={stats.subpixels}")
    h, w, c = stats.shape
    ref = None if reference is None else np.asarray(reference, dtype=np.float64)
    inputs = MethodInputs(stats, None, ref, nonfinite, strata=strata)
    halo = tileable_halo(m, w, h, where, inputs=inputs)
    grid = m.tile_grid()
    mf = client.scatter(m.for_tiles(inputs), broadcast=True)   # the film's whole-image decisions made here
    tasks = []
    fill = FilmFill(inputs)   # the film's fill-in values for pixels with one sample, shipped with each tile
    for (oy, ox), box, inner in _boxes(w, h, tile, halo, grid=grid):
        # each grown tile goes to one worker, the film stays here
        sub = client.scatter(fill.mark(tile_inputs(inputs, (oy[0], oy[1], ox[0], ox[1])), now=True))
        tasks.append((box, (mf, sub, inner)))
    return _run_tiles(_reconstruct_tile, tasks, (h, w, c), client)


def _reconstruct_tiled_samples(m, source, tile, client, reference, nonfinite, where):
    from ..io import read_log
    from ..io.reader import SampleLog
    from ..core.samples import SampleSet, check_policy
    from ..core.stats import PixelStats

    check_policy(nonfinite, where)
    if m.name == "splat" and m.params.get("spread") == "all":
        raise InputError(where, "spread", "splat's paper variant (spread='all') is not local: it splits a "
                         "single-round source into pseudo-rounds scheduled by the film's smallest pixel count, "
                         "and sums large batches in two blocks whose split moves with the batch; tile the robust "
                         "variant (the default), or reconstruct untiled")
    if isinstance(source, PixelStats):
        raise InputError(where, "source", f"{m.name} filters individual samples: give it a sample log or a "
                         "SampleSet, not pixel statistics")
    if isinstance(source, (str, os.PathLike)):
        source = read_log(source)
    if not isinstance(source, (SampleLog, SampleSet)):
        raise InputError(where, "source", f"got {type(source).__name__}, expected a sample log or a SampleSet")
    w, h, c = source.width, source.height, len(source.channels)
    halo = tileable_halo(m, w, h, where)   # each tile reads its own samples
    ref = None if reference is None else np.asarray(reference, dtype=np.float64)
    mf = m if client is None else client.scatter(m, broadcast=True)
    tasks = []
    for outer, box, inner in _boxes(w, h, tile, halo, grid=m.tile_grid()):
        (oy, ox) = outer
        r = None if ref is None else ref[oy[0]:oy[1], ox[0]:ox[1]]
        if isinstance(source, SampleLog):
            src = str(Path(source.path).resolve())       # the task streams the log itself
        else:
            src, film_n, tile_n = _tile_samples(source, outer, where)
            _check_round_densities(where, film_n, tile_n, w * h, src.width * src.height)
            if client is not None:
                src = client.scatter(src)
        if client is not None and r is not None:
            r = client.scatter(r)
        tasks.append((box, (mf, src, outer, inner, w * h, nonfinite, r)))
    return _run_tiles(_splat_tile, tasks, (h, w, c), client)


def _opened(source):
    """A sample log opened from a path (a SampleLog or SampleSet is returned as it is)."""
    import os

    from ..io import read_log

    return read_log(source) if isinstance(source, (str, os.PathLike)) else source

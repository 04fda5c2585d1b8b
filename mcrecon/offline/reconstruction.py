"""Offline reconstruction from any source: a sample log, samples in memory, pixel statistics.

:func:`reconstruct` is the one path the Python API, the CLI and the
experiments take: it reads what the method declares it needs
(:attr:`mcrecon.methods.Method.requires`), starts a run, and reconstructs.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..methods.base import Method
from ..methods import get_method
from ..methods.base import MethodInputs, RunState
from ..core.halves import is_half_buffer_pair
from ..core.samples import SampleSet, check_policy
from ..core.stats import PixelStats


from .._lazy import public_dir as _public_dir
from .inputs import gather_inputs
from .pixel_files import is_pixel_file_source, read_pixel_file_source
from .tiles import FilmReader, check_tile, film_inputs, reconstruct_tiles

__all__ = ['reconstruct', 'split_source_fireflies', 'Reconstruction']

@dataclasses.dataclass(eq=False)
class Reconstruction:
    """An image with the method and run that made it.

    Attributes
    ----------
    image : ndarray (H, W, C) float64
    method : Method
    run : RunState
    inputs : MethodInputs
    fireflies : FireflySplit or None
        With ``fireflies="cascade"``: the split (the method saw the base
        samples; ``fireflies.excess`` is part of ``image``).
    channels : tuple of str
        The image's channel names: the file's output colours for a
        pixel-statistics EXR (whose statistics may be in another space,
        ``inputs.channels``), else the source's.
    files : tuple of PixelStatsEXR
        The pixel-statistics EXRs read (one, or a half-buffer pair's two);
        empty for other sources.
    """

    image: np.ndarray
    method: Method
    run: RunState
    inputs: MethodInputs
    fireflies: object = None
    channels: tuple = ()
    files: tuple = ()
    _sanity: list | None = dataclasses.field(default=None, repr=False)
    #: With ``fireflies``: the samples before the split (the base's range is clipped; the image is not).
    _sanity_source: object = dataclasses.field(default=None, repr=False)

    def diagnostics(self) -> dict:
        """The method's diagnostic maps of this reconstruction."""
        return dict(self.method.diagnostics(self.run))

    def sanity(self) -> dict | None:
        """Negative pixels from non-negative samples and overshoot beyond the samples' 3x3 range.

        See :func:`mcrecon.core.metrics.output_sanity`; computed on first use
        (methods that read no statistics get them from their samples, one
        more streaming pass).  None for pixel statistics without a range.
        """
        if self._sanity is None:
            import warnings

            from ..core.metrics import output_sanity

            stats = self.inputs.stats
            if self._sanity_source is not None:
                stats = None  # the base's statistics: compare with all the samples instead
            if (stats is None or not stats.has_range) and (self._sanity_source or self.inputs.samples) is not None:
                src = self._sanity_source if self._sanity_source is not None else self.inputs.samples
                with warnings.catch_warnings():  # the reconstruction already reported dropped samples
                    warnings.simplefilter("ignore")
                    stats = PixelStats.from_source(src, nonfinite=self.inputs.nonfinite)
            self._sanity = [output_sanity(self.image, stats) if stats is not None else None]
        return self._sanity[0]


def split_source_fireflies(source, *, nonfinite: str = "drop", **split_options):
    """Read every sample of ``source`` and split it (:func:`mcrecon.filters.fireflies.split_fireflies`).

    Returns ``(base, split)``: a :class:`SampleSet` of the base samples
    (same positions, channels and rounds) and the split.  The samples are
    held in memory (positions, values and the base values: about 64 bytes
    per sample for RGB).
    """
    from ..filters.fireflies import split_fireflies
    from ..core.samples import apply_nonfinite, check_samples

    check_policy(nonfinite, "reconstruct")
    if isinstance(source, PixelStats) or is_half_buffer_pair(source):
        raise InputError("reconstruct", "fireflies", "fireflies='cascade' splits individual samples, which pixel "
                         "statistics no longer hold; give a sample log or a SampleSet, or fireflies='none'")
    if isinstance(source, (str, Path)):
        from ..io import read_log
        source = read_log(source)
    if not (hasattr(source, "round_slices") and hasattr(source, "iter_chunks")):
        raise InputError("reconstruct", "source", f"got {type(source).__name__}; expected a sample log path, "
                         "a SampleLog or a SampleSet")
    where = getattr(source, "name", "samples")
    chunks = [(c.positions, c.values, c.round) for c in source.iter_chunks(with_round=True)]
    if chunks:
        pos = np.concatenate([c[0] for c in chunks]).astype(np.float64, copy=False)
        val = np.concatenate([c[1] for c in chunks]).astype(np.float64, copy=False)
        rounds = np.concatenate([c[2] for c in chunks])
    else:
        pos, val, rounds = np.zeros((0, 2)), np.zeros((0, len(source.channels))), np.zeros(0, np.int64)
    pos, val, n_bad = check_samples(pos, val, width=source.width, height=source.height,
                                    n_channels=len(source.channels), where=where)
    if n_bad:
        import warnings

        from ..errors import McreconWarning

        finite = np.isfinite(val).all(axis=1)
        pos, val = apply_nonfinite(pos, val, n_bad, nonfinite, where=where)
        if nonfinite == "drop":
            rounds = rounds[finite]
        warnings.warn(f"{where}: values: {n_bad} sample(s) with NaN or Inf "
                      f"{'dropped' if nonfinite == 'drop' else 'set to 0'} (policy nonfinite={nonfinite!r})",
                      McreconWarning, stacklevel=3)
    split = split_fireflies(pos, val, width=source.width, height=source.height, **split_options)
    split.n_nonfinite = int(n_bad)
    base = SampleSet(pos, split.base_values, width=source.width, height=source.height,
                     channels=source.channels, rounds=rounds, name=where)
    return base, split


def reconstruct(source, *, method="box", nonfinite: str = "drop", reference=None, full: bool = False,
                fireflies: str = "none", exr_options: dict | None = None, tile: int | None = None,
                diagnostics: bool = True, **options):
    """Reconstruct an (H, W, C) float64 image offline.

    Parameters
    ----------
    source : path-like, SampleLog, SampleSet, PixelStats, Halves or a pair
        A sample log (streamed in chunks), samples in memory, statistics
        already built, a pixel-statistics EXR (a path ending in ``.exr`` or
        a :class:`~mcrecon.io.pixel_exr.PixelStatsEXR`; the image comes back
        in the file's output colours), or a half-buffer pair: statistics of
        two independent halves of the samples (dual buffers a renderer
        wrote: ``(stats_a, stats_b)``, :class:`~mcrecon.core.halves.Halves`
        or two EXR paths ``("a.exr", "b.exr")``), for methods that declare
        ``requires.half_buffers`` (``auto`` and ``nfor`` of the built-in methods;
        ``mcrecon.methods.half_buffer_methods()`` lists them all).
        The pair must agree in size, channels and subpixel grid; each
        pixel's counts may differ.  The statistics of all the samples are
        their Chan merge.  On pixel-statistics files a method whose options
        need what they lack (the samples, a sample range) runs with the
        options it declares for them when those were not given, with a
        warning (``Requirements.statistics_options``).
    method : str or Method
        A registered method name (``mcrecon.available_methods()``) with
        its keyword ``options``, or a method object.
    nonfinite : {'drop', 'zero', 'raise'}
        Policy for NaN/Inf sample values.
    reference : ndarray, optional
        Reference image for methods that read one (default: the log's).
    full : bool
        Return a :class:`Reconstruction` (image, method, run with its
        diagnostics) instead of the image.
    fireflies : {'none', 'cascade'}
        ``cascade``: split the samples into luminance cascades first
        (:mod:`mcrecon.filters.fireflies`); the method reconstructs the base part
        and the rare bright part is added back, spread with the support its
        sample density needs (energy kept, consistent).  Any method; needs
        the individual samples (a log or a SampleSet) and holds them in
        memory.  Measured in ``docs/fireflies.md``.
    exr_options : dict, optional
        How to read pixel-statistics EXRs (the keywords of
        :func:`mcrecon.io.read_pixel_stats_exr`: ``layout``, ``mean``,
        ``variance``, ``count``, ``spp``, ...); by default the layout is
        detected from the channel names.  A file without a sample count
        (Mitsuba's moment integrator writes none) needs ``count`` or ``spp``.
    tile : int, optional
        Reconstruct in tiles of at most ``tile`` x ``tile`` pixels, each
        grown by the method's halo (:meth:`~mcrecon.methods.Method.halo`):
        the untiled image, with the method's working memory of one tile
        (:func:`mcrecon.offline.tiles.reconstruct_tiles`; half buffers are
        merged tile by tile).  A sample source is read one band of tiles at
        a time, so the film's statistics are never held: the
        :class:`Reconstruction`'s ``inputs`` then hold the samples, not
        statistics (its sanity line is added band by band).  Refused for
        whole-image methods and for pixels with fewer than two samples.
        Default: untiled.
    diagnostics : bool
        With ``tile`` and ``full``: assemble the tiles' diagnostic maps,
        film-sized arrays beside the tiles' work; False leaves
        ``Reconstruction.diagnostics()`` empty.  (Untiled, the method
        builds its maps when they are asked for.)

    Examples
    --------
    >>> import numpy as np, mcrecon
    >>> rng = np.random.default_rng(0)
    >>> pos = rng.random((4000, 2)) * [20, 10]
    >>> samples = mcrecon.SampleSet(pos, rng.normal(1.0, 0.1, (4000, 3)), width=20, height=10)
    >>> image = mcrecon.reconstruct(samples, method="gem")
    >>> image.shape
    (10, 20, 3)
    >>> bool(abs(image.mean() - 1.0) < 0.01)
    True
    """
    tile = check_tile(tile)
    sanity = None
    if isinstance(method, Method):
        if options:
            raise InputError("reconstruct", sorted(options)[0], "options go to get_method(); a method object "
                             "already carries its options")
        m = method
    else:
        m = get_method(str(method), **options)
    from ..filters.fireflies import FIREFLY_MODES
    if fireflies not in FIREFLY_MODES:
        raise InputError("reconstruct", "fireflies", f"unknown mode {fireflies!r}; valid: {', '.join(FIREFLY_MODES)}")
    split = files = None
    if is_pixel_file_source(source):
        files = read_pixel_file_source(source, m, options=exr_options, fireflies=fireflies)
        m, source = files.method, files.source
    elif exr_options:
        raise InputError("reconstruct", "exr_options", "applies to pixel-statistics EXR inputs (paths ending in "
                         ".exr), not to this source")
    if fireflies == "cascade":
        if isinstance(source, (str, Path)):
            from ..io import read_log
            source = read_log(source)
        if reference is None and m.requires.reference != "none" and hasattr(source, "reference"):
            reference = source.reference()  # the base SampleSet carries no stored reference
        original = source
        source, split = split_source_fireflies(source, nonfinite=nonfinite)
    if tile is not None and files is None:
        inputs = film_inputs(source, m, nonfinite=nonfinite, reference=reference)
    else:
        inputs = gather_inputs(source, m, nonfinite=nonfinite, reference=reference, merged=tile is None,
                               **({"what": files.what, "surface": "files"} if files is not None else {}))
    h, w, _ = inputs.shape
    if tile is not None:
        image, run = reconstruct_tiles(m, inputs, tile=tile, diagnostics=full and diagnostics)
        if isinstance(inputs, FilmReader):  # read band by band: the caller gets the samples and the sanity line
            sanity = [inputs.sanity]
            inputs = MethodInputs(None, inputs.source, None, nonfinite)
        elif inputs.stats is None:  # the colour's merge for the caller (counts, range): a third of a featured one
            inputs = dataclasses.replace(inputs, stats=inputs.halves.without_features().merged())
    else:
        run = m.start(w, h, inputs.channels, reference=inputs.reference)
        image = np.asarray(m.reconstruct(inputs, run=run), dtype=np.float64)
    if split is not None:
        image = image + split.excess
    if files is not None:  # statistics in the file's working space (XYZ for the presets): to its colours
        image = files.output_image(image)
    if not full:
        return image
    return Reconstruction(image, m, run, inputs, fireflies=split, _sanity=sanity if split is None else None,
                          _sanity_source=original if split is not None else None,
                          channels=files.channels if files is not None else tuple(inputs.channels),
                          files=files.files if files is not None else ())

__dir__ = _public_dir(__name__)

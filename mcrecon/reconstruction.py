"""Offline reconstruction from any source: a sample log, samples in memory, pixel statistics.

:func:`reconstruct` is the one path the Python API, the CLI and the
experiments take: it reads what the method declares it needs
(:attr:`mcrecon.methods.Method.requires`), starts a run, and reconstructs.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from .errors import InputError
from .methods import Method, get_method
from .methods.base import MethodInputs, RunState, SplitHalves, check_half_buffers, half_buffer_methods, \
    is_half_buffer_pair, merge_halves
from .samples import SampleSet, check_policy, check_reference
from .stats import PixelStats

__all__ = ["reconstruct", "gather_inputs", "check_given_statistics", "statistics_for", "split_source_fireflies",
           "Reconstruction"]


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
    """

    image: np.ndarray
    method: Method
    run: RunState
    inputs: MethodInputs
    fireflies: object = None
    _sanity: list | None = dataclasses.field(default=None, repr=False)
    #: With ``fireflies``: the samples before the split (the base's range is clipped; the image is not).
    _sanity_source: object = dataclasses.field(default=None, repr=False)

    def diagnostics(self) -> dict:
        """The method's diagnostic maps of this reconstruction."""
        return dict(self.method.diagnostics(self.run))

    def sanity(self) -> dict | None:
        """Negative pixels from non-negative samples and overshoot beyond the samples' 3x3 range.

        See :func:`mcrecon.metrics.output_sanity`; computed on first use
        (methods that read no statistics get them from their samples, one
        more streaming pass).  None for pixel statistics without a range.
        """
        if self._sanity is None:
            import warnings

            from .metrics import output_sanity

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


def statistics_for(source, req, *, nonfinite: str = "drop"):
    """``(stats, halves)`` of a sample source for a method's requirements ``req``.

    A method that reads the samples *and* takes half buffers splits the
    samples into two halves anyway (:func:`mcrecon.estimates.split_halves`):
    for it one pass builds the halves, handed over as a
    :class:`~mcrecon.methods.base.SplitHalves` of ``source``, and the
    statistics of all the samples are their Chan merge (equal to
    accumulating every sample to a few ulps; auto at 1024^2: -0.45 s).
    Otherwise the statistics (if declared) and no halves.
    """
    if req.samples and req.half_buffers and req.statistics and not req.subpixels:
        from .estimates import split_halves
        split = split_halves(source, nonfinite=nonfinite)
        return merge_halves(split.a, split.b), SplitHalves(split.a, split.b, source)
    stats = PixelStats.from_source(source, subpixels=req.subpixels, nonfinite=nonfinite) \
        if req.statistics else None
    return stats, None


def check_given_statistics(stats: PixelStats, where: str, field: str = "stats", *,
                           need_samples: bool = True) -> None:
    """Refuse statistics a user built that hold NaN/Inf in a sampled pixel, or (``need_samples``) no sample.

    :meth:`PixelStats.add` and :meth:`PixelStats.from_moments` never make
    such statistics; arrays filled in from outside can, and a method would
    spread the NaN over its support.
    """
    sampled = stats.count > 0
    if need_samples and not sampled.any():
        raise InputError(where, field, "no pixel has a sample: there is nothing to reconstruct")
    for name, arr in (("mean", stats.mean), ("m2", stats.m2)):
        bad = sampled & ~np.isfinite(arr).all(axis=2)
        if bad.any():
            raise InputError(where, f"{field}.{name}", f"{int(bad.sum())} sampled pixel(s) hold NaN or Inf "
                             "(statistics built outside PixelStats.add/from_moments?); fix the input")


def gather_inputs(source, method: Method, *, nonfinite: str = "drop", reference=None, where: str | None = None,
                  logs: bool = True) -> MethodInputs:
    """The inputs ``method`` declares, read from ``source``: the one place a source becomes MethodInputs.

    Parameters
    ----------
    source : path-like, SampleLog, SampleSet, PixelStats or (PixelStats, PixelStats)
        A sample log is streamed into statistics (with the subpixel grid the
        method asks for) and handed over as the sample source of methods
        that filter samples; pixel statistics cannot serve those.  A tuple
        of two PixelStats is a half-buffer pair (two independent halves of
        the samples), for methods with ``requires.half_buffers``: handed
        over as ``inputs.halves``, with ``inputs.stats`` their merge.  For
        a method that needs the samples and takes half buffers, the
        samples come with their split (:func:`statistics_for`).  Pixel
        statistics and halves the caller gives are checked
        (:func:`check_given_statistics`).
    method : Method
    nonfinite : {'drop', 'zero', 'raise'}
        Policy for NaN/Inf sample values.
    reference : ndarray (H, W, C), optional
        The reference image; by default the log's stored one, for methods
        that read a reference.
    where : str, optional
        How error messages name the caller (e.g. ``"mcrecon.restoration.gem"``);
        by default the method for what it refuses and ``"reconstruct"`` for
        the source.
    logs : bool
        Accept sample log paths and SampleLogs (False: in-memory sources only).
    """
    src_where = where or "reconstruct"
    m_where = where or method.where
    check_policy(nonfinite, src_where)
    req, name = method.requires, method.name
    samples_from = "a sample log or a SampleSet" if logs else "a mcrecon.SampleSet"
    halves = None
    if is_half_buffer_pair(source):
        if not req.half_buffers:
            raise InputError(m_where, "halves", f"{name} does not use half buffers; methods that "
                             f"do: {', '.join(half_buffer_methods()) or '(none)'} (for {name}, give the "
                             "statistics of all the samples: mcrecon.methods.base.merge_halves(a, b))")
        halves = check_half_buffers(source, src_where)
        if req.subpixels and halves[0].subpixels != req.subpixels:
            raise InputError(m_where, "halves", f"this configuration needs a {req.subpixels}x"
                             f"{req.subpixels} subpixel grid, got subpixels={halves[0].subpixels}")
        for i, h in enumerate(halves):
            check_given_statistics(h, src_where, f"halves[{i}]", need_samples=False)
        stats, samples, stored_ref = merge_halves(*halves), None, None
        check_given_statistics(stats, src_where, "halves")
    elif isinstance(source, PixelStats):
        if req.samples and req.half_buffers:
            raise InputError(m_where, "input", f"{name} (these options) needs the individual "
                             "samples or two independent half buffers, which one set of pixel statistics does not "
                             f"hold; give it {samples_from}, or a half-buffer pair (stats_a, stats_b)"
                             + ("; or candidates='box,gauss' (the SURE candidates need neither)"
                                if name == "auto" else ""))
        if req.samples:
            raise InputError(m_where, "input", f"{name} filters individual samples, which pixel "
                             f"statistics no longer hold; give it {samples_from}")
        check_given_statistics(source, src_where)
        stats, samples, stored_ref = source, None, None
    else:
        if logs and isinstance(source, (str, Path)):
            from .io import read_log
            source = read_log(source)
        if not (hasattr(source, "round_slices") and hasattr(source, "iter_chunks")) or \
                not (logs or isinstance(source, SampleSet)):
            kinds = "a sample log path, a SampleLog, a SampleSet, PixelStats" if logs else \
                "PixelStats (PixelStats.from_moments / from_samples), a mcrecon.SampleSet"
            raise InputError(src_where, "source", f"got {type(source).__name__}; expected {kinds} or a "
                             "half-buffer pair (stats_a, stats_b)")
        stats, halves = statistics_for(source, req, nonfinite=nonfinite)
        stored_ref = source.reference() if req.reference != "none" and hasattr(source, "reference") else None
        samples = source if req.samples else None
    shape = stats.shape if stats is not None else (samples.height, samples.width, len(samples.channels))
    ref = check_reference(reference if reference is not None else stored_ref, shape,
                          **({"where": f"{where}: reference"} if where else {}))
    return MethodInputs(stats, samples, ref if req.reference != "none" else None, nonfinite, halves)


def split_source_fireflies(source, *, nonfinite: str = "drop", **split_options):
    """Read every sample of ``source`` and split it (:func:`mcrecon.fireflies.split_fireflies`).

    Returns ``(base, split)``: a :class:`SampleSet` of the base samples
    (same positions, channels and rounds) and the split.  The samples are
    held in memory (positions, values and the base values: about 64 bytes
    per sample for RGB).
    """
    from .fireflies import split_fireflies
    from .samples import SampleSet, apply_nonfinite, check_samples

    check_policy(nonfinite, "reconstruct")
    if isinstance(source, PixelStats) or is_half_buffer_pair(source):
        raise InputError("reconstruct", "fireflies", "fireflies='cascade' splits individual samples, which pixel "
                         "statistics no longer hold; give a sample log or a SampleSet, or fireflies='none'")
    if isinstance(source, (str, Path)):
        from .io import read_log
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

        from .errors import McreconWarning

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
                fireflies: str = "none", **options):
    """Reconstruct an (H, W, C) float64 image offline.

    Parameters
    ----------
    source : path-like, SampleLog, SampleSet, PixelStats or (PixelStats, PixelStats)
        A sample log (streamed in chunks), samples in memory, statistics
        already built, or a half-buffer pair: statistics of two independent
        halves of the samples (dual buffers a renderer wrote), for methods
        that declare ``requires.half_buffers`` (``auto``).  The pair must
        agree in size, channels and subpixel grid; each pixel's counts may
        differ.  The statistics of all the samples are their Chan merge.
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
        (:mod:`mcrecon.fireflies`); the method reconstructs the base part
        and the rare bright part is added back, spread with the support its
        sample density needs (energy kept, consistent).  Any method; needs
        the individual samples (a log or a SampleSet) and holds them in
        memory.  Measured in ``docs/fireflies.md``.

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
    if isinstance(method, Method):
        if options:
            raise InputError("reconstruct", sorted(options)[0], "options go to get_method(); a method object "
                             "already carries its options")
        m = method
    else:
        m = get_method(str(method), **options)
    from .fireflies import FIREFLY_MODES
    if fireflies not in FIREFLY_MODES:
        raise InputError("reconstruct", "fireflies", f"unknown mode {fireflies!r}; valid: {', '.join(FIREFLY_MODES)}")
    split = None
    if fireflies == "cascade":
        if isinstance(source, (str, Path)):
            from .io import read_log
            source = read_log(source)
        if reference is None and m.requires.reference != "none" and hasattr(source, "reference"):
            reference = source.reference()  # the base SampleSet carries no stored reference
        original = source
        source, split = split_source_fireflies(source, nonfinite=nonfinite)
    inputs = gather_inputs(source, m, nonfinite=nonfinite, reference=reference)
    h, w, _ = inputs.shape
    run = m.start(w, h, inputs.channels, reference=inputs.reference)
    image = np.asarray(m.reconstruct(inputs, run=run), dtype=np.float64)
    if split is not None:
        image = image + split.excess
    if not full:
        return image
    return Reconstruction(image, m, run, inputs, fireflies=split,
                          _sanity_source=original if split is not None else None)


from ._lazy import public_dir as _public_dir  # noqa: E402

__dir__ = _public_dir(__name__)

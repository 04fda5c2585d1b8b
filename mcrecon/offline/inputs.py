"""The one input dispatcher: a source (log path, SampleLog, SampleSet, PixelStats, half-buffer
pair) into the :class:`~mcrecon.methods.MethodInputs` a method declares.

What a method can take is declared on its :class:`~mcrecon.methods.Requirements`
and refused in one place, :func:`mcrecon.methods.supply.check_supply`; this
module only says what each source holds (:class:`~mcrecon.methods.supply.Supply`)
and builds what the method reads, half buffers included
(:class:`~mcrecon.core.halves.Halves`, one pass over the samples).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..methods import half_buffer_methods, statistics_methods
from ..methods.base import Method, MethodInputs
from ..methods.supply import Supply, check_supply
from ..core.features import layout_of, usable_names
from ..core.halves import Halves, as_halves, is_half_buffer_pair, split_halves
from ..core.samples import SampleSet, check_policy, check_reference, source_name
from ..core.stats import PixelStats
from ..core.strata import PrefixHalves, prefix_halves_of

__all__ = ['gather_inputs', 'check_given_statistics', 'statistics_for', 'check_method_supply']

#: The registry's lists the refusals name (the methods that take half buffers, or pixel statistics alone).
_LISTS = {"half_buffer_methods": half_buffer_methods, "statistics_methods": statistics_methods}


def check_method_supply(method: Method, supply: Supply, where: str | None = None) -> None:
    """:func:`~mcrecon.methods.supply.check_supply` with the registry's lists for the messages."""
    check_supply(method, supply, where=where, **_LISTS)


def statistics_for(source, req, *, nonfinite: str = "drop", merged: bool = True, strata=None, window=None):
    """``(stats, halves)`` of a sample source for a method's requirements ``req``.

    A method that reads the samples *and* takes half buffers reads the
    halves: for it one pass builds them
    (:func:`mcrecon.core.halves.split_halves`, ``halves.source`` the
    source), and the statistics of all the samples are their Chan merge
    (equal to accumulating every sample to a few ulps, at the cost of one
    pass instead of two).  Otherwise the statistics (if declared) and no
    halves.  ``merged=False`` leaves the merge of halves to the caller
    (``stats`` None): a tiled reconstruction merges tile by tile, so no
    third set of the film's statistics sits beside the two halves.
    ``strata`` (:class:`~mcrecon.core.strata.PrefixHalves`, empty), when
    given, is filled by the same pass over the samples (bit for bit
    :func:`~mcrecon.core.strata.prefix_halves_of`: every sample as stored,
    in stored order); it stays empty when no statistics are built.
    ``window`` ``(y0, y1, x0, x1)``: the statistics of those pixels only,
    read from the whole source (the film's cropped to them, bit for bit:
    :meth:`~mcrecon.core.stats.PixelStats.window_of`).
    """
    # every feature the method can accumulate ((N,) or (N, k) per sample); others are ignored
    features = usable_names(source) if req.features != "none" else ()
    if req.samples and req.half_buffers and req.statistics and not req.subpixels:
        split = split_halves(source, nonfinite=nonfinite, features=features,
                             each_batch=None if strata is None else strata.add, window=window)
        split.transient = True   # this call's alone: a method may let go of features it has done with
        # the merge's features are merged when read: a method reads few of them, one at a time
        return (split.a.merged(split.b, features_on_read=True) if merged else None), split
    stats = PixelStats.from_source(source, subpixels=req.subpixels, nonfinite=nonfinite, features=features,
                                   each_batch=None if strata is None else strata.add,
                                   window=window) if req.statistics else None
    return stats, None


def _fit_features(stats: PixelStats | None, req):
    """Statistics given by the caller, with their features dropped for a method that reads none
    (so a method that says ``features='none'`` sees exactly what it always saw)."""
    if stats is None or req.features != "none" or not stats.features:
        return stats
    return stats.without_features()


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


def _given_halves(source, method: Method, src_where: str, m_where: str, what: str, surface: str) -> Halves:
    """A caller's half-buffer pair, checked, as the :class:`Halves` the method reads."""
    req = method.requires
    if not req.half_buffers:  # the method's refusal first: the pair's contents do not matter then
        check_method_supply(method, Supply(what, halves=True, surface=surface), m_where)
    halves = as_halves(source, src_where)
    for i, h in enumerate(halves):
        check_given_statistics(h, src_where, f"halves[{i}]", need_samples=False)
    la, lb = layout_of(halves.a.features), layout_of(halves.b.features)
    if la != lb:  # the same names and components, in any order
        fmt = lambda lay: ",".join(f"{n}({k})" for n, k in sorted(lay.items())) or "none"  # noqa: E731
        raise InputError(src_where, "halves", f"the halves differ in features: {fmt(la)} vs {fmt(lb)}; "
                         "give both halves the same features")
    check_method_supply(method, Supply(what, halves=True, subpixels=halves.a.subpixels,
                                       has_range=halves.a.has_range, features=tuple(halves.a.feature_names),
                                       surface=surface), m_where)
    return halves.without_features() if req.features == "none" else halves


def gather_inputs(source, method: Method, *, nonfinite: str = "drop", reference=None, where: str | None = None,
                  logs: bool = True, what: str | None = None, surface: str = "python",
                  merged: bool = True, window=None) -> MethodInputs:
    """The inputs ``method`` declares, read from ``source``: the one place a source becomes MethodInputs.

    Parameters
    ----------
    source : path-like, SampleLog, SampleSet, PixelStats, Halves or (PixelStats, PixelStats)
        A sample log is streamed into statistics (with the subpixel grid the
        method asks for) and handed over as the sample source of methods
        that filter samples; pixel statistics cannot serve those.  A
        half-buffer pair (two independent halves of the samples, a tuple of
        two PixelStats or :class:`~mcrecon.core.halves.Halves`) is for
        methods with ``requires.half_buffers``: handed over as
        ``inputs.halves``, with ``inputs.stats`` their merge.  For a method
        that reads the samples and takes half buffers, the samples come
        with their split (:func:`statistics_for`).  Pixel statistics and
        halves the caller gives are checked (:func:`check_given_statistics`).
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
    what, surface : str, optional
        How refusals name in-memory statistics read from files, and the
        wording of their fixes (:class:`~mcrecon.methods.supply.Supply`).
    merged : bool
        False: halves split from samples come without their merge
        (``stats`` None; :func:`statistics_for`).
    window : (y0, y1, x0, x1), optional
        For a sample source: the inputs of those pixels of the film only
        (statistics, halves, prefix halves and reference), each the film's
        cropped to the window, bit for bit, from one pass over the whole
        source (:func:`statistics_for`); the memory of the window.  The
        samples handed to a method that reads them are the whole source's.
    """
    src_where = where or "reconstruct"
    m_where = where or method.where
    check_policy(nonfinite, src_where)
    req = method.requires
    halves = strata = None
    if is_half_buffer_pair(source):
        halves = _given_halves(source, method, src_where, m_where, what or "the half buffers", surface)
        stats, samples, stored_ref = halves.merged(), None, None
        check_given_statistics(stats, src_where, "halves")
    elif isinstance(source, PixelStats):
        check_method_supply(method, Supply(what or "one set of pixel statistics", subpixels=source.subpixels,
                                           has_range=source.has_range, features=tuple(source.feature_names),
                                           surface=surface, logs=logs), m_where)
        check_given_statistics(source, src_where)
        stats, samples, stored_ref = _fit_features(source, req), None, None
    else:
        if logs and isinstance(source, (str, Path)):
            from ..io import read_log
            source = read_log(source)
        if not (hasattr(source, "round_slices") and hasattr(source, "iter_chunks")) or \
                not (logs or isinstance(source, SampleSet)):
            kinds = "a sample log path, a SampleLog, a SampleSet, PixelStats" if logs else \
                "PixelStats (PixelStats.from_moments / from_samples), a mcrecon.SampleSet"
            raise InputError(src_where, "source", f"got {type(source).__name__}; expected {kinds} or a "
                             "half-buffer pair (stats_a, stats_b)")
        n = getattr(source, "n_samples", None)
        check_method_supply(method, Supply(source_name(source), samples=True, subpixels=-1,
                                           features=tuple(getattr(source, "feature_names", ())),
                                           n_samples=int(n) if n is not None else None, surface=surface,
                                           logs=logs), m_where)
        # the prefix halves follow the samples in their stored order (each pixel's sequence order), filled by
        # the statistics' pass over them (a pass of their own only for a method that reads no statistics)
        strata = PrefixHalves(source.width, source.height, len(source.channels), window=window) \
            if req.prefix_halves else None
        stats, halves = statistics_for(source, req, nonfinite=nonfinite, merged=merged, strata=strata, window=window)
        if strata is not None and stats is None and halves is None:
            strata = prefix_halves_of(source)
            if window is not None:
                strata = strata.crop(*window)
        stored_ref = source.reference() if req.reference != "none" and hasattr(source, "reference") else None
        samples = source if req.samples else None
    shape = stats.shape if stats is not None else halves.shape if halves is not None else \
        (samples.height, samples.width, len(samples.channels))
    ref = reference if reference is not None else stored_ref
    if window is not None:
        if not hasattr(source, "iter_chunks"):
            raise InputError(src_where, "window", "a window of the film is read from a sample source (a log or a "
                             "SampleSet); crop statistics or half buffers given in memory instead")
        y0, y1, x0, x1 = window
        film = (source.height, source.width, len(source.channels))
        if ref is not None:
            ref = check_reference(ref, film, **({"where": f"{where}: reference"} if where else {}))[y0:y1, x0:x1]
        if stats is None and halves is None:
            shape = (y1 - y0, x1 - x0, film[2])
    ref = check_reference(ref, shape, **({"where": f"{where}: reference"} if where else {}))
    return MethodInputs(stats, samples, ref if req.reference != "none" else None, nonfinite, halves, strata)

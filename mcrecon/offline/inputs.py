"""The one input dispatcher: a source (log path, SampleLog, SampleSet, PixelStats, half-buffer
pair) into the :class:`~mcrecon.methods.MethodInputs` a method declares.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..methods.base import Method
from ..methods.base import MethodInputs, half_buffer_methods
from ..core.halves import SplitHalves, check_half_buffers, is_half_buffer_pair, merge_halves
from ..core.samples import SampleSet, check_policy, check_reference, source_name
from ..core.stats import PixelStats





__all__ = ['gather_inputs', 'check_given_statistics', 'statistics_for', 'check_method', 'pixel_stats_options']

def statistics_for(source, req, *, nonfinite: str = "drop"):
    """``(stats, halves)`` of a sample source for a method's requirements ``req``.

    A method that reads the samples *and* takes half buffers splits the
    samples into two halves anyway (:func:`mcrecon.core.halves.split_halves`):
    for it one pass builds the halves, handed over as a
    :class:`~mcrecon.core.halves.SplitHalves` of ``source``, and the
    statistics of all the samples are their Chan merge (equal to
    accumulating every sample to a few ulps; auto at 1024^2: -0.45 s).
    Otherwise the statistics (if declared) and no halves.
    """
    # every feature the method can accumulate ((N,) or (N, k) per sample); others are ignored
    from ..core.features import usable_names
    features = usable_names(source) if req.features != "none" else ()
    if req.samples and req.half_buffers and req.statistics and not req.subpixels:
        from ..core.halves import split_halves
        split = split_halves(source, nonfinite=nonfinite, features=features)
        return merge_halves(split.a, split.b), SplitHalves(split.a, split.b, source)
    stats = PixelStats.from_source(source, subpixels=req.subpixels, nonfinite=nonfinite, features=features) \
        if req.statistics else None
    return stats, None


def check_features_for(method: Method, features: tuple, where: str, source_kind: str) -> None:
    """Refuse a source without features for a method that requires them (naming the fix)."""
    if method.requires.features == "required" and not features:
        raise InputError(where, "features", f"{method.name} needs per-sample features (albedo, normal, depth) and "
                         f"{source_kind} has none; write them into the log (/features/NAME), pass "
                         "SampleSet(features=...) or PixelStats.from_moments(features=...), or pick another method")


def fit_features(stats: PixelStats | None, req):
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
                             "statistics of all the samples: mcrecon.core.halves.merge_halves(a, b))")
        halves = check_half_buffers(source, src_where)
        if req.subpixels and halves[0].subpixels != req.subpixels:
            raise InputError(m_where, "halves", f"this configuration needs a {req.subpixels}x"
                             f"{req.subpixels} subpixel grid, got subpixels={halves[0].subpixels}")
        for i, h in enumerate(halves):
            check_given_statistics(h, src_where, f"halves[{i}]", need_samples=False)
        from ..core.features import layout_of
        la, lb = layout_of(halves[0].features), layout_of(halves[1].features)
        if la != lb:  # the same names and components, in any order
            fmt = lambda lay: ",".join(f"{n}({k})" for n, k in sorted(lay.items())) or "none"
            raise InputError(src_where, "halves", f"the halves differ in features: {fmt(la)} vs {fmt(lb)}; "
                             "give both halves the same features")
        check_features_for(method, halves[0].feature_names, m_where, "the half buffers")
        halves = (fit_features(halves[0], req), fit_features(halves[1], req))
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
        check_features_for(method, source.feature_names, m_where, "these pixel statistics")
        stats, samples, stored_ref = fit_features(source, req), None, None
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
        check_features_for(method, tuple(getattr(source, "feature_names", ())), m_where, source_name(source))
        stats, halves = statistics_for(source, req, nonfinite=nonfinite)
        stored_ref = source.reference() if req.reference != "none" and hasattr(source, "reference") else None
        samples = source if req.samples else None
    shape = stats.shape if stats is not None else (samples.height, samples.width, len(samples.channels))
    ref = check_reference(reference if reference is not None else stored_ref, shape,
                          **({"where": f"{where}: reference"} if where else {}))
    return MethodInputs(stats, samples, ref if req.reference != "none" else None, nonfinite, halves)


# ------------------------------------------------------------------ methods
def check_method(method, where: str = "pixel statistics", *, half_buffers: bool = False) -> None:
    """Refuse, with the reason, a method that cannot run on statistics read from an EXR.

    ``half_buffers``: the statistics come as a half-buffer pair (two EXRs
    of independent halves), which methods declaring
    ``requires.half_buffers`` take in place of the samples.
    """
    req = method.requires
    if half_buffers and not req.half_buffers:
        from ..methods.base import half_buffer_methods

        raise InputError(method.where, "--half-buffer", f"{method.name} does not use half buffers; methods that "
                         f"do: {', '.join(half_buffer_methods()) or '(none)'} (for {method.name}, give one EXR of "
                         "all the samples)")
    if req.samples and req.half_buffers and not half_buffers:
        raise InputError(method.where, "input", f"{method.name} (these options) needs the individual samples or "
                         f"two independent half buffers, which one pixel-statistics EXR ({where}) does not hold; "
                         "give the other half with --half-buffer B.exr, or a sample log"
                         + (", or use --candidates box,gauss (the SURE candidates)" if method.name == "auto"
                            else ""))
    if req.samples and not req.half_buffers:
        raise InputError(method.where, "input", f"{method.name} filters individual samples (their film "
                         f"positions and values), which a pixel-statistics EXR ({where}) does not hold; give it "
                         "a sample log, or pick gem, awr, box or ci")
    if req.subpixels:
        raise InputError(method.where, "input", f"this {method.name} configuration needs per-subpixel sums on a "
                         f"{req.subpixels}x{req.subpixels} grid (subpixel_exact_below > 0), which a "
                         f"pixel-statistics EXR ({where}) does not hold; use --subpixel-exact-below 0 (the pixel "
                         "kernel) or a sample log")


def pixel_stats_options(name: str, given: dict, *, half_buffers: bool = False) -> tuple[dict, str | None]:
    """Options for method ``name`` on statistics without the sample range, and a note when changed.

    AWR's default ``variance='range'`` estimator needs each pixel's
    sample minimum and maximum; a pixel-statistics EXR has none, so when
    the user did not choose, ``variance='sample'`` (the sample variance)
    is used; a ``variance`` the user gave that needs the range is refused.

    ``auto``'s default candidates include dual-buffer ones (``nlm``),
    which need two halves of the samples: on one EXR (``half_buffers``
    False) and without ``candidates`` given, its SURE candidates
    (``box,gauss``) are used, with a note; candidates the user gave are
    kept (:func:`check_method` then refuses dual-buffer ones, suggesting
    ``--half-buffer``).
    """
    opts = dict(given)
    if name == "auto" and not half_buffers and "candidates" not in opts:
        from ..methods import method_class
        from ..methods.auto.method import DUAL_BUFFER

        default = str(next(o.default for o in method_class("auto").options if o.name == "candidates"))
        kept = [c.strip() for c in default.split(",") if c.strip() and c.strip() not in DUAL_BUFFER]
        dropped = [c.strip() for c in default.split(",") if c.strip() in DUAL_BUFFER]
        if dropped:
            opts["candidates"] = ",".join(kept)
            many = len(dropped) > 1
            return opts, (f"auto: using --candidates {','.join(kept)} (its SURE candidates): the default "
                          f"candidate{'s' if many else ''} {','.join(dropped)} need{'' if many else 's'} two "
                          "independent halves of the samples, which one "
                          "pixel-statistics EXR does not hold; give the other half with --half-buffer B.exr")
    if name == "awr" and "variance" in opts and str(opts["variance"]) != "sample":
        raise InputError("method awr", "--variance", f"{opts['variance']!r} needs each pixel's sample minimum and "
                         "maximum, which a pixel-statistics EXR does not hold; use --variance sample (the default "
                         "for these inputs)")
    if name == "awr" and "variance" not in opts:
        opts["variance"] = "sample"
        return opts, ("awr: using --variance sample (the pixels' sample variance): the default 'range' "
                      "estimator needs per-pixel sample minima and maxima, which a pixel-statistics EXR lacks")
    return opts, None
